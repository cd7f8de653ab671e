"""Collections and peers for ``benchmarks/colmap.py`` (issue 14): the real dinoSparseRing set, pycolmap's pipelines.

- dinoSparseRing (Middlebury multi-view, Seitz, Curless, Diebel, Scharstein,
  Szeliski, "A Comparison and Evaluation of Multi-View Stereo Reconstruction
  Algorithms", CVPR 2006): 16 views on a ring, 640x480, ``dinoSR_par.txt``
  (read by ``colmap.load_par``), an untextured object on a black background.
  Accuracy (:func:`dino_quality`): a 3D point is accurate when it lies inside
  the README's bounding box widened by 3 mm, and projects onto the object's
  silhouette in every view where it is in front of the camera and inside the
  image (not only the views of its track: a point on the object projects into
  every silhouette, whatever the occlusions). Silhouettes (:func:`dino_masks`):
  the README's recipe (threshold 0.19 on the brightest colour channel, dilate
  10 px, erode 7 px, elliptical elements), then holes filled (dark shadows on
  the object).
- Peers, every one triangulated the same way (:func:`triangulate_with`):
  pycolmap ``extract_features`` (one PINHOLE camera with the known intrinsics)
  + ``match_exhaustive``; and ``FeatureMatcher.match_guided`` with a
  CALIBRATED ``TwoViewGeometry`` built from the known poses.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import cv2
import numpy as np

#: README.txt of dinoSparseRing: the "tight" bounding box of the object, metres.
DINO_BOX = (np.array([-0.061897, -0.018874, -0.057845]), np.array([0.010897, 0.068227, 0.015495]))
DINO_MARGIN = 0.003  # metres
DINO_PAR = "dinoSR_par.txt"

#: Triangulation options: COLMAP's defaults ("3v": a point needs three views) and with two-view tracks kept.
TRIANGULATIONS = {"3v": {}, "2v": {"ignore_two_view_tracks": False}}
#: Runs whose median is the matching time of a method (one run is noise on a shared 2-core machine).
TIME_REPEATS = 5


def _pycolmap():
    import pycolmap

    pycolmap.logging.minloglevel = 2
    return pycolmap


# --------------------------------------------------------------------------------------
# dinoSparseRing
# --------------------------------------------------------------------------------------
def find_dino(data_dir) -> Path | None:
    """The dinoSparseRing folder under ``data_dir``, or None."""
    folder = Path(data_dir) / "dinoSparseRing"
    return folder if (folder / DINO_PAR).is_file() else None


def dino_masks(folder, names, threshold=0.19, dilate=10, erode=7) -> dict:
    """Silhouettes ``{name: (H, W) bool}`` (module docstring)."""
    masks = {}
    for name in names:
        img = cv2.imread(str(Path(folder) / name))
        m = (img.max(axis=2).astype(np.float32) / 255.0 > threshold).astype(np.uint8)
        m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate + 1, 2 * dilate + 1)))
        m = cv2.erode(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode + 1, 2 * erode + 1)))
        h, w = m.shape
        flood = np.pad(m, 1).copy()
        cv2.floodFill(flood, np.zeros((h + 4, w + 4), np.uint8), (0, 0), 2)  # the background, from a corner
        masks[name] = flood[1:-1, 1:-1] != 2
    return masks


def dino_quality(rec, views, masks, margin=DINO_MARGIN) -> dict:
    """Counts, track lengths, reprojection error and accuracy of a triangulated model of dino."""
    n = len(rec.points3D)
    if n == 0:
        return {"points": 0, "accurate": 0, "accurate_fraction": float("nan"), "mean_track_length": 0.0,
                "mean_reprojection_error": float("nan"), "points_track_ge_3": 0, "in_box": 0}
    X = np.array([p.xyz for p in rec.points3D.values()])
    lengths = np.array([p.track.length() for p in rec.points3D.values()])
    in_box = np.all((X >= DINO_BOX[0] - margin) & (X <= DINO_BOX[1] + margin), axis=1)
    on_sil = np.ones(n, bool)
    for v in views:
        Xc = X @ v.R.T + v.t
        z = Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            px = np.rint((Xc @ v.K.T)[:, :2] / z[:, None])
        w, h = v.image_size
        inside = (z > 0) & np.all(np.isfinite(px), axis=1) & (px[:, 0] >= 0) & (px[:, 0] < w) \
            & (px[:, 1] >= 0) & (px[:, 1] < h)
        idx = np.flatnonzero(inside)
        ok = masks[v.name][px[idx, 1].astype(int), px[idx, 0].astype(int)]
        on_sil[idx[~ok]] = False
    acc = in_box & on_sil
    return {"points": int(n), "accurate": int(acc.sum()), "accurate_fraction": float(acc.mean()),
            "in_box": int(in_box.sum()), "mean_track_length": float(lengths.mean()),
            "mean_reprojection_error": float(rec.compute_mean_reprojection_error()),
            "points_track_ge_3": int((lengths >= 3).sum())}


# --------------------------------------------------------------------------------------
# Triangulation with named options, for every method
# --------------------------------------------------------------------------------------
def triangulate_with(database, model, image_dir, out_dir, options: dict):
    """``colmap.triangulate`` with ``IncrementalPipelineOptions().triangulation`` fields set from ``options``."""
    from episeg_cv import colmap

    pycolmap = _pycolmap()
    opts = pycolmap.IncrementalPipelineOptions()
    for k, v in options.items():
        setattr(opts.triangulation, k, v)
    return colmap.triangulate(database, model, image_dir, out_dir, options=opts)


# --------------------------------------------------------------------------------------
# pycolmap's pipelines
# --------------------------------------------------------------------------------------
def pycolmap_extract(views, image_dir, database, max_features: int, threads: int = -1) -> float:
    """COLMAP's SIFT (CPU) into a new database, one PINHOLE camera with the views' (shared) intrinsics; seconds."""
    pycolmap = _pycolmap()
    params = {tuple(v.camera_params) for v in views}
    if len(params) != 1 or views[0].camera_model != "PINHOLE":
        raise ValueError("the peers need one PINHOLE camera shared by every view")
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(repr(float(p)) for p in views[0].camera_params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = max_features
    extraction.num_threads = threads
    t0 = time.perf_counter()
    pycolmap.extract_features(str(database), str(image_dir), image_names=[v.name for v in views],
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    return time.perf_counter() - t0


def pycolmap_exhaustive(database, threads: int = -1) -> float:
    """``match_exhaustive`` (ratio 0.8, cross-check, RANSAC verification: COLMAP's defaults); seconds."""
    pycolmap = _pycolmap()
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    t0 = time.perf_counter()
    pycolmap.match_exhaustive(str(database), matching_options=matching, device=pycolmap.Device.cpu)
    return time.perf_counter() - t0


def _calibrated_geometry(v1, v2):
    """CALIBRATED TwoViewGeometry from the known poses; F in COLMAP's pixel convention (centre of the
    top-left pixel at (0.5, 0.5)): ``F_c = T^-T F T^-1``, ``T`` the translation by +0.5."""
    pycolmap = _pycolmap()
    g = v1.geometry_to(v2)
    tvg = pycolmap.TwoViewGeometry()
    tvg.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
    tvg.E = g.essential_matrix
    Ti = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1.0]])
    tvg.F = Ti.T @ g.fundamental_matrix @ Ti
    tvg.cam2_from_cam1 = pycolmap.Rigid3d(pycolmap.Rotation3d(g.R), g.t)
    return tvg


def _keypoints(arr):
    pycolmap = _pycolmap()
    out = pycolmap.FeatureKeypoints()
    for row in np.asarray(arr, dtype=np.float64):
        k = pycolmap.FeatureKeypoint(x=float(row[0]), y=float(row[1]))
        if len(row) >= 6:
            k.a11, k.a12, k.a21, k.a22 = (float(x) for x in row[2:6])
        out.append(k)
    return out


def pycolmap_guided(views, features_db, database, max_error: float = 4.0) -> float:
    """Known-pose matching with pycolmap's ``FeatureMatcher.match_guided`` on every pair; seconds.

    ``features_db`` (features only) is copied to ``database``; for each pair, a
    CALIBRATED ``TwoViewGeometry`` from the poses goes to ``match_guided(max_error, ...)``
    (ratio 0.8, cross-check, max distance 0.7: COLMAP's matching defaults), whose
    ``inlier_matches`` are written as both the matches and the verified inliers.
    """
    import dataclasses

    pycolmap = _pycolmap()
    shutil.copyfile(features_db, database)
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = 1
    matcher = pycolmap.FeatureMatcher.create(options, pycolmap.Device.cpu)
    db = pycolmap.Database.open(str(database))
    t0 = time.perf_counter()
    try:
        images = {im.name: im for im in db.read_all_images()}
        cams = {c.camera_id: c for c in db.read_all_cameras()}
        vs = sorted((dataclasses.replace(v, image_id=images[v.name].image_id) for v in views),
                    key=lambda v: v.image_id)
        feats = {v.image_id: (_keypoints(db.read_keypoints(v.image_id)), db.read_descriptors(v.image_id)) for v in vs}
        for a in range(len(vs)):
            for b in range(a + 1, len(vs)):
                v1, v2 = vs[a], vs[b]
                tvg = _calibrated_geometry(v1, v2)
                c1, c2 = cams[images[v1.name].camera_id], cams[images[v2.name].camera_id]
                matcher.match_guided(max_error, feats[v1.image_id][0], feats[v1.image_id][1], c1,
                                     feats[v2.image_id][0], feats[v2.image_id][1], c2, tvg)
                inl = np.asarray(tvg.inlier_matches, dtype=np.uint32).reshape(-1, 2)
                db.write_matches(v1.image_id, v2.image_id, inl)
                db.write_two_view_geometry(v1.image_id, v2.image_id, tvg)
    finally:
        db.close()
    return time.perf_counter() - t0


# --------------------------------------------------------------------------------------
# The issue-14 section: same features, end to end, on the real set and synthetic rooms
# --------------------------------------------------------------------------------------
#: The library's defaults, on COLMAP's features and end to end: what the goals are checked on.
DEFAULT_SAME = "ours on COLMAP's features, track consensus, tol auto (default)"
DEFAULT_E2E = "ours end to end, track consensus, tol auto (default)"
#: label -> (features, verify, tol, the consensus's loose ratio or "complete" for ``TrackConsensus(complete=True)``);
#: None: the library's default.
OURS = {
    "ours on COLMAP's features, pair rule, tol 2": ("database", "pairs", 2.0, None),
    "ours on COLMAP's features, previous default (tol 2, edges below ratio 0.9)": ("database", "tracks", 2.0, 0.9),
    DEFAULT_SAME: ("database", "tracks", None, None),
    "ours end to end, pair rule, tol 2": ("collection", "pairs", 2.0, None),
    "ours end to end, previous default (tol 2, edges below ratio 0.9)": ("collection", "tracks", 2.0, 0.9),
    DEFAULT_E2E: ("collection", "tracks", None, None),
    "ours on COLMAP's features, track consensus + completion (opt-in)": ("database", "tracks", None, "complete"),
    "ours end to end, track consensus + completion (opt-in)": ("collection", "tracks", None, "complete"),
}
PYCOLMAP = "pycolmap extract + match_exhaustive"
GUIDED = "pycolmap match_guided (known poses, CALIBRATED)"
METHODS = [PYCOLMAP, GUIDED, *OURS]


def _progress(msg):
    import sys

    print(f"[colmap bench {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _quality_all(database, model, image_dir, out, quality) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    res = {}
    for tag, options in TRIANGULATIONS.items():
        t0 = time.perf_counter()
        rec = triangulate_with(database, model, image_dir, out / tag, options)
        res[tag] = {**quality(rec), "seconds_triangulation": time.perf_counter() - t0}
    return res


def run_set(name, model, image_dir, views, quality, work: Path, max_features: int, workers: int) -> dict:
    """Every method of :data:`METHODS` on one collection; quality under both triangulations, times."""
    from episeg_cv import colmap
    from episeg_cv.features import PRESETS

    work.mkdir(parents=True, exist_ok=True)
    features_db = work / "colmap_features.db"
    seconds_extract = pycolmap_extract(views, image_dir, features_db, max_features)
    out, again = {}, {}  # again[m](): one more timed matching of method m, its seconds
    for m in METHODS:
        k = len(out)
        db = work / f"{k}.db"
        shutil.copyfile(features_db, db)
        t0 = time.perf_counter()
        entry = {}
        if m == PYCOLMAP:
            entry["seconds_matching"] = pycolmap_exhaustive(db)
            entry["seconds_features"] = seconds_extract
            again[m] = lambda k=k: pycolmap_exhaustive(_fresh_copy(features_db, work / f"{k}_again.db"))
        elif m == GUIDED:
            entry["seconds_matching"] = pycolmap_guided(views, features_db, db)
            entry["seconds_features"] = seconds_extract
        else:
            features, verify, tol, loose = OURS[m]
            if features == "collection":
                db.unlink()
                features = PRESETS["collection"].replace(max_features=max_features)
            notes = []
            given = ({} if tol is None else {"tol": tol})
            verify = verify if loose is None else colmap.TrackConsensus(complete=True) if loose == "complete" else \
                colmap.TrackConsensus(loose=loose)
            options = dict(features=features, verify=verify, **given, workers=workers,
                           cache_dir=work / f"{k}.features")
            report = colmap.match_model(model, image_dir, db, **options, log=notes.append)
            entry.update(seconds_matching=report.seconds_matching, seconds_verify=report.seconds_verify,
                         seconds_features=report.seconds_features if features != "database" else seconds_extract,
                         seconds_features_read=report.seconds_features if features == "database" else None,
                         pairs_per_second=report.pairs_per_second, runner=report.runner, verify=report.verify, band=report.band,
                         inliers=report.n_inliers, warnings=notes)
            copy = features_db if features == "database" else None
            again[m] = lambda k=k, copy=copy, options=options: colmap.match_model(
                model, image_dir, _fresh_copy(copy, work / f"{k}_again.db"), **options, overwrite=True,
                log=lambda msg: None).seconds_matching
        entry["seconds_wall"] = time.perf_counter() - t0
        entry["quality"] = _quality_all(db, model, image_dir, work / f"{k}_tri", quality)
        out[m] = entry
        q = entry["quality"]
        _progress(f"{name}, {m}: 3v {q['3v']['accurate']}/{q['3v']['points']} accurate, 2v "
                  f"{q['2v']['accurate']}/{q['2v']['points']}; matching {entry['seconds_matching']:.2f} s (first run)")
    # the matching time: the median of TIME_REPEATS runs (the first one included), the repeats interleaved
    # round by round, so that a change of the shared machine's load falls on every method alike
    runs = {m: [out[m]["seconds_matching"]] for m in again}
    for _ in range(TIME_REPEATS - 1):
        for m, run in again.items():
            runs[m].append(run())
    for m, entry in out.items():
        if m in runs:
            entry["seconds_matching_runs"] = runs[m]
            entry["seconds_matching"] = float(np.median(runs[m]))
        entry["seconds_total"] = entry["seconds_features"] + entry["seconds_matching"] + \
            entry["quality"]["3v"]["seconds_triangulation"]
    return {"methods": out, "n_views": len(views), "n_pairs": len(views) * (len(views) - 1) // 2,
            "seconds_extract_pycolmap": seconds_extract}


def _fresh_copy(features_db, path: Path) -> Path:
    """``path`` made anew: a copy of ``features_db`` (None: no file, the run makes it)."""
    path.unlink(missing_ok=True)
    if features_db is not None:
        shutil.copyfile(features_db, path)
    return path


def run_parallel(model, image_dir, work: Path, repeats: int, dask: bool) -> dict:
    """pairs/s of ``match_model`` (defaults) with 1 and 2 workers and a local Dask cluster of 2, interleaved."""
    from episeg_cv import colmap

    work.mkdir(parents=True, exist_ok=True)
    cache = work / "cache"
    colmap.match_model(model, image_dir, work / "warm.db", cache_dir=cache, overwrite=True, log=lambda m: None)
    reference = colmap.read_database_matches(work / "warm.db")
    # workers = cores: workers=1 runs everything on one core (COLMAP's num_threads=1), workers=2 on two
    runners = {"workers=1": {"workers": 1}, "workers=2": {"workers": 2}}
    if dask:
        runners["Dask local:2"] = {"scheduler": "local:2"}
    out = {label: {"pairs_per_second": [], "seconds_matching": [], "identical": True} for label in runners}
    for r in range(repeats):
        for label, kw in runners.items():
            db = work / f"{label.replace(' ', '_').replace(':', '').replace(',', '')}.db"
            t0, c0 = time.perf_counter(), time.process_time()
            report = colmap.match_model(model, image_dir, db, cache_dir=cache, overwrite=True, log=lambda m: None,
                                        **kw)
            e = out[label]
            # this process's CPU time per wall second: about the cores the threads got (not Dask's workers)
            e["cpu_per_wall"] = e.get("cpu_per_wall", []) + [(time.process_time() - c0) / (time.perf_counter() - t0)]
            e["pairs_per_second"].append(report.pairs_per_second)
            e["seconds_matching"].append(report.seconds_matching)
            for stage in STAGES:
                e.setdefault(f"seconds_{stage}", []).append(getattr(report, f"seconds_{stage}"))
            e.setdefault("seconds_rest", []).append(report.seconds_matching - sum(getattr(report, f"seconds_{k}")
                                                                                  for k in STAGES))
            e["seconds_wall"] = e.get("seconds_wall", []) + [time.perf_counter() - t0]
            got = colmap.read_database_matches(db)
            e["identical"] &= got.keys() == reference.keys() and all(
                np.array_equal(got[k][0], reference[k][0]) and np.array_equal(got[k][1], reference[k][1])
                for k in reference)
            e["runner"] = report.runner
        _progress(f"parallel, repeat {r + 1}/{repeats}: " + ", ".join(
            f"{k} {v['pairs_per_second'][-1]:.1f} pairs/s" for k, v in out.items()))
    for e in out.values():
        e["pairs_per_second_median"] = float(np.median(e["pairs_per_second"]))
    one = out["workers=1"]["pairs_per_second_median"]
    for e in out.values():
        e["speed_up"] = e["pairs_per_second_median"] / one if one else float("nan")
    from _gil import python_share  # (benchmarks/ is on sys.path)
    return {"runners": out, "n_pairs": len(reference), "gil": python_share(model, image_dir, work, cache)}


#: The stages of ``MatchReport.seconds_matching`` (its ``seconds_<stage>`` fields).
STAGES = ("band", "pairs", "verify", "write")
#: Threads of the extrapolation in the stage table (what a user's machine may have).
EXTRAPOLATE_TO = 16


def extrapolate(t1: float, t2: float, n: int, cap: float = float("inf")) -> tuple[float, float]:
    """Amdahl's law fitted to a stage's time on 1 and 2 threads: ``(serial share f, time on n threads)``.

    ``t2 = t1 (f + (1 - f) / 2)`` gives ``f = 2 t2 / t1 - 1`` (clipped to [0, 1]); then ``t_n = t1 (f + (1 -
    f) / n)``, and no faster than ``t1 / cap`` (the pairs' GIL ceiling). On a 2-core machine where the two
    threads get fewer than 2 cores, ``f`` comes out too large: the estimate is pessimistic.
    """
    f = min(1.0, max(0.0, 2.0 * t2 / t1 - 1.0)) if t1 > 0 else 1.0
    return f, max(t1 * (f + (1.0 - f) / n), t1 / cap)


def _pct(a, b):
    return 100.0 * (a / b - 1.0) if b else float("nan")


def goals(sets: dict) -> list:
    """The issue's goals, per collection: ``[(goal, set, met, text)]``."""
    rows = []
    for name, s in sets.items():
        M = s["methods"]
        pc = M[PYCOLMAP]["quality"]["3v"]
        for goal, method, need in (("same features: >= +25 % accurate points", DEFAULT_SAME, 25.0),
                                   ("end to end: >= +10 % accurate points", DEFAULT_E2E, 10.0)):
            q = M[method]["quality"]["3v"]
            gain = _pct(q["accurate"], pc["accurate"])
            dfrac = 100 * (q["accurate_fraction"] - pc["accurate_fraction"])
            met = gain >= need and dfrac >= -0.5
            rows.append((goal, name, met, f"{q['accurate']} vs {pc['accurate']} ({gain:+.0f} %), fraction "
                                          f"{100 * q['accurate_fraction']:.1f} vs {100 * pc['accurate_fraction']:.1f} % "
                                          f"({dfrac:+.1f} points)"))
        ratio = M[DEFAULT_E2E]["seconds_matching"] / M[PYCOLMAP]["seconds_matching"]
        rows.append(("matching time <= 0.5x match_exhaustive (all cores)", name, ratio <= 0.5,
                     f"{M[DEFAULT_E2E]['seconds_matching']:.2f} s vs {M[PYCOLMAP]['seconds_matching']:.2f} s "
                     f"({ratio:.2f}x)"))
    return rows


def markdown(res: dict) -> list:
    """The section of ``colmap.md``."""
    L = ["## Known poses on a real collection and synthetic rooms: same features, and end to end (issue 14)\n"]
    if res.get("dino_missing"):
        L.append(f"**dinoSparseRing not found** under `{res['data_dir']}`: the real collection was skipped "
                 "(pass `--data DIR`, the folder holding `dinoSparseRing/`).\n")
    L.append("- **Data.** dinoSparseRing (Middlebury multi-view; S. M. Seitz, B. Curless, J. Diebel, D. Scharstein, "
             "R. Szeliski, *A Comparison and Evaluation of Multi-View Stereo Reconstruction Algorithms*, CVPR 2006): "
             "16 views on a ring, 640x480, calibrated poses from `dinoSR_par.txt`, read directly as MODEL. A 3D "
             f"point is accurate when it lies inside the README's bounding box widened by {DINO_MARGIN * 1000:.0f} mm "
             "and projects onto the object's silhouette (threshold 0.19 on the brightest channel, dilate 10 px, "
             "erode 7 px, holes filled) in every view where it is in front of the camera and inside the image. "
             "(The box never binds on this set: every point of every method is inside it; the silhouettes do "
             "the work.) Synthetic rooms: `scenes.make_collection` with exact poses and rendered depth, accurate = "
             "within 1 % of depth in every image of the track; MODEL = the saved model folder, so "
             "`depth_range=\"auto\"` applies there (none on dino: its par file has no 3D points).")
    L.append("- **Peers**, all triangulated by `pycolmap.triangulate_points` with the known poses and the same "
             "options: **3v** = COLMAP's defaults (`IncrementalPipelineOptions()`, `ignore_two_view_tracks=True`, "
             "`min_angle=1.5`): the headline; **2v** = the same with `ignore_two_view_tracks=False`. "
             f"{PYCOLMAP}: `extract_features` (one PINHOLE camera with the known intrinsics, 8192 features, CPU) + "
             f"`match_exhaustive` (ratio 0.8, cross-check, RANSAC). {GUIDED}: `FeatureMatcher.match_guided(4 px, ...)` "
             "with a CALIBRATED `TwoViewGeometry` (E, F, cam2_from_cam1) built from the poses, on the same features. "
             "Ours on COLMAP's features: `match_model(..., features=\"database\")` on a copy of that database. "
             "Ours end to end: `match_model` with the defaults (the `\"collection\"` SIFT preset). Pair rule = "
             "`verify=\"pairs\"` (ratio 0.68 per pair); track consensus = `verify=\"tracks\"` (the default), whose "
             "edges are every mutual candidate (`TrackConsensus.loose = 1`, the default; the previous default "
             "took those below ratio 0.9). tol auto = `tol=\"auto\"` (the default for collections): one band "
             "for the collection from the confident matches, around the given poses, of up to 16 pairs of "
             "cameras that look alike, until every image is in one (`episeg_cv.colmap.band.band_pairs`; the "
             "band found is in the JSON); tol 2 = the fixed 2 px, the previous "
             "default.")
    L.append("- **Times**: matching = `match_exhaustive` / the `match_guided` loop / `MatchReport.seconds_matching` "
             "(matching, consensus and database writes; ours on all cores: `workers` = the core count, threads). "
             f"Matching times are the median of {TIME_REPEATS} runs: the first, then the others interleaved round "
             "by round over the methods of a collection, so that a change of the shared machine's load falls on "
             "every method alike (`match_guided`: one run; every run in the JSON); counts and quality are from "
             "the first run (deterministic except pycolmap's RANSAC). "
             "Total = features + matching + 3v triangulation.\n")
    for name, s in res["sets"].items():
        M = s["methods"]
        L.append(f"### {name} ({s['n_views']} views, {s['n_pairs']} pairs)\n")
        L.append("| method | 3v points | 3v accurate | 3v fraction | 3v track length | 3v reproj. (px) | 2v points | "
                 "2v accurate | 2v fraction | matching (s) | total (s) |")
        L.append("|---|" + "---:|" * 10)
        for m in METHODS:
            e = M[m]
            a, b = e["quality"]["3v"], e["quality"]["2v"]
            L.append(f"| {m} | {a['points']} | **{a['accurate']}** | {100 * a['accurate_fraction']:.1f} % | "
                     f"{a['mean_track_length']:.2f} | {a['mean_reprojection_error']:.3f} | {b['points']} | "
                     f"{b['accurate']} | {100 * b['accurate_fraction']:.1f} % | {e['seconds_matching']:.2f} | "
                     f"{e['seconds_total']:.2f} |")
        L.append("")
    L.append("### The issue's goals, from these numbers\n")
    L.append("| goal | collection | met | numbers |")
    L.append("|---|---|---|---|")
    for goal, name, met, text in goals(res["sets"]):
        L.append(f"| {goal} | {name} | {'**yes**' if met else 'no'} | {text} |")
    P = res.get("parallel")
    if P:
        L.append("")
        L.append(f"### Parallel runs ({P['n_views']} views, {P['n_pairs']} pairs, `match_model` defaults, features "
                 "cached, runs interleaved, in a fresh process of their own)\n")
        L.append("| runner | pairs/s (median) | speed-up | identical matches | driver CPU s per wall s (median) |")
        L.append("|---|---:|---:|---|---:|")
        for label, e in P["runners"].items():
            L.append(f"| {label} ({e['runner']}) | {e['pairs_per_second_median']:.1f} | {e['speed_up']:.2f}x | "
                     f"{'yes' if e['identical'] else '**no**'} | {np.median(e['cpu_per_wall']):.2f} |")
        L.append("")
        L.append("`workers` counts cores, as COLMAP's `num_threads`: `workers=1` runs everything (pairs, band, "
                 "track consensus) on one core; `workers=2` runs the pairs on two threads, one pair each, and the "
                 "band's pairs and the consensus on two kernel threads; Dask `local:2` runs the pairs in two worker "
                 "processes of one thread each (the band's pairs too), the consensus in this process.")
        L.append("")
        L.append("The last column is the CPU time of the benchmark process per second of wall time: with "
                 "`workers=2` it shows how many cores the two threads actually got (near 1.0 on a busy machine: "
                 "then no speed-up can show). Dask's workers are other processes, not counted there. The runs "
                 "are made in a fresh process (`colmap.py --parallel-child`), as a user's `episeg colmap` runs: "
                 "the benchmark's own process holds every earlier part's results by then, and in a process holding "
                 "3 M more Python objects a Dask run's matching took 0.07 s longer on these 24 views (scratch), "
                 "one worker's did not.")
        L.append("")
        G = P.get("gil")
        one, two = P["runners"]["workers=1"], P["runners"].get("workers=2")
        if two is not None and "seconds_band" in one:
            med = lambda e, k: float(np.median(e[k]))  # noqa: E731
            n = EXTRAPOLATE_TO
            L.append(f"Where the time goes (`MatchReport.seconds_<stage>`, medians), and what Amdahl's law fitted to "
                     f"1 and 2 threads gives for {n} threads (a model, not a measurement: each stage's serial share "
                     f"`f = 2 t2 / t1 - 1`, then `t{n} = t1 (f + (1 - f) / {n})`, the pairs no faster than the GIL "
                     "ceiling below; what the stages leave of `seconds_matching` is taken as serial; the last row "
                     "sums the medians):\n")
            L.append(f"| stage | workers=1 (s) | workers=2 (s) | speed-up | serial share f | {n} threads, "
                     f"estimated (s) |" + (" Dask local:2 (s) |" if "Dask local:2" in P["runners"] else ""))
            L.append("|---|---:|---:|---:|---:|---:|" + ("---:|" if "Dask local:2" in P["runners"] else ""))
            total1 = total2 = totaln = 0.0
            dask = P["runners"].get("Dask local:2")
            total_d = 0.0
            for stage in STAGES + ("rest",):
                t1, t2 = med(one, f"seconds_{stage}"), med(two, f"seconds_{stage}")
                if stage == "rest":
                    f, tn = 1.0, t1
                else:
                    f, tn = extrapolate(t1, t2, n, G["ceiling"] if (G and stage == "pairs") else float("inf"))
                td = med(dask, f"seconds_{stage}") if dask else 0.0
                total1, total2, totaln, total_d = total1 + t1, total2 + t2, totaln + tn, total_d + td
                name = {"band": "band (`tol=\"auto\"`)", "pairs": "pairs", "verify": "track consensus",
                        "write": "database writes", "rest": "the rest (Python between stages)"}[stage]
                L.append(f"| {name} | {t1:.3f} | {t2:.3f} | {t1 / t2 if t2 > 0 else float('nan'):.2f}x | {f:.2f} | "
                         f"{tn:.3f} |" + (f" {td:.3f} |" if dask else ""))
            L.append(f"| **matching** | **{total1:.3f}** | **{total2:.3f}** | **{total1 / total2:.2f}x** | | "
                     f"**{totaln:.3f}** ({total1 / totaln:.1f}x one thread) |" + (f" **{total_d:.3f}** |" if dask else ""))
            L.append("")
        if G:
            L.append(f"**Threads stop near {G['ceiling']:.1f}x, on any number of cores.** Matched again on one "
                     f"thread, the {G['pairs']} pairs took {G['cpu_s']:.2f} s of CPU, {G['kernels_s']:.2f} s of it "
                     f"inside the compiled kernels (each wrapped to sum its CPU time, `benchmarks/_gil.py`): "
                     f"{100 * G['python_share']:.0f} % is Python between them, which holds the GIL, so N threads "
                     f"run the pairs at most 1 / {G['python_share']:.2f} = {G['ceiling']:.1f}x faster than one. "
                     "Dask's worker processes do not share a GIL.")
            L.append("")
        L.append("Goals: `--workers 2` >= 1.6x one worker, Dask `local:2` >= 1.4x. " + "; ".join(
            f"{label}: {e['speed_up']:.2f}x ({'met' if e['speed_up'] >= need else 'not met'})"
            for label, e, need in ((k, v, 1.6 if k == "workers=2" else 1.4) for k, v in P["runners"].items()
                                   if not k.startswith("workers=1"))) + ".")
    L.append("")
    return L
