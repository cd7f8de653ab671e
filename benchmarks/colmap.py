"""Known-pose reconstruction end to end: pycolmap's own pipeline against episeg_cv's guided matching.

Issue 7. On a posed synthetic collection (``scenes.make_collection``: a room
with boxes, exact poses and depth, several baselines), from the same images
and the same known poses:

1. pycolmap: ``extract_features`` (one PINHOLE camera) -> ``match_exhaustive``
   (default verification) -> ``triangulate_points`` with the known poses;
2. ours, ``constraint="line"``, ``depth_range="none"`` -> ``colmap.triangulate``;
3. ours, ``constraint="segment"``, ``depth_range="none"``;
4. ours, ``constraint="segment"``, ``depth_range="auto"``.

Per method: 3D points, track lengths, reprojection error, the points within
1 % of depth of the rendered surface in every image of their track, matching
and total time. Then pairs/s of method 4 with 1 and 2 worker processes and a
local Dask cluster (checking identical matches), and the peak resident memory
of a matching run at two collection sizes, each measured in its own process.

Issue 14 adds a second part (``_colmap_sets.py``): the real dinoSparseRing
collection (Seitz et al., CVPR 2006; from ``<repo>/../shared/data``, or
``--data DIR``; skipped with a note when absent) and synthetic rooms, each
with pycolmap's pipeline, pycolmap's known-pose ``match_guided``, ours on
COLMAP's own features (``features="database"``) and ours end to end, with the
pair rule and the track consensus, under COLMAP's default triangulation and
with two-view tracks; the issue's goals evaluated from the numbers; and pairs/s
with 1 and 2 workers and a local Dask cluster on 24 views.

Usage::

    python benchmarks/colmap.py            # 12 views at 640x480, 5 repeats, workers, Dask, memory, dino + 2 rooms
    python benchmarks/colmap.py --quick    # 6 views at 480x360, 1 repeat, no Dask, memory at one size, dino (~2 min)

Writes ``benchmarks/results/colmap.{md,json}`` (``benchmarks/results/quick/`` with ``--quick``, git-ignored).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _colmap_sets as sets  # noqa: E402
from _common import machine_metadata, package_dirty  # noqa: E402

SCRIPT = "benchmarks/colmap.py"
RESULTS = Path(__file__).resolve().parent / "results"
MAX_FEATURES = 8192
ACCURACY = 0.01  # |z_true - z| <= ACCURACY * z
FULL = {"n_views": 12, "image_size": (640, 480), "repeats": 5, "dask": True, "memory_views": (12, 24),
        "memory_workers": (1, 2), "sets": ["dino", [12, 7], [10, 3]], "parallel_views": 24, "parallel_repeats": 3}
QUICK = {"n_views": 6, "image_size": (480, 360), "repeats": 1, "dask": False, "memory_views": (6,),
         "memory_workers": (1,), "sets": ["dino"], "parallel_views": 0, "parallel_repeats": 0}
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"  # <repo>/../shared/data
SEED = 7
OURS = {  # label -> (constraint, depth_range, ratio; None: the library's default)
    "ours, line": ("line", "none", None),
    "ours, segment": ("segment", "none", None),
    "ours, segment + auto depth": ("segment", "auto", None),
    "ours, segment + auto depth, ratio 0.75": ("segment", "auto", 0.75),
}
PYCOLMAP = "pycolmap"
METHODS = [PYCOLMAP, *OURS]


def progress(msg: str) -> None:
    print(f"[colmap bench {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _pycolmap():
    import pycolmap

    pycolmap.logging.minloglevel = 2
    return pycolmap


# --------------------------------------------------------------------------------------
# pycolmap's own known-pose pipeline
# --------------------------------------------------------------------------------------
def _pycolmap_extract(paths, names, camera_params, database, max_features):
    pycolmap = _pycolmap()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(repr(float(p)) for p in camera_params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = max_features
    pycolmap.extract_features(str(database), str(paths["images"]), image_names=list(names),
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)


def _pycolmap_match(database, threads=-1):
    pycolmap = _pycolmap()
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    pycolmap.match_exhaustive(str(database), matching_options=matching, device=pycolmap.Device.cpu)


def _known_pose_reconstruction(database, views):
    """The known poses as a Reconstruction with the database's camera, rig, frame and image ids."""
    pycolmap = _pycolmap()
    by_name = {v.name: v for v in views}
    db = pycolmap.Database.open(str(database))
    try:
        cameras = db.read_all_cameras()
        images = db.read_all_images()
        frames = db.read_all_frames()
    finally:
        db.close()
    if len(cameras) != 1:
        raise RuntimeError(f"expected one camera in {database}, found {len(cameras)}")
    for f in frames:  # add_image_with_trivial_frame uses frame id = image id; the database must agree
        ids = [d.id for d in f.data_ids]
        if ids != [f.frame_id]:
            raise RuntimeError(f"frame {f.frame_id} of {database} holds data ids {ids}, not its own id")
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(cameras[0])
    for im in sorted(images, key=lambda im: im.image_id):
        v = by_name[im.name]
        rec.add_image_with_trivial_frame(pycolmap.Image(name=im.name, camera_id=cameras[0].camera_id,
                                                        image_id=im.image_id))
        rec.frame(im.image_id).rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(v.R), v.t)
        rec.register_frame(im.image_id)
    return rec


def run_pycolmap(paths, views, work: Path, max_features: int) -> dict:
    pycolmap = _pycolmap()
    work.mkdir(parents=True, exist_ok=True)
    database = work / "pycolmap.db"
    names = [v.name for v in views]
    t0 = time.perf_counter()
    _pycolmap_extract(paths, names, views[0].camera_params, database, max_features)
    t1 = time.perf_counter()
    shutil.copyfile(database, work / "pycolmap_features_only.db")  # for the single-thread matching run
    t2 = time.perf_counter()
    _pycolmap_match(database)
    t3 = time.perf_counter()
    rec = _known_pose_reconstruction(database, views)
    (work / "pycolmap_tri").mkdir(exist_ok=True)
    rec = pycolmap.triangulate_points(rec, str(database), str(paths["images"]), str(work / "pycolmap_tri"))
    t4 = time.perf_counter()
    out = {"seconds_features": t1 - t0, "seconds_matching": t3 - t2, "seconds_triangulation": t4 - t3,
           "seconds_total": (t1 - t0) + (t4 - t2), "n_pairs": len(views) * (len(views) - 1) // 2}
    out.update(_database_counts(database))
    return {"stats": out, "reconstruction": rec, "database": database}


# --------------------------------------------------------------------------------------
# Ours
# --------------------------------------------------------------------------------------
def run_ours(paths, work: Path, tag: str, constraint: str, depth_range: str, max_features: int,
             workers: int | None = None, scheduler=None, cache_dir=None, triangulate: bool = True,
             ratio=None) -> dict:
    from episeg_cv import colmap
    from episeg_cv.features import PRESETS

    work.mkdir(parents=True, exist_ok=True)
    database = work / f"{tag}.db"
    cache = Path(cache_dir) if cache_dir is not None else work / f"{tag}.features"
    warnings = []
    t0 = time.perf_counter()
    report = colmap.match_model(paths["model"], paths["images"], database, constraint=constraint,
                                depth_range=depth_range, workers=workers, scheduler=scheduler,
                                features=PRESETS["collection"].replace(max_features=max_features), overwrite=True,
                                cache_dir=cache,
                                log=warnings.append, **({} if ratio is None else {"ratio": ratio}))
    t1 = time.perf_counter()
    rec = None
    t2 = t1
    if triangulate:
        rec = colmap.triangulate(database, paths["model"], paths["images"], work / f"{tag}_tri")
        t2 = time.perf_counter()
    out = {"seconds_features": report.seconds_features, "seconds_matching": report.seconds_matching,
           "seconds_match_model": t1 - t0, "seconds_triangulation": t2 - t1, "seconds_total": t2 - t0,
           "n_pairs": report.n_pairs, "n_pairs_done": report.n_pairs_done, "pairs_per_second": report.pairs_per_second,
           "runner": report.runner,
           "search_length": {k: float(v) for k, v in getattr(report, "search_length", {}).items()},
           "report_matches": report.n_matches,
           "report_inliers": report.n_inliers, "warnings": warnings,
           "depth_ranges": {k: list(v) for k, v in report.depth_ranges.items()}}
    out.update(_database_counts(database))
    return {"stats": out, "reconstruction": rec, "database": database, "cache": cache}


def _database_counts(database) -> dict:
    """Keypoints per image (by name), raw matches and verified inlier matches summed over pairs."""
    from episeg_cv import colmap

    pycolmap = _pycolmap()
    db = pycolmap.Database.open(str(database))
    try:
        keypoints = {im.name: int(db.num_keypoints_for_image(im.image_id)) for im in db.read_all_images()}
    finally:
        db.close()
    pairs = colmap.read_database_matches(database)
    return {"keypoints": dict(sorted(keypoints.items())),
            "matches": int(sum(len(m) for m, _ in pairs.values())),
            "inliers": int(sum(len(i) for _, i in pairs.values())),
            "verified_pairs": int(sum(len(i) > 0 for _, i in pairs.values()))}


# --------------------------------------------------------------------------------------
# Quality of a triangulated model against the rendered depth
# --------------------------------------------------------------------------------------
def quality(rec, collection) -> dict:
    """Point counts, track lengths, reprojection error, and accuracy against the true depth.

    A point is checked in an image by projecting it with the true pose and
    comparing its depth ``z`` in that camera with the rendered depth at the
    rounded pixel: accurate there if ``|z_true - z| <= 0.01 z``. ``accurate``
    requires this in every image of the point's track; ``accurate_first``
    only in the first image of the track (COLMAP's track order).
    """
    index = {name: k for k, name in enumerate(collection.names)}
    image_k = {iid: index[im.name] for iid, im in rec.images.items()}
    w, h = collection.image_size
    K = collection.K
    n = len(rec.points3D)
    lengths = np.zeros(n, int)
    ok_all = np.zeros(n, bool)
    ok_first = np.zeros(n, bool)
    obs_total = obs_ok = 0
    for p, pt in enumerate(rec.points3D.values()):
        ks = [image_k[el.image_id] for el in pt.track.elements]
        lengths[p] = len(ks)
        Xc = np.einsum("kij,j->ki", collection.R[ks], pt.xyz) + collection.t[ks]
        z = Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (Xc @ K.T)[:, :2] / z[:, None]
        good = np.zeros(len(ks), bool)
        for m, k in enumerate(ks):
            if z[m] <= 0 or not np.all(np.isfinite(uv[m])):
                continue
            x, y = int(np.rint(uv[m, 0])), int(np.rint(uv[m, 1]))
            if 0 <= x < w and 0 <= y < h:
                zt = collection.depths[k][y, x]
                good[m] = np.isfinite(zt) and abs(zt - z[m]) <= ACCURACY * z[m]
        ok_all[p], ok_first[p] = good.all(), good[0]
        obs_total += len(ks)
        obs_ok += int(good.sum())
    long = lengths >= 3
    return {
        "points": n,
        "points_track_ge_3": int(long.sum()),
        "mean_track_length": float(lengths.mean()) if n else 0.0,
        "mean_reprojection_error": float(rec.compute_mean_reprojection_error()) if n else float("nan"),
        "accurate": int(ok_all.sum()),
        "accurate_fraction": float(ok_all.mean()) if n else float("nan"),
        "accurate_first": int(ok_first.sum()),
        "accurate_first_fraction": float(ok_first.mean()) if n else float("nan"),
        "accurate_track_ge_3": int((ok_all & long).sum()),
        "observations": int(obs_total),
        "observations_accurate_fraction": obs_ok / obs_total if obs_total else float("nan"),
    }


# --------------------------------------------------------------------------------------
# Parallel runners (method 4)
# --------------------------------------------------------------------------------------
def same_matches(a: dict, b: dict) -> dict:
    keys = set(a) | set(b)
    missing = sorted(f"{p[0]}-{p[1]}" for p in keys if (p in a) != (p in b))
    differ = sorted(f"{p[0]}-{p[1]}" for p in set(a) & set(b)
                    if not (np.array_equal(a[p][0], b[p][0]) and np.array_equal(a[p][1], b[p][1])))
    return {"identical": not missing and not differ, "pairs_missing_or_extra": missing, "pairs_differing": differ}


def parallel_once(paths, work: Path, tag: str, reference: dict, cache, **runner) -> tuple[dict, bool]:
    """Method 4 once on a runner (features from ``cache``, matching only); ``(entry, correct)``."""
    from episeg_cv import colmap

    constraint, depth_range, _ = OURS["ours, segment + auto depth"]
    try:
        res = run_ours(paths, work, tag, constraint, depth_range, MAX_FEATURES, cache_dir=cache,
                       triangulate=False, **runner)
    except Exception as e:  # noqa: BLE001 - recorded in the report
        return {"error": f"{type(e).__name__}: {e}"}, False
    s = res["stats"]
    check = same_matches(reference, colmap.read_database_matches(res["database"]))
    entry = {"seconds_matching": s["seconds_matching"], "pairs_per_second": s["pairs_per_second"],
             "n_pairs": s["n_pairs"], "n_pairs_done": s["n_pairs_done"], "runner": s["runner"], **check}
    return entry, check["identical"] and s["n_pairs_done"] == s["n_pairs"]


def run_parallel(paths, work: Path, reference_db, cache, features_only_db, repeats: int, dask: bool) -> dict:
    """Pairs/s of method 4 on 1 and 2 workers and a local Dask cluster, and of pycolmap's matcher on 1 and 2 threads.

    Each runner is first run once untimed (a failure is recorded, not
    raised); the timed runs are interleaved: every repeat runs every runner
    once, so that they share the machine's load. Every run's matches are
    compared with ``reference_db``.
    """
    from episeg_cv import colmap

    work.mkdir(parents=True, exist_ok=True)
    reference = colmap.read_database_matches(reference_db)
    runners = {"workers=1": {"workers": 1}, "workers=2": {"workers": 2}}
    if dask:
        runners["Dask local:2"] = {"scheduler": "local:2"}
    out = {label: {"label": label, "first": None, "runs": []} for label in runners}
    for label, kw in runners.items():
        entry, ok = parallel_once(paths, work, f"asis_{label.replace(' ', '_').replace(':', '')}", reference,
                                  cache, **kw)
        out[label]["first"] = entry
        out[label]["first_ok"] = ok
        progress(f"  {label}, first (untimed) run: " + (entry.get("error") or
                 f"{entry['pairs_per_second']:.1f} pairs/s, identical={entry['identical']}, "
                 f"{entry['n_pairs_done']}/{entry['n_pairs']} pairs"))
    pycolmap_threads = {"threads=1": 1, "threads=2 (default -1: all cores)": -1}
    pc = {label: [] for label in pycolmap_threads}
    for r in range(repeats):
        for label, kw in runners.items():
            p = out[label]
            entry, _ = parallel_once(paths, work, f"r{r}_{label.replace(' ', '_').replace(':', '')}", reference,
                                     cache, **kw)
            p["runs"].append(entry)
        for label, threads in pycolmap_threads.items():
            db = work / f"pycolmap_{threads}_{r}.db"
            shutil.copyfile(features_only_db, db)
            t0 = time.perf_counter()
            _pycolmap_match(db, threads)
            pc[label].append(time.perf_counter() - t0)
        progress(f"  repeat {r + 1}/{repeats}: " + ", ".join(
            f"{label} {p['runs'][-1].get('pairs_per_second', float('nan')):.1f}" for label, p in out.items())
            + " pairs/s (ours); pycolmap " + ", ".join(f"{k} {v[-1]:.2f} s" for k, v in pc.items()))
    for p in out.values():
        done = [e for e in p["runs"] if "error" not in e]
        if done:
            p["pairs_per_second_median"] = _median([e["pairs_per_second"] for e in done])
            p["pairs_per_second_max"] = max(e["pairs_per_second"] for e in done)
            p["seconds_matching_median"] = _median([e["seconds_matching"] for e in done])
            p["seconds_matching_min"] = min(e["seconds_matching"] for e in done)
            p["identical"] = all(e["identical"] for e in done)
            p["n_pairs"] = done[0]["n_pairs"]
    return out, pc


# --------------------------------------------------------------------------------------
# Peak memory, one process per measurement
# --------------------------------------------------------------------------------------
def _maxrss_mib(who) -> float:
    return resource.getrusage(who).ru_maxrss / 1024.0  # Linux: KiB


def _status_mib(pid="self", key="VmHWM") -> float | None:
    """``VmHWM`` (peak resident set of this process image) or ``VmRSS`` from ``/proc/<pid>/status``, MiB."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        pass
    return None


class _WorkerSampler:
    """Every 20 ms: the peak (``VmHWM``) of every descendant process, and the summed ``VmRSS`` of all."""

    def __init__(self, interval: float = 0.02):
        import threading

        import psutil

        self._me, self.interval = psutil.Process(), interval
        self.worker_peak: dict[int, float] = {}
        self.total_peak = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        import psutil

        while not self._stop.is_set():
            total = _status_mib("self", "VmRSS") or 0.0
            try:
                children = self._me.children(recursive=True)
            except psutil.Error:
                children = []
            for c in children:
                hwm, rss = _status_mib(c.pid), _status_mib(c.pid, "VmRSS")
                if hwm is not None:
                    self.worker_peak[c.pid] = max(self.worker_peak.get(c.pid, 0.0), hwm)
                total += rss or 0.0
            self.total_peak = max(self.total_peak, total)
            self._stop.wait(self.interval)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def child_main(folder: str, method: str, workers: int) -> int:
    """Run one matching job in this fresh process and print its peak memory as JSON.

    The driver's peak is ``VmHWM`` of this process image. ``ru_maxrss`` is
    reported too, but on Linux it is carried over ``execve`` from the forked
    parent, so in a child of a large process it holds the parent's size.
    """
    from episeg_cv import colmap
    from episeg_cv.features import PRESETS

    _pycolmap()
    paths = {"images": Path(folder) / "images", "model": Path(folder) / "model"}
    work = Path(tempfile.mkdtemp(prefix="mem_", dir=folder))
    base = _status_mib()
    t0 = time.perf_counter()
    with _WorkerSampler() as sampler:
        if method == "pycolmap":
            views, _ = colmap.load_model(paths["model"])
            _pycolmap_extract(paths, [v.name for v in views], views[0].camera_params, work / "db.db", MAX_FEATURES)
            _pycolmap_match(work / "db.db")
            n_pairs = len(views) * (len(views) - 1) // 2
        else:
            report = colmap.match_model(paths["model"], paths["images"], work / "db.db", constraint="segment",
                                        depth_range="auto", workers=workers,
                                        features=PRESETS["collection"].replace(max_features=MAX_FEATURES),
                                        cache_dir=work / "features", overwrite=True, log=lambda m: None)
            n_pairs = report.n_pairs_done
    seconds = time.perf_counter() - t0
    peak = _status_mib()
    print(json.dumps({"peak_after_imports_mib": base, "peak_driver_mib": peak,
                      "peak_largest_worker_mib": max(sampler.worker_peak.values(), default=None),
                      "worker_processes_seen": len(sampler.worker_peak),
                      "peak_total_rss_sampled_mib": max(sampler.total_peak, peak or 0.0),
                      "ru_maxrss_self_mib": _maxrss_mib(resource.RUSAGE_SELF),
                      "ru_maxrss_children_mib": _maxrss_mib(resource.RUSAGE_CHILDREN),
                      "pairs": n_pairs, "seconds": seconds}))
    shutil.rmtree(work, ignore_errors=True)
    return 0


def measure_memory(folder: Path, method: str, workers: int) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(folder), method, str(workers)]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    if out.returncode != 0:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr.strip() else f"exit {out.returncode}"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_parallel_child(model: Path, images: Path, work: Path, repeats: int, dask: bool) -> dict:
    """:func:`_colmap_sets.run_parallel` in a fresh process, as a user's ``episeg colmap`` runs: this
    process holds every earlier part's results, and in a process holding 3 M more Python objects a Dask
    run's matching took 0.07 s longer (0.93 -> 1.00 s on 24 views, scratch), one worker's not."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--parallel-child", str(model), str(images), str(work),
           str(repeats), str(int(dask))]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=3600)
    if out.returncode != 0:
        raise RuntimeError(f"parallel runs failed: {out.stderr.strip()[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


# --------------------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------------------
def _median(xs):
    return statistics.median(xs) if xs else float("nan")


def run_sets(cfg: dict, work: Path, data_dir: Path) -> dict:
    """Part 2 (issue 14): every method on dino and the synthetic rooms; pairs/s on 24 views."""
    from episeg_cv import colmap, scenes

    out = {"sets": {}, "data_dir": str(data_dir), "workers": os.cpu_count() or 1}
    for spec in cfg["sets"]:
        if spec == "dino":
            folder = sets.find_dino(data_dir)
            if folder is None:
                out["dino_missing"] = True
                progress(f"NOTE: dinoSparseRing not found under {data_dir}; the real collection is skipped "
                         "(--data DIR)")
                continue
            model = folder / sets.DINO_PAR
            views = colmap.load_par(model, folder)
            masks = sets.dino_masks(folder, [v.name for v in views])
            name, image_dir = "dinoSparseRing (real)", folder
            quality_fn = lambda rec, views=views, masks=masks: sets.dino_quality(rec, views, masks)  # noqa: E731
        else:
            n, seed = spec
            c = scenes.make_collection(n, cfg["image_size"], seed=seed)
            paths = colmap.save_collection(c, work / f"set_room{n}_s{seed}")
            model, image_dir = paths["model"], paths["images"]
            views, _ = colmap.load_model(model)
            name = f"room, {n} views, seed {seed} (synthetic)"
            quality_fn = lambda rec, c=c: quality(rec, c)  # noqa: E731
        progress(f"part 2: {name}")
        out["sets"][name] = sets.run_set(name, model, image_dir, views, quality_fn, work / f"set_{len(out['sets'])}",
                                         MAX_FEATURES, out["workers"])
    if cfg["parallel_views"]:
        n = cfg["parallel_views"]
        paths = colmap.save_collection(scenes.make_collection(n, cfg["image_size"], seed=SEED), work / f"par_{n}")
        progress(f"part 2: parallel runs on {n} views")
        out["parallel"] = run_parallel_child(paths["model"], paths["images"], work / "parallel24",
                                             cfg["parallel_repeats"], cfg["dask"])
        out["parallel"]["n_views"] = n
    return out


def run(cfg: dict, work: Path) -> dict:
    from episeg_cv import colmap, scenes

    pycolmap = _pycolmap()
    n, size, repeats = cfg["n_views"], cfg["image_size"], cfg["repeats"]
    t = time.perf_counter()
    collection = scenes.make_collection(n, size, seed=SEED)
    paths = colmap.save_collection(collection, work / f"collection_{n}")
    views, model = colmap.load_model(paths["model"])
    model_check = quality(model, collection)  # the accuracy test on exact points: should be 100 %
    progress(f"rendered and saved {n} views at {size[0]}x{size[1]} in {time.perf_counter() - t:.1f} s "
             f"({len(model.points3D)} model points for depth_range='auto')")

    # 1. the four methods, interleaved; the order rotates between repeats
    runs = {m: [] for m in METHODS}
    first = {}
    for r in range(repeats):
        order = METHODS[r % len(METHODS):] + METHODS[:r % len(METHODS)]
        for m in order:
            rw = work / f"run{r}"
            if m == PYCOLMAP:
                res = run_pycolmap(paths, views, rw, MAX_FEATURES)
            else:
                constraint, depth_range, ratio = OURS[m]
                res = run_ours(paths, rw, m.replace(", ", "_").replace(" ", "_").replace("+", ""),
                               constraint, depth_range, MAX_FEATURES, ratio=ratio)
            q = quality(res["reconstruction"], collection)
            s = res["stats"]
            runs[m].append({**{k: v for k, v in s.items() if k not in ("keypoints", "depth_ranges")}, **q})
            if r == 0:
                first[m] = res
            progress(f"repeat {r + 1}/{repeats} {m}: {q['points']} points, {q['accurate']} accurate "
                     f"({100 * q['accurate_fraction']:.1f} %), matching {s['seconds_matching']:.2f} s, "
                     f"total {s['seconds_total']:.2f} s")

    methods = {}
    for m in METHODS:
        rr = runs[m]
        methods[m] = {
            "quality": {k: rr[0][k] for k in quality_keys()},
            "accurate_min_max": [min(x["accurate"] for x in rr), max(x["accurate"] for x in rr)],
            "points_min_max": [min(x["points"] for x in rr), max(x["points"] for x in rr)],
            "seconds_features_median": _median([x["seconds_features"] for x in rr]),
            "seconds_matching_median": _median([x["seconds_matching"] for x in rr]),
            "seconds_triangulation_median": _median([x["seconds_triangulation"] for x in rr]),
            "seconds_total_median": _median([x["seconds_total"] for x in rr]),
            "seconds_matching_min": min(x["seconds_matching"] for x in rr),
            "seconds_total_min": min(x["seconds_total"] for x in rr),
            "pairs_per_second_median": _median([x["n_pairs"] / x["seconds_matching"] for x in rr]),
            "matches": rr[0]["matches"], "inliers": rr[0]["inliers"], "verified_pairs": rr[0]["verified_pairs"],
            "n_pairs": rr[0]["n_pairs"],
            "keypoints": first[m]["stats"]["keypoints"],
            "search_length": rr[0].get("search_length"),
            "warnings": rr[0].get("warnings", []),
            "runs": rr,
        }
    auto = first["ours, segment + auto depth"]["stats"]
    methods["ours, segment + auto depth"]["depth_ranges"] = auto["depth_ranges"]

    # 2. parallel runners for method 4 (same feature cache as its first run; reference = its first database)
    ref = first["ours, segment + auto depth"]
    progress("parallel runners (segment + auto depth) and pycolmap's matcher threads, interleaved")
    parallel, pc = run_parallel(paths, work / "parallel", ref["database"], ref["cache"],
                                work / "run0" / "pycolmap_features_only.db", repeats, cfg["dask"])
    n_pairs = n * (n - 1) // 2
    parallel_pycolmap = {k: {"seconds_matching": v, "seconds_matching_median": _median(v),
                             "seconds_matching_min": min(v), "pairs_per_second_median": n_pairs / _median(v),
                             "pairs_per_second_max": n_pairs / min(v)} for k, v in pc.items()}

    # 3. peak memory, a process per measurement
    memory = []
    for nv in cfg["memory_views"]:
        folder = work / f"collection_{nv}"
        if nv != n:
            t = time.perf_counter()
            colmap.save_collection(scenes.make_collection(nv, size, seed=SEED), folder)
            progress(f"rendered and saved {nv} views for the memory runs in {time.perf_counter() - t:.1f} s")
        for method, workers in [("ours", w) for w in cfg["memory_workers"]] + [("pycolmap", 1)]:
            m = measure_memory(folder, method, workers)
            m.update({"views": nv, "pairs_total": nv * (nv - 1) // 2, "method": method, "workers": workers})
            memory.append(m)
            progress(f"memory {nv} views {method} workers={workers}: " + (m.get("error") or
                     f"driver {m['peak_driver_mib']:.0f} MiB, largest worker {_f(m['peak_largest_worker_mib'], 0)} MiB, "
                     f"all processes {m['peak_total_rss_sampled_mib']:.0f} MiB"))
    return {"collection": {"n_views": n, "image_size": list(size), "seed": SEED, "pairs": n_pairs,
                           "model_points": len(model.points3D),
                           "model_points_accurate_fraction": model_check["accurate_fraction"], "focal_px": float(collection.K[0, 0]),
                           "depth_min_max": [float(min(np.min(d[np.isfinite(d)]) for d in collection.depths)),
                                             float(max(np.max(d[np.isfinite(d)]) for d in collection.depths))]},
            "methods": methods, "parallel": parallel, "parallel_pycolmap": parallel_pycolmap, "memory": memory,
            "pycolmap_version": pycolmap.__version__}


def quality_keys():
    return ("points", "points_track_ge_3", "mean_track_length", "mean_reprojection_error", "accurate",
            "accurate_fraction", "accurate_first", "accurate_first_fraction", "accurate_track_ge_3",
            "observations", "observations_accurate_fraction")


# --------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------
def _f(v, d=2):
    return "n/a" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{d}f}"


def _end_note(meta) -> str:
    end = meta.get("at_the_end") or {}
    if not end:
        return ""
    same = end.get("git_commit") == meta.get("git_commit") and \
        end.get("episeg_cv_uncommitted_changes") == meta.get("episeg_cv_uncommitted_changes")
    return " and at the end" if same else (f"; **the code changed during the run**: HEAD {end.get('git_commit')} at "
                                           f"the end, uncommitted changes {end.get('episeg_cv_uncommitted_changes')}")


def write_markdown(path: Path, res: dict) -> None:
    meta, col, M = res["machine"], res["collection"], res["methods"]
    reps = res["config"]["repeats"]
    L = ["# Known-pose reconstruction: pycolmap's pipeline against episeg_cv's guided matching\n"]
    dirty = ", with uncommitted changes in episeg_cv/" if meta.get("episeg_cv_uncommitted_changes") else ""
    L.append(f"Made by `{res['command']}` on {meta['date']} in {res['wall_time_s']:.0f} s ({meta['cpu']}, "
             f"{meta['cpu_count']} cores, {meta['platform']}, python {meta['python']}, numpy {meta['numpy']}, "
             f"cv2 {meta['cv2']}, pycolmap {res['pycolmap_version']}, episeg_cv {meta['episeg_cv']}, git HEAD "
             f"{meta['git_commit']} at the start{dirty}{_end_note(meta)}). Load average (1 min) {res['load_average'][0]:.2f} at the "
             f"start, {res['load_average'][1]:.2f} at the end. Raw numbers in `{path.stem}.json`.\n")
    L.append("## Setup\n")
    L.append(f"- Collection: `scenes.make_collection({col['n_views']}, ({col['image_size'][0]}, "
             f"{col['image_size'][1]}), seed={col['seed']})`, the room with boxes, exact poses and rendered depth "
             f"({col['depth_min_max'][0]:.2f}-{col['depth_min_max'][1]:.2f} m), focal {col['focal_px']:.0f} px; "
             f"all {col['pairs']} pairs matched by every method. Written with `colmap.save_collection` (PNG images, "
             f"a COLMAP model with {col['model_points']} 3D points sampled from the rendered depth, which is what "
             "`depth_range=\"auto\"` reads: **exact points, so the auto ranges are those of a perfect earlier "
             "model**, widened by the library's percentiles and 25 % margin).")
    L.append(f"- pycolmap: `extract_features` (fresh database, `CameraMode.SINGLE`, PINHOLE with the true "
             f"intrinsics, `sift.max_num_features={MAX_FEATURES}`, CPU, default threads = all cores), "
             "`match_exhaustive` (defaults: ratio 0.8, cross-check, geometric verification by RANSAC), "
             "`triangulate_points` into a Reconstruction holding the true poses with the database's image ids.")
    L.append(f"- Ours: `colmap.match_model(model, images, db, constraint=..., depth_range=..., "
             f"max_features={MAX_FEATURES})` on all cores, the default (OpenCV SIFT as the library sets it up, default ratio "
             f"{res['config']['ratio']}, the collection defaults `tol=\"auto\"` and the track consensus, fresh feature cache every run, so feature time is included), then `colmap.triangulate` (the same `pycolmap.triangulate_points`, default "
             "options).")
    L.append(f"- **Accurate point**: projected with the true pose into *every* image of its track, its depth `z` "
             f"in that camera is within {100 * ACCURACY:.0f} % of the rendered depth at the rounded pixel "
             "(`|z_true - z| <= 0.01 z`). `accurate (first image)` checks only the first image of the track. "
             f"Check of the test: the model's exact points (sampled from the depth) score "
             f"{100 * col['model_points_accurate_fraction']:.1f} %.")
    L.append(f"- Times: median of {reps} repeat(s), the four methods interleaved in each repeat (order rotated). "
             "Matching = `match_exhaustive` (matching + verification) for pycolmap, `MatchReport.seconds_matching` "
             "(matching + database writes) for ours. Total = features + matching + triangulation (for ours: wall "
             "time of `match_model` + `triangulate`). Quality numbers are from the first repeat; the min-max over "
             "repeats is given for the accurate points (pycolmap's RANSAC is randomised).\n")

    L.append("## Main table\n")
    L.append("| metric | " + " | ".join(METHODS) + " |")
    L.append("|---|" + "---:|" * len(METHODS))

    def row(label, fn):
        L.append(f"| {label} | " + " | ".join(fn(M[m]) for m in METHODS) + " |")

    def kp(m, f):
        return f"{f(list(m['keypoints'].values())):.0f}"

    row("keypoints per image, mean (min-max)",
        lambda m: f"{kp(m, np.mean)} ({kp(m, np.min)}-{kp(m, np.max)})")
    row("raw matches (all pairs)", lambda m: str(m["matches"]))
    row("verified / inlier matches", lambda m: str(m["inliers"]))
    row("pairs with inliers", lambda m: f"{m['verified_pairs']} / {m['n_pairs']}")
    row("3D points", lambda m: str(m["quality"]["points"]))
    row("points with track length >= 3", lambda m: str(m["quality"]["points_track_ge_3"]))
    row("mean track length", lambda m: _f(m["quality"]["mean_track_length"]))
    row("mean reprojection error (px)", lambda m: _f(m["quality"]["mean_reprojection_error"], 3))
    row("**accurate points** (all track images)", lambda m: f"**{m['quality']['accurate']}**")
    row("accurate fraction", lambda m: f"{100 * m['quality']['accurate_fraction']:.1f} %")
    row(f"accurate points, min-max over {reps} repeat(s)",
        lambda m: f"{m['accurate_min_max'][0]}-{m['accurate_min_max'][1]}")
    row("accurate points with track >= 3", lambda m: str(m["quality"]["accurate_track_ge_3"]))
    row("accurate (first image only)", lambda m: f"{m['quality']['accurate_first']} "
        f"({100 * m['quality']['accurate_first_fraction']:.1f} %)")
    row("observations within 1 %", lambda m: f"{100 * m['quality']['observations_accurate_fraction']:.1f} %")
    row("features (s)", lambda m: _f(m["seconds_features_median"]))
    row("**matching (s)**, median (min)", lambda m: f"**{_f(m['seconds_matching_median'])}** "
        f"({_f(m['seconds_matching_min'])})")
    row("triangulation (s)", lambda m: _f(m["seconds_triangulation_median"]))
    row("**total (s)**, median (min)", lambda m: f"**{_f(m['seconds_total_median'])}** ({_f(m['seconds_total_min'])})")
    row("matching, pairs/s (median)", lambda m: _f(m["pairs_per_second_median"], 1))
    def search(m):
        sl = m.get("search_length")
        if not sl or m is M[PYCOLMAP]:
            return ""
        key = "line" if m is M["ours, line"] else "segment" if m is M["ours, segment"] else "segment_in_depth_range"
        return f"{sl[key]:.0f}"

    row("search length per query in image 2 (px, `MatchReport.search_length`)", search)
    L.append("")

    L.append("Keypoints per image (the database's counts):\n")
    L.append("| image | pycolmap | ours (OpenCV SIFT) |")
    L.append("|---|---:|---:|")
    for name in M[PYCOLMAP]["keypoints"]:
        L.append(f"| {name} | {M[PYCOLMAP]['keypoints'][name]} | {M['ours, segment']['keypoints'].get(name, '')} |")
    L.append("")

    # workers table
    P = res["parallel"]
    L.append("## Workers and Dask (ours, segment + auto depth)\n")
    L.append(f"Same feature cache (method 4's first run) for every row; matching only (`seconds_matching`; for "
             f"pycolmap `match_exhaustive` on a copy of its features-only database). All rows interleaved in each of "
             f"{reps} repeat(s), in a separate phase after the main table (so their absolute times differ from "
             "it). `identical`: `colmap.read_database_matches` equal, pair by pair (matches and inliers), to the "
             "database of method 4 in the main table, in every run. 'first run': an extra, untimed run of each runner "
             "before the timed ones.\n")
    L.append("| runner | first run | pairs/s, median (best) | matching (s), median | identical to the main "
             "run |")
    L.append("|---|---|---:|---:|---|")
    for label, p in P.items():
        a = p["first"]
        first = (f"**fails**: `{a['error']}`" if "error" in a else
                 ("ok" if p["first_ok"] else
                  f"**wrong**: {a['n_pairs_done']}/{a['n_pairs']} pairs done, identical={a['identical']}"))
        errors = sum("error" in e for e in p["runs"])
        L.append(f"| ours, {label} | {first}{f' ({errors} timed runs failed)' if errors else ''} | "
                 f"{_f(p.get('pairs_per_second_median'), 1)} ({_f(p.get('pairs_per_second_max'), 1)}) | "
                 f"{_f(p.get('seconds_matching_median'))} | "
                 f"{'yes' if p.get('identical') else 'no' if 'identical' in p else 'n/a'} |")
    for label, p in res["parallel_pycolmap"].items():
        L.append(f"| pycolmap `match_exhaustive`, {label} | ok | {_f(p['pairs_per_second_median'], 1)} "
                 f"({_f(p['pairs_per_second_max'], 1)}) | {_f(p['seconds_matching_median'])} | (other matcher) |")
    L.append("")

    # memory
    L.append("## Peak memory\n")
    L.append("One fresh process per row (`--child` mode of this script), running features + matching into a new "
             "database (ours: `match_model`, segment + auto depth; pycolmap: `extract_features` + "
             "`match_exhaustive`, its threads in the same process). Driver: `VmHWM` (peak resident set) of the "
             "process from `/proc/self/status`, after the imports and at the end. Workers: the largest `VmHWM` of "
             "any worker process, and the peak of the summed resident sets of driver + workers, both sampled "
             "every 20 ms. (`ru_maxrss` is in the JSON but not used: on Linux it is carried over `execve` from the "
             "forked parent, so in these children it reports the benchmark process's own size.)\n")
    L.append("| views | pairs | method | workers | driver after imports (MiB) | driver peak (MiB) | "
             "largest worker peak (MiB) | all processes, peak sum (MiB) | run (s) |")
    L.append("|---:|---:|---|---:|---:|---:|---:|---:|---:|")
    for m in res["memory"]:
        name = "ours" if m["method"] == "ours" else "pycolmap (threads: all cores)"
        if "error" in m:
            L.append(f"| {m['views']} | {m['pairs_total']} | {name} | {m['workers']} | failed: `{m['error']}` "
                     "| | | | |")
            continue
        child = _f(m["peak_largest_worker_mib"], 0) if m["workers"] > 1 else "-"
        L.append(f"| {m['views']} | {m['pairs']} | {name} | {m['workers']} | {_f(m['peak_after_imports_mib'], 0)} | "
                 f"{_f(m['peak_driver_mib'], 0)} | {child} | {_f(m['peak_total_rss_sampled_mib'], 0)} | "
                 f"{m['seconds']:.1f} |")
    L.append("")

    L.append("## What the numbers say\n")
    L.extend(verdict(res))
    L.append("")
    if res.get("part2"):
        L.extend(sets.markdown(res["part2"]))
    path.write_text("\n".join(L) + "\n")


def verdict(res) -> list[str]:
    M = res["methods"]
    pc = M[PYCOLMAP]
    acc = {m: M[m]["quality"]["accurate"] for m in METHODS}
    best = max(acc, key=acc.get)
    out = []
    order = sorted(METHODS, key=lambda m: -acc[m])
    out.append(f"- **Accurate points**: most with {best} ({acc[best]}); ranking "
               + ", ".join(f"{m} {acc[m]} ({100 * M[m]['quality']['accurate_fraction']:.1f} %)" for m in order)
               + ".")
    for m in OURS:
        q = M[m]["quality"]
        ratio = M[m]["seconds_matching_median"] / pc["seconds_matching_median"]
        tot = M[m]["seconds_total_median"] / pc["seconds_total_median"]
        out.append(f"- {m}: {q['accurate'] - pc['quality']['accurate']:+d} accurate points against pycolmap "
                   f"({q['accurate'] / max(pc['quality']['accurate'], 1):.2f}x), "
                   f"{q['points'] - pc['quality']['points']:+d} points in all; matching time "
                   f"{ratio:.2f}x pycolmap's ({M[m]['seconds_matching_median']:.2f} s vs "
                   f"{pc['seconds_matching_median']:.2f} s; best runs {M[m]['seconds_matching_min']:.2f} s vs "
                   f"{pc['seconds_matching_min']:.2f} s, "
                   f"{M[m]['seconds_matching_min'] / pc['seconds_matching_min']:.2f}x), total time {tot:.2f}x "
                   f"(best runs {M[m]['seconds_total_min'] / pc['seconds_total_min']:.2f}x).")
    pp = res["parallel_pycolmap"]
    P = res["parallel"]
    one, two = (pp.get(k, {}).get("seconds_matching_median") for k in ("threads=1", "threads=2 (default -1: all cores)"))
    w1 = P["workers=1"].get("seconds_matching_median")
    if one and two and w1:
        out.append(f"- Same cores: in the main table both matched on all cores (their defaults). In the interleaved "
                   f"second phase, ours (segment + auto depth) on one core (workers=1) took {w1:.2f} s against "
                   f"pycolmap's matcher {one:.2f} s on one thread ({w1 / one:.2f}x) and {two:.2f} s on all cores "
                   f"({w1 / two:.2f}x).")
    s = M["ours, segment + auto depth"]
    goal_acc = s["quality"]["accurate"] > pc["quality"]["accurate"]
    goal_time = s["seconds_matching_median"] < pc["seconds_matching_median"]
    out.append(f"- Issue goal (more accurate 3D points than pycolmap's pipeline, at a fraction of its matching "
               f"time), for segment + auto depth: more accurate points: **{'yes' if goal_acc else 'no'}** "
               f"({s['quality']['accurate']} vs {pc['quality']['accurate']}; over the repeats "
               f"{s['accurate_min_max'][0]}-{s['accurate_min_max'][1]} vs "
               f"{pc['accurate_min_max'][0]}-{pc['accurate_min_max'][1]}); less matching time: "
               f"**{'yes' if goal_time else 'no'}** ({s['seconds_matching_median'] / pc['seconds_matching_median']:.2f}"
               f"x by the medians, {s['seconds_matching_min'] / pc['seconds_matching_min']:.2f}x by the best runs; "
               "on this noisy 2-core machine only a ratio well below 1 means a clear win).")
    frac = {m: M[m]["quality"]["accurate_fraction"] for m in METHODS}
    bf = max(frac, key=frac.get)
    out.append(f"- Accurate fraction: highest with {bf} ({100 * frac[bf]:.1f} %), lowest with "
               f"{min(frac, key=frac.get)} ({100 * min(frac.values()):.1f} %). Mean reprojection error: " + ", ".join(
                   f"{m} {M[m]['quality']['mean_reprojection_error']:.3f} px" for m in METHODS) + ".")
    kp_pc = np.mean(list(pc["keypoints"].values()))
    kp_us = np.mean(list(s["keypoints"].values()))
    top = max(max(pc["keypoints"].values()), max(s["keypoints"].values()))
    cap = "the cap binds neither" if top < MAX_FEATURES else "the cap is reached on some image"
    out.append(f"- The two SIFTs differ: with the same cap of {MAX_FEATURES}, pycolmap kept {kp_pc:.0f} keypoints per "
               f"image on average and OpenCV {kp_us:.0f} ({cap}), so the matchers do not see the "
               f"same keypoints. Ours (segment + auto depth) has {kp_us / kp_pc:.2f}x pycolmap's keypoints, "
               f"{s['inliers'] / max(pc['inliers'], 1):.2f}x its verified matches and "
               f"{s['quality']['points'] / max(pc['quality']['points'], 1):.2f}x its 3D points.")
    w1 = P["workers=1"]["pairs_per_second_median"]
    parts = []
    for label, p in P.items():
        if label == "workers=1":
            continue
        if p.get("pairs_per_second_median") is not None:
            parts.append(f"{label} {p['pairs_per_second_median']:.1f} pairs/s ({p['pairs_per_second_median'] / w1:.2f}x)"
                         f"{', identical matches in every run' if p.get('identical') else ', matches DIFFER'}")
    if parts:
        out.append(f"- Parallel matching: workers=1 {w1:.1f} pairs/s; " + "; ".join(parts) + ".")
    la, cores = res["load_average"], res["machine"].get("cpu_count") or 1
    if max(la) >= 0.9 * cores:
        out.append(f"- The machine was shared: load average {la[0]:.2f} at the start and {la[1]:.2f} at the end on "
                   f"{cores} cores. Times vary between repeats (every run is in the JSON), and 2 workers or 2 "
                   "threads had less than 2 free cores, so parallel speed-ups are understated here.")
    broken = [label for label, p in P.items() if not p["first_ok"] or "pairs_per_second_median" not in p
              or not p.get("identical")]
    if broken:
        out.append(f"- **{' and '.join(broken)}: failed, lost pairs or gave other matches** (see the workers table).")
    mem = [m for m in res["memory"] if "error" not in m]
    for method, w in sorted({(m["method"], m["workers"]) for m in mem}):
        rows = sorted((m for m in mem if m["method"] == method and m["workers"] == w), key=lambda m: m["views"])
        if len(rows) >= 2:
            a, b = rows[0], rows[-1]
            who = f"ours with workers={w}" if method == "ours" else "pycolmap"
            extra = (f"; largest worker {a['peak_largest_worker_mib']:.0f} -> {b['peak_largest_worker_mib']:.0f} MiB"
                     if w > 1 and a.get("peak_largest_worker_mib") and b.get("peak_largest_worker_mib") else "")
            out.append(f"- Memory, {who}: driver peak {a['peak_driver_mib']:.0f} MiB at {a['views']} views "
                       f"({a['pairs']} pairs), {b['peak_driver_mib']:.0f} MiB at {b['views']} views ({b['pairs']} "
                       f"pairs): {b['peak_driver_mib'] / a['peak_driver_mib']:.2f}x for {b['pairs'] / a['pairs']:.1f}x "
                       f"the pairs; above the imports: {a['peak_driver_mib'] - a['peak_after_imports_mib']:.0f} -> "
                       f"{b['peak_driver_mib'] - b['peak_after_imports_mib']:.0f} MiB{extra}.")
    return out


# --------------------------------------------------------------------------------------
def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="6 views at 480x360, 1 repeat, no Dask, memory at one size")
    p.add_argument("--repeats", type=int, default=None, help="timed repeats (default 5, 1 with --quick)")
    p.add_argument("--out", type=Path, default=None,
                   help="output directory (default benchmarks/results; benchmarks/results/quick with --quick)")
    p.add_argument("--keep", type=Path, default=None, help="keep the work folder (images, databases) here")
    p.add_argument("--data", type=Path, default=DATA,
                   help="folder holding dinoSparseRing/ (default: <repo>/../shared/data)")
    p.add_argument("--child", nargs=3, metavar=("FOLDER", "METHOD", "WORKERS"), help=argparse.SUPPRESS)
    p.add_argument("--parallel-child", nargs=5, metavar=("MODEL", "IMAGES", "WORK", "REPEATS", "DASK"),
                   help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.repeats is not None and args.repeats < 1:
        p.error(f"--repeats must be >= 1, got {args.repeats}")
    return args


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(argv)
    if args.child:
        folder, method, workers = args.child
        return child_main(folder, method, int(workers))
    if args.parallel_child:
        model, images, work, repeats, dask = args.parallel_child
        res = sets.run_parallel(Path(model), Path(images), Path(work), int(repeats), bool(int(dask)))
        print(json.dumps(res))
        return 0
    cfg = dict(QUICK if args.quick else FULL)
    if args.repeats is not None:
        cfg["repeats"] = args.repeats
    command = " ".join(["python", SCRIPT] + [shlex.quote(a) for a in argv])
    load0 = os.getloadavg()[0]
    meta = machine_metadata()  # at the start: the commit of the code that runs
    meta["episeg_cv_uncommitted_changes"] = package_dirty()
    t0 = time.perf_counter()
    progress(f"{command}: {cfg}")
    if args.keep:
        args.keep.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix="colmap_bench_", dir=args.keep))
    else:
        work = Path(tempfile.mkdtemp(prefix="colmap_bench_"))
    try:
        body = run(cfg, work)
        body["part2"] = run_sets(cfg, work, args.data)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    from episeg_cv import AcceptRule

    end = {"git_commit": machine_metadata()["git_commit"], "episeg_cv_uncommitted_changes": package_dirty()}
    if (end["git_commit"], end["episeg_cv_uncommitted_changes"]) != (meta["git_commit"],
                                                                   meta["episeg_cv_uncommitted_changes"]) \
            or end["episeg_cv_uncommitted_changes"]:
        progress(f"WARNING: episeg_cv changed during or before the run ({meta['git_commit']} -> {end['git_commit']}, "
                 f"uncommitted changes: {end['episeg_cv_uncommitted_changes']}); rerun on a clean tree")
    meta["at_the_end"] = end
    res = {"command": command, "machine": meta, "load_average": [load0, os.getloadavg()[0]],
           "config": {**cfg, "image_size": list(cfg["image_size"]), "max_features": MAX_FEATURES,
                      "accuracy": ACCURACY, "statistic": "median",
                      "ratio": AcceptRule().ratio},
           **body, "wall_time_s": time.perf_counter() - t0}
    args.out = args.out or (RESULTS / "quick" if args.quick else RESULTS)  # --quick never overwrites the full run
    args.out.mkdir(parents=True, exist_ok=True)
    stem = "colmap"
    (args.out / f"{stem}.json").write_text(json.dumps(res, indent=1, default=float) + "\n")
    write_markdown(args.out / f"{stem}.md", res)
    progress(f"wrote {args.out / (stem + '.md')} and {stem}.json in {res['wall_time_s']:.0f} s")
    for line in verdict(res):
        print(line)
    for goal, name, met, text in sets.goals(res["part2"]["sets"]):
        print(f"- {goal}, {name}: {'met' if met else 'NOT met'} ({text})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
