"""Posed collections with pose errors: how many accurate 3D points ``match_model`` keeps, with and without refinement.

Users of ``episeg colmap`` give poses from odometry or GPS, never exact ones.
On dinoSparseRing (real) and two rendered rooms, each view's pose gets an
error of ``p`` pixels (``_noisy_poses.py``: a rotation by ``p / f`` about a
random axis and a camera-centre move of ``p z / f`` in a random direction,
``z`` the view's typical depth), ``p`` in 0, 0.5, 1, 2, 4, 8 px, two seeds per
noisy level. Rows per level:

(a) pycolmap ``extract_features`` + ``match_exhaustive`` (pose-free: matched once);
(b) ``match_model`` on COLMAP's features (``features="database"``), defaults, the noisy poses;
(c) the same with ``refine_poses=True``;
(d), (e) the same two end to end (our features, the ``"collection"`` preset).

Every database is triangulated (``pycolmap.triangulate_points`` through
``_colmap_sets.triangulate_with``, COLMAP's default options) twice: with the
TRUE poses (the matching alone) and with the poses the method used (the noisy
ones; the refined ones, ``MatchReport.poses.views``, for (c) and (e)): what a
user gets, judged up to its frame (moved by the similarity that best takes its
points onto those the true poses triangulate from the same database, trimmed
least squares). Accuracy
as in ``benchmarks/colmap.py`` (rooms: within 1 % of the rendered depth in
every image of the track; dino: on the silhouettes), always judged with the
true poses. The goal, per level: at least pycolmap's accurate points at an
accurate fraction at most 0.5 points below its.

Usage::

    python benchmarks/noisy_poses.py            # dino + rooms (12 views seed 7, 10 views seed 3), 6 levels, 2 seeds
    python benchmarks/noisy_poses.py --quick    # dino + a 6-view room at 480x360, levels 0 and 2 px

Writes ``benchmarks/results/noisy_poses.{md,json}`` (``benchmarks/results/quick/`` with ``--quick``, git-ignored).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from episeg_cv.refinement import rotation_angle_deg

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _colmap_sets as sets  # noqa: E402
import _noisy_poses as noise  # noqa: E402
from _common import machine_metadata, package_dirty  # noqa: E402
from colmap import DATA, MAX_FEATURES, quality  # noqa: E402

SCRIPT = "benchmarks/noisy_poses.py"
RESULTS = Path(__file__).resolve().parent / "results"
FULL = {"sets": ["dino", [12, 7], [10, 3]], "image_size": (640, 480), "levels": [0, 0.5, 1, 2, 4, 8], "seeds": 2}
QUICK = {"sets": ["dino", [6, 7]], "image_size": (480, 360), "levels": [0, 2], "seeds": 2}
#: One of our rows' accurate fraction may be this much below pycolmap's (0.5 points) and still meet the goal.
FRACTION_SLACK = 0.005

PYCOLMAP = "(a) pycolmap extract + match_exhaustive"
#: label -> (features, refine_poses)
OURS = {
    "(b) ours on COLMAP's features, default": ("database", False),
    "(c) ours on COLMAP's features, refine_poses=True": ("database", True),
    "(d) ours end to end, default": ("collection", False),
    "(e) ours end to end, refine_poses=True": ("collection", True),
}
METHODS = [PYCOLMAP, *OURS]
#: How each triangulation is named in the tables and the JSON.
TRIANGULATIONS = {"true": "triangulated with the true poses (the matching alone)",
                  "used": "triangulated with the poses the method used, up to the frame (what a user gets)"}


def progress(msg: str) -> None:
    print(f"[noisy_poses {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _seed(level: float, s: int) -> list:
    """The noise seed of a level (in thousandths of a pixel) and a repetition."""
    return [int(round(1000 * level)), s]


def _rot_stats(views, true_views) -> dict:
    e = noise.relative_rotation_errors(views, true_views)
    return {"median": float(np.median(e)), "max": float(e.max())}


def load_set(spec, cfg: dict, work: Path, data_dir: Path):
    """``(name, true views, image folder, quality function, typical depth per view)``, or None (no dino)."""
    from episeg_cv import colmap, scenes

    if spec == "dino":
        folder = sets.find_dino(data_dir)
        if folder is None:
            return None
        views = colmap.load_par(folder / sets.DINO_PAR, folder)
        masks = sets.dino_masks(folder, [v.name for v in views])
        return ("dinoSparseRing (real)", views, folder,
                lambda rec: sets.dino_quality(rec, views, masks), noise.box_depths(views, sets.DINO_BOX))
    n, seed = spec
    c = scenes.make_collection(n, cfg["image_size"], seed=seed)
    paths = colmap.save_collection(c, work / f"room{n}_s{seed}")
    views, _ = colmap.load_model(paths["model"])
    return (f"room, {n} views, seed {seed} (synthetic)", views, paths["images"],
            lambda rec: quality(rec, c), noise.median_depths(c.depths))


def run_set(name, true_views, image_dir, quality_fn, depths, cfg: dict, work: Path) -> dict:
    """Every method at every noise level and seed on one collection."""
    import pycolmap

    from episeg_cv import colmap

    work.mkdir(parents=True, exist_ok=True)

    def triangulate(db, views, tag):
        rec = sets.triangulate_with(db, views, image_dir, work / tag, {})
        shutil.rmtree(work / tag, ignore_errors=True)
        return rec

    def judged_up_to_frame(rec, true_tracks) -> dict:
        """Quality of ``rec`` moved by the similarity that best takes its points onto those triangulated from the
        same database with the true poses (``true_tracks``); and in its own frame (``given_frame``)."""
        given_frame = quality_fn(rec)
        A, B = noise.corresponding_points(noise.tracks(rec), true_tracks)
        if len(A) < 3:
            return {**given_frame, "given_frame": given_frame, "similarity": None}
        s, Q, c = noise.trimmed_similarity(A, B)
        rec.transform(pycolmap.Sim3d(s, pycolmap.Rotation3d(Q), c))
        return {**quality_fn(rec), "given_frame": given_frame, "similarity": {
            "points": len(A), "scale": s, "rotation_deg": rotation_angle_deg(Q),
            "translation": float(np.linalg.norm(c))}}

    features_db = work / "colmap_features.db"
    seconds_extract = sets.pycolmap_extract(true_views, image_dir, features_db, MAX_FEATURES)
    pyc_db = work / "pycolmap.db"
    shutil.copyfile(features_db, pyc_db)
    pyc = {"seconds_matching": sets.pycolmap_exhaustive(pyc_db), "seconds_extract": seconds_extract}
    rec = triangulate(pyc_db, true_views, "pyc_true")
    pyc["true"], pyc_tracks = quality_fn(rec), noise.tracks(rec)
    progress(f"{name}: pycolmap {pyc['true']['accurate']} accurate of {pyc['true']['points']}")
    # our features once, outside every timed row (they do not depend on the poses)
    colmap.match_model(true_views, image_dir, work / "warm.db", cache_dir=work / "cache", log=lambda m: None)
    rows = []
    for level in cfg["levels"]:
        for s in range(cfg["seeds"] if level > 0 else 1):
            seed = _seed(level, s)
            given = noise.perturb_views(true_views, level, depths, seed) if level > 0 else list(true_views)
            base = {"level": level, "seed": seed, "rotation_error_given": _rot_stats(given, true_views)}
            rows.append({**base, "method": PYCOLMAP, "true": pyc["true"],
                         "used": judged_up_to_frame(triangulate(pyc_db, given, "pyc_used"), pyc_tracks)})
            for label, (features, refine_poses) in OURS.items():
                db = work / f"{len(rows)}.db"
                if features == "database":
                    shutil.copyfile(features_db, db)
                notes = []
                t0 = time.perf_counter()
                report = colmap.match_model(given, image_dir, db, features=features, log=notes.append,
                                            cache_dir=work / ("cache_db" if features == "database" else "cache"),
                                            **({"refine_poses": True} if refine_poses else {}))
                row = {**base, "method": label, "seconds_match_model": time.perf_counter() - t0,
                       "band": report.band, "warnings": notes}
                used = given
                if refine_poses:
                    P = report.poses
                    used = list(P.views)
                    row["refinement"] = {"rounds": int(P.rounds), "changes_px": [float(x) for x in P.changes_px],
                                         "points": [int(x) for x in P.points], "converged": bool(P.converged),
                                         "seconds": float(P.seconds),
                                         "rotation_error_refined": _rot_stats(used, true_views)}
                rec = triangulate(db, true_views, f"{len(rows)}_true")
                row["true"] = quality_fn(rec)
                row["used"] = judged_up_to_frame(triangulate(db, used, f"{len(rows)}_used"), noise.tracks(rec))
                db.unlink()
                rows.append(row)
                progress(f"{name}, {level} px seed {seed}, {label}: {row['true']['accurate']} accurate "
                         f"({100 * row['true']['accurate_fraction']:.1f} %) with the true poses, "
                         f"{row['used']['accurate']} ({100 * row['used']['accurate_fraction']:.1f} %) with its own; "
                         f"{row['seconds_match_model']:.1f} s")
    v0 = true_views[0]
    return {"n_views": len(true_views), "n_pairs": len(true_views) * (len(true_views) - 1) // 2,
            "focal_px": float(v0.K[0, 0]), "depths": [float(z) for z in depths], "pycolmap": pyc, "rows": rows}


# --------------------------------------------------------------------------------------
# Goals and report
# --------------------------------------------------------------------------------------
def _rows(s: dict, method: str, level) -> list:
    return [r for r in s["rows"] if r["method"] == method and r["level"] == level]


def meets(s: dict, method: str, level, tri: str) -> bool:
    """Whether every seed of ``method`` at ``level`` keeps >= pycolmap's accurate points (same level and seed)
    at a fraction no more than :data:`FRACTION_SLACK` below pycolmap's."""
    ours = _rows(s, method, level)
    if not ours:
        raise ValueError(f"no rows of {method!r} at {level} px")
    pyc = {tuple(r["seed"]): r[tri] for r in _rows(s, PYCOLMAP, level)}
    return all(r[tri]["accurate"] >= pyc[tuple(r["seed"])]["accurate"] and
               r[tri]["accurate_fraction"] >= pyc[tuple(r["seed"])]["accurate_fraction"] - FRACTION_SLACK
               for r in ours)


def goals(res: dict) -> list:
    """``[(method, tri, {set: [levels met]}, levels met on every set, highest level up to which all are met)]``."""
    out = []
    levels = res["config"]["levels"]
    for method in OURS:
        for tri in TRIANGULATIONS:
            per = {name: [lv for lv in levels if meets(s, method, lv, tri)] for name, s in res["sets"].items()}
            every = [lv for lv in levels if all(lv in m for m in per.values())]
            upto = None
            for lv in levels:
                if lv not in every:
                    break
                upto = lv
            out.append((method, tri, per, every, upto))
    return out


def _lv(levels) -> str:
    return ", ".join(f"{lv:g}" for lv in levels) + " px" if levels else "none"


def summary(res: dict) -> list:
    """The goals paragraph, from the numbers: per triangulation, up to which level each of ours meets the goal."""
    G = {(m, tri): upto for m, tri, per, every, upto in goals(res)}

    def upto(method, tri):
        up = G[(method, tri)]
        return "none (not even exact poses)" if up is None else f"**{up:g} px**"

    L = []
    for tri, what in TRIANGULATIONS.items():
        same, same_r, e2e, e2e_r = OURS
        L.append(f"- **{what[0].upper() + what[1:]}.** The goal (at least pycolmap's accurate points, the fraction "
                 f"at most {100 * FRACTION_SLACK:.1f} points below its) holds on every collection and every seed at "
                 f"every level from exact poses up to: the defaults: {upto(same, tri)} on COLMAP's features, "
                 f"{upto(e2e, tri)} end to end; `refine_poses=True`: {upto(same_r, tri)} and {upto(e2e_r, tri)}. "
                 "The levels met per collection are in the table below.")
    return L


def _mm(rows, tri, key, scale=1.0, d=0) -> str:
    xs = [scale * r[tri][key] for r in rows]
    if len(xs) == 1:
        return f"{xs[0]:.{d}f}"
    return f"{min(xs):.{d}f} / {np.mean(xs):.{d}f}"


def _f(v, d=2):
    return "n/a" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{d}f}"


def markdown(res: dict) -> list:
    meta, cfg = res["machine"], res["config"]
    L = ["# Posed collections with pose errors: accurate 3D points of `match_model`, with and without "
         "`refine_poses`\n"]
    dirty = ", with uncommitted changes in episeg_cv/" if meta.get("episeg_cv_uncommitted_changes") else ""
    changed = "" if res["code_unchanged"] else "; **the library changed during the run**"
    L.append(f"Made by `{res['command']}` on {meta['date']} in {res['wall_time_s']:.0f} s ({meta['cpu']}, "
             f"{meta['cpu_count']} cores, {meta['platform']}, python {meta['python']}, numpy {meta['numpy']}, cv2 "
             f"{meta['cv2']}, pycolmap {res['pycolmap_version']}, episeg_cv {meta['episeg_cv']}, git HEAD "
             f"{meta['git_commit']} at the start{dirty}{changed}). Load average (1 min) {res['load_average'][0]:.2f} "
             f"at the start, {res['load_average'][1]:.2f} at the end. Raw numbers in `noisy_poses.json`.\n")
    L.append("## Protocol\n")
    L.append("- **Noise in pixels**, so that a level means the same on every lens (`benchmarks/_noisy_poses.py`). "
             "Each view's pose gets a rotation error of angle `theta` about a random axis, applied in the camera "
             "frame, and its camera centre moves by `d` in a random direction, with `f theta = p` and "
             "`f d / z = p` pixels (`f = K[0, 0]`; `z` the view's typical depth: on dinoSparseRing the distance "
             "from the camera centre to the centre of the object's bounding box (its README), on the rooms the "
             "median rendered depth). A sideways move of `d` shifts points at depth `z` by `p` px; the part "
             "along the viewing direction less. Levels `p` = " + ", ".join(f"{lv:g}" for lv in cfg["levels"]) +
             f" px; {cfg['seeds']} seeds per noisy level (seed `[1000 p, s]` for repetition `s`, the same on every "
             "collection); tables give min / mean over the seeds where there are several.")
    L.append(f"- **Methods.** {PYCOLMAP}: `extract_features` (one PINHOLE camera with the true intrinsics, "
             f"{MAX_FEATURES} features, CPU) + `match_exhaustive` (COLMAP's defaults, RANSAC verification): it "
             "ignores the poses, so it is matched once per collection. Ours: `colmap.match_model(views, images, "
             "db, ...)` with the noisy poses given as a list of `View` (no 3D points, so no depth range: as a user "
             "with odometry poses has), every other setting the default (`tol=\"auto\"`, the track consensus, all "
             "cores); (b)/(c) on a copy of pycolmap's features database (`features=\"database\"`), (d)/(e) with our "
             "own features (the `\"collection\"` preset, computed once per collection before the timed rows). "
             "(c)/(e) add `refine_poses=True`: rounds of matching, triangulation, bundle adjustment of the poses "
             "with fixed intrinsics and a similarity back to the given frame, then the matching with the refined "
             "poses.")
    L.append("- **Triangulation.** Every database is triangulated by `pycolmap.triangulate_points` with COLMAP's "
             "default options (two-view tracks ignored, minimum angle 1.5°) twice: with the **true** poses, which "
             "isolates the matching, and with the poses **used** by the method: the noisy ones for (a), (b), (d), "
             "the refined ones (`MatchReport.poses.views`) for (c), (e). A model triangulated with the used "
             "poses is in their frame (the given one; the refined poses are taken back to it by a similarity), "
             "off the true one by what the noise has in common over the views, which no method can recover "
             "from the poses alone; so it is first moved by the similarity that best takes its 3D points onto "
             "those that the true poses triangulate from the same database (points paired by a shared keypoint; "
             "least squares over the half of the pairs it fits best, so that wrong matches triangulated far off "
             "do not pull it: `_noisy_poses.corresponding_points`, `trimmed_similarity`): what is judged is the "
             "shape of the model, not where the given poses put it. The tables give the accurate points in the "
             "given frame too. Accuracy is always judged with the true poses: on the rooms a point is accurate "
             "when it is within 1 % of the rendered depth in every image of its track (`benchmarks/colmap.py`'s "
             "`quality`), on dinoSparseRing when it lies in the bounding box and on the object's silhouette in "
             "every view (`_colmap_sets.dino_quality`).")
    L.append("- **Goal** (per collection, level and seed, against pycolmap triangulated the same way with the same "
             f"poses): at least pycolmap's accurate points, at an accurate fraction no more than "
             f"{100 * FRACTION_SLACK:.1f} points below pycolmap's. A level is met when every seed meets it.")
    L.append("- **Times** are the wall time of the `match_model` call on a shared machine: the cost of the "
             "refinement, not a speed claim.\n")
    if res["missing_sets"]:
        L.append(f"**dinoSparseRing not found** under `{res['data_dir']}`: skipped (pass `--data DIR`).\n")
    L.append("## Goals, from these numbers\n")
    L.extend(summary(res))
    L.append("")
    L.append("| method | triangulated with | " + " | ".join(n.split(" (")[0] for n in res["sets"]) +
             " | every collection |")
    L.append("|---|---|" + "---|" * (len(res["sets"]) + 1))
    for method, tri, per, every, upto in goals(res):
        L.append(f"| {method} | {tri} poses | " + " | ".join(_lv(m) for m in per.values()) + f" | {_lv(every)} |")
    L.append("")
    for name, s in res["sets"].items():
        depth = np.array(s["depths"])
        L.append(f"## {name}: {s['n_views']} views, {s['n_pairs']} pairs\n")
        L.append(f"f = {s['focal_px']:.0f} px, typical depth {depth.min():.3g}-{depth.max():.3g}: 1 px of noise "
                 f"is {np.degrees(1 / s['focal_px']):.4f}° of rotation and {1000 * depth.min() / s['focal_px']:.3g}-"
                 f"{1000 * depth.max() / s['focal_px']:.3g} thousandths of a world unit of camera centre. "
                 f"pycolmap: matching {s['pycolmap']['seconds_matching']:.2f} s.\n")
        levels = cfg["levels"]
        for tri, what in TRIANGULATIONS.items():
            used = tri == "used"
            L.append(f"### Accurate points, {what}\n")
            L.append("| noise (px) | method | accurate (min / mean) | points (mean) | fraction % (min / mean) | "
                     + ("accurate in the given frame (mean) | " if used else "") + "goal met |")
            L.append("|---:|---|---:|---:|---:|" + ("---:|" if used else "") + "---|")
            for lv in levels:
                for m in METHODS:
                    rows = _rows(s, m, lv)
                    if not rows:
                        continue
                    met = "" if m == PYCOLMAP else ("**yes**" if meets(s, m, lv, tri) else "no")
                    given = f"{np.mean([r[tri]['given_frame']['accurate'] for r in rows]):.0f} | " if used else ""
                    L.append(f"| {lv:g} | {m} | {_mm(rows, tri, 'accurate')} | "
                             f"{np.mean([r[tri]['points'] for r in rows]):.0f} | "
                             f"{_mm(rows, tri, 'accurate_fraction', 100, 1)} | {given}{met} |")
            L.append("")
        refined = [r for r in s["rows"] if "refinement" in r]
        if refined:
            L.append("### The refinement\n")
            L.append("Per seed: rounds, the last round's largest effect of its pose change (px), 3D points per "
                     "round, whether it converged; the wall time of `match_model` with the default and with "
                     "`refine_poses=True`; the relative-rotation error over all pairs against the true poses "
                     "(degrees, median / max) of the given and of the refined poses (`match_model` keeps the "
                     "given poses when the refinement does not converge).\n")
            L.append("| noise (px) | seed | features | rounds | last change (px) | points per round | converged | "
                     "match_model s (default / refine) | rotation error given (°) | refined (°) |")
            L.append("|---:|---|---|---:|---:|---|---|---:|---:|---:|")
            for r in refined:
                R = r["refinement"]
                features = OURS[r["method"]][0]
                default = next(x for x in s["rows"] if x["level"] == r["level"] and x["seed"] == r["seed"]
                               and OURS.get(x["method"]) == (features, False))
                g, e = r["rotation_error_given"], R["rotation_error_refined"]
                L.append(f"| {r['level']:g} | {r['seed'][1]} | {'COLMAP' if features == 'database' else 'ours'} | "
                         f"{R['rounds']} | {_f(R['changes_px'][-1] if R['changes_px'] else None, 3)} | "
                         f"{', '.join(str(p) for p in R['points'])} | {'yes' if R['converged'] else 'no'} | "
                         f"{default['seconds_match_model']:.1f} / {r['seconds_match_model']:.1f} | "
                         f"{g['median']:.4f} / {g['max']:.4f} | {e['median']:.4f} / {e['max']:.4f} |")
            L.append("")
    return L


# --------------------------------------------------------------------------------------
def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="dino and a 6-view room at 480x360, levels 0 and 2 px")
    p.add_argument("--out", type=Path, default=None,
                   help="output directory (default benchmarks/results; benchmarks/results/quick with --quick)")
    p.add_argument("--keep", type=Path, default=None, help="keep the work folder (images, databases) here")
    p.add_argument("--data", type=Path, default=DATA,
                   help="folder holding dinoSparseRing/ (default: <repo>/../shared/data)")
    return p.parse_args(argv)


def main(argv=None) -> int:
    import pycolmap

    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(argv)
    cfg = dict(QUICK if args.quick else FULL)
    command = " ".join(["python", SCRIPT] + [shlex.quote(a) for a in argv])
    load0 = os.getloadavg()[0]
    meta = machine_metadata()
    meta["episeg_cv_uncommitted_changes"] = package_dirty()
    progress(f"{command}: {cfg}")
    t0 = time.perf_counter()
    if args.keep:
        args.keep.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="noisy_poses_", dir=args.keep))
    out_sets, missing = {}, []
    try:
        for k, spec in enumerate(cfg["sets"]):
            loaded = load_set(spec, cfg, work, args.data)
            if loaded is None:
                missing.append(str(spec))
                progress(f"NOTE: dinoSparseRing not found under {args.data}; skipped (--data DIR)")
                continue
            name, views, image_dir, quality_fn, depths = loaded
            out_sets[name] = run_set(name, views, image_dir, quality_fn, depths, cfg, work / f"set{k}")
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    end = {"git_commit": machine_metadata()["git_commit"], "episeg_cv_uncommitted_changes": package_dirty()}
    unchanged = (end["git_commit"], end["episeg_cv_uncommitted_changes"]) == \
        (meta["git_commit"], meta["episeg_cv_uncommitted_changes"]) and not end["episeg_cv_uncommitted_changes"]
    if not unchanged:
        progress("WARNING: episeg_cv changed during or before the run; rerun on a clean tree")
    meta["at_the_end"] = end
    res = {"command": command, "machine": meta, "load_average": [load0, os.getloadavg()[0]],
           "pycolmap_version": pycolmap.__version__, "code_unchanged": unchanged,
           "config": {**cfg, "image_size": list(cfg["image_size"]), "max_features": MAX_FEATURES,
                      "fraction_slack": FRACTION_SLACK},
           "missing_sets": missing, "data_dir": str(args.data), "sets": out_sets,
           "wall_time_s": time.perf_counter() - t0}
    res["goals"] = [{"method": m, "triangulation": tri, "levels_met": per, "levels_met_everywhere": every,
                     "met_from_0_up_to": upto} for m, tri, per, every, upto in goals(res)]
    args.out = args.out or (RESULTS / "quick" if args.quick else RESULTS)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "noisy_poses.json").write_text(json.dumps(res, indent=1, default=float) + "\n")
    (args.out / "noisy_poses.md").write_text("\n".join(markdown(res)) + "\n")
    progress(f"wrote {args.out / 'noisy_poses.md'} and noisy_poses.json in {res['wall_time_s']:.0f} s")
    for line in summary(res):
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
