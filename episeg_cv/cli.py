"""The ``episeg`` command: a thin layer over the public API.

Subcommands
-----------
``episeg demo [--out DIR]``
    Segment- vs line-guided matching on the bundled default pair, scored
    against its ground truth; writes ``matches.png``, ``segments.png`` and
    ``matches.json``.
``episeg match IMG1 IMG2 --calib FILE [...]``
    Detect, match under the segment (or line, or no) constraint, and write the
    matches as JSON, NPZ or CSV, and a figure.
``episeg segments IMG1 IMG2 --calib FILE [--points x,y ...] [--random N]``
    The paper's figure for chosen points.
``episeg bench [--quick]``
    Run the scripts of ``benchmarks/`` (source checkout only).
``episeg colmap MODEL IMAGE_DIR --database DB [...]``
    Match every pair of a posed collection (a COLMAP model or a poses JSON)
    on its epipolar segments and write a COLMAP database
    (:func:`episeg_cv.colmap.match_model`); optionally triangulate it.
``episeg synthetic DIR [--views N]``
    Render a posed synthetic collection (images, COLMAP model, poses JSON)
    to try ``episeg colmap`` on.

Exit codes: 0 success, 1 bad data (missing or unreadable file, bad
calibration), 2 usage errors. Errors print one line on stderr, no traceback.

The matches file (``--out``, format ``episeg-matches`` version 1)
-----------------------------------------------------------------
JSON::

    {"meta": {"format": "episeg-matches", "format_version": 1, "command", "episeg_cv", "opencv",
              "numpy", "image1", "image2", "calib", "convention", "undistorted",
              "settings": {...}, "counts": {"keypoints1", "keypoints2", "matches", <label>: n, ...}},
     "keypoints1": [[x, y], ...],          # as detected, pixels of the input image 1
     "keypoints2": [[x, y], ...],
     "matches": [[i1, i2], ...],           # indices into keypoints1 / keypoints2
     "distances": [d, ...],                # descriptor distances, as cv2.BFMatcher reports
     "labels": ["on_segment", ...]}        # Rejection.NAMES of each match (episeg_cv.explain_pairs)

With lens distortion, ``keypoints1_undistorted`` and ``keypoints2_undistorted``
(the positions the constraint used) are added. ``.npz`` holds the same names as
arrays (``meta`` as a JSON string); ``.csv`` has one row per match with the
header ``x1,y1,x2,y2,distance,label``.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

__all__ = ["main", "write_matches", "read_matches"]

PROG = "episeg"
FORMAT = "episeg-matches"
FORMAT_VERSION = 1
BENCH_SCRIPTS = ("table1.py", "compare.py", "speed.py")
#: Lines drawn in the match figures (a random subset; the legend gives the full counts).
MAX_LINES = 300


class UserError(Exception):
    """Bad input from the user (exit code 1)."""


# --------------------------------------------------------------------------------------
# Console output
# --------------------------------------------------------------------------------------
class _Console:
    """stdout for results, stderr for progress and notes; ``--quiet`` / ``--verbose``."""

    def __init__(self, quiet: bool = False, verbose: bool = False):
        self.quiet, self.verbose = quiet, verbose and not quiet
        self.tty = sys.stderr.isatty()

    def print(self, *args):
        if not self.quiet:
            print(*args, flush=True)

    def info(self, msg: str):
        if self.verbose:
            print(f"{PROG}: {msg}", file=sys.stderr, flush=True)

    def progress(self, total: int, desc: str) -> "_Progress":
        return _Progress(self, total, desc)


class _Progress:
    """A small progress bar on stderr: redrawn in place on a terminal, one line per step with --verbose."""

    def __init__(self, console: _Console, total: int, desc: str):
        self.c, self.total, self.desc, self.n, self.t0 = console, max(int(total), 1), desc, 0, time.perf_counter()
        self.on = not console.quiet and (console.tty or console.verbose)

    def step(self, what: str = ""):
        self.n += 1
        if not self.on:
            return
        frac = min(self.n / self.total, 1.0)
        bar = "#" * int(round(24 * frac)) + "." * (24 - int(round(24 * frac)))
        line = f"{self.desc} [{bar}] {self.n}/{self.total} {time.perf_counter() - self.t0:5.1f}s {what}"
        if self.c.tty:
            end = "\n" if self.n >= self.total else ""
            print("\r" + line[:100].ljust(100), end=end, file=sys.stderr, flush=True)
        else:
            print(f"{PROG}: {line}", file=sys.stderr, flush=True)

    def close(self):
        if self.on and self.c.tty and self.n < self.total:
            print(file=sys.stderr, flush=True)


# --------------------------------------------------------------------------------------
# Helpers shared by the subcommands
# --------------------------------------------------------------------------------------
def _read_image(path) -> np.ndarray:
    p = Path(path)
    if not p.is_file():
        raise UserError(f"image not found: {p}")
    img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise UserError(f"cannot read image {p} (not an image format OpenCV can decode)")
    return img


def _size(img) -> tuple[int, int]:
    return int(img.shape[1]), int(img.shape[0])


def make_detector(name: str, max_features: int):
    """``(detector, norm)`` for ``sift``, ``orb`` or ``akaze`` (OpenCV 4 or 5), with OpenCV's default settings."""
    from .collection import create_detector

    return create_detector(name, max_features, sift_contrast=None), cv2.NORM_L2 if name == "sift" else cv2.NORM_HAMMING


def detect(detector, image, max_features: int):
    """Keypoints and descriptors, at most ``max_features`` (strongest responses kept)."""
    kps = detector.detect(image, None)
    if len(kps) > max_features:
        order = np.argsort([-k.response for k in kps], kind="stable")[:max_features]
        kps = [kps[i] for i in np.sort(order)]
    kps, des = detector.compute(image, kps)
    kps = list(kps)
    if des is None:
        des = np.zeros((0, 128 if isinstance(detector, cv2.SIFT) else 32),
                       np.float32 if isinstance(detector, cv2.SIFT) else np.uint8)
    return kps, des


def _pairs(dmatches) -> tuple[np.ndarray, np.ndarray]:
    from .opencv import _pairs_of

    return _pairs_of(dmatches), np.array([m.distance for m in dmatches], dtype=np.float32)


def ratio_matches(knn, ratio: float):
    """Lowe's ratio test on ``knnMatch(k=2)`` output."""
    return [m[0] for m in knn if len(m) >= 2 and m[0].distance < ratio * m[1].distance]


def run_matching(geometry, des1, des2, pts1, pts2, norm, *, constraint="segment", tol=2.0,
                 depth_range=(0.0, np.inf), cross_check=False, ratio=None):
    """``(pairs, distances)`` with :class:`~episeg_cv.SegmentMatcher`.

    ``constraint="none"`` is plain ``cv2.BFMatcher``: ``knnMatch(k=2)`` and the
    ratio test, or ``match`` with ``crossCheck`` (as OpenCV offers them).
    """
    from .matching import DEFAULT_RATIO
    from .opencv import SegmentMatcher

    ratio = DEFAULT_RATIO if ratio is None else ratio
    m = SegmentMatcher(geometry, norm, cross_check, tol=tol, depth_range=depth_range, constraint=constraint,
                       ratio=ratio)
    if len(des1) == 0 or len(des2) == 0:
        return np.zeros((0, 2), np.intp), np.zeros(0, np.float32)
    if constraint == "none":
        dm = m.match(des1, des2, pts1, pts2) if cross_check else ratio_matches(m.knnMatch(des1, des2, pts1, pts2, 2), ratio)
    else:
        dm = m.match(des1, des2, pts1, pts2)
    return _pairs(dm)


def _labels(pairs, pts1, pts2, geometry, tol, depth_range):
    from .geometry import Rejection
    from .matching import explain_pairs

    codes, counts = explain_pairs(pairs, pts1, pts2, geometry, tol=tol, depth_range=depth_range)
    return [Rejection.NAMES[c] for c in codes], counts


def _versions() -> dict:
    from . import __version__

    return {"episeg_cv": __version__, "opencv": cv2.__version__, "numpy": np.__version__}


def _json_number(x):
    x = float(x)
    return x if np.isfinite(x) else None


def write_matches(path, meta: dict, keypoints1, keypoints2, matches, distances, labels, extra=None) -> Path:
    """Write a matches file in the documented format; the suffix picks JSON, NPZ or CSV.

    Parameters
    ----------
    path : str or os.PathLike
        ``*.json``, ``*.npz`` or ``*.csv``.
    meta : dict
        Settings, versions and counts (JSON-serialisable).
    keypoints1, keypoints2 : (N1, 2), (N2, 2) float
    matches : (K, 2) int
    distances : (K,) float
    labels : sequence of str, length K
    extra : dict of str to (N, 2) arrays, optional
        More keypoint arrays (e.g. ``keypoints1_undistorted``); JSON and NPZ only.

    Returns
    -------
    pathlib.Path
    """
    path = Path(path)
    k1 = np.asarray(keypoints1, np.float64).reshape(-1, 2)
    k2 = np.asarray(keypoints2, np.float64).reshape(-1, 2)
    m = np.asarray(matches, np.int64).reshape(-1, 2)
    d = np.asarray(distances, np.float64).reshape(-1)
    labels = [str(x) for x in labels]
    if not (len(m) == len(d) == len(labels)):
        raise ValueError(f"matches, distances and labels must have the same length, got {len(m)}, {len(d)}, {len(labels)}")
    extra = extra or {}
    suffix = path.suffix.lower()
    if path.parent != Path(""):
        path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".json":
        out = {"meta": meta, "keypoints1": np.round(k1, 4).tolist(), "keypoints2": np.round(k2, 4).tolist(),
               "matches": m.tolist(), "distances": [round(float(x), 5) for x in d], "labels": labels}
        out.update({k: np.round(np.asarray(v, np.float64), 4).tolist() for k, v in extra.items()})
        path.write_text(json.dumps(out, separators=(",", ":")) + "\n")
    elif suffix == ".npz":
        np.savez_compressed(path, meta=np.array(json.dumps(meta)), keypoints1=k1, keypoints2=k2, matches=m,
                            distances=d.astype(np.float32), labels=np.array(labels, dtype="U16"),
                            **{k: np.asarray(v, np.float64) for k, v in extra.items()})
    elif suffix == ".csv":
        with path.open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["x1", "y1", "x2", "y2", "distance", "label"])
            for (i, j), dist, lab in zip(m, d, labels):
                w.writerow([f"{k1[i, 0]:.4f}", f"{k1[i, 1]:.4f}", f"{k2[j, 0]:.4f}", f"{k2[j, 1]:.4f}",
                            f"{dist:.5g}", lab])
    else:
        raise UserError(f"--out must end in .json, .npz or .csv, got {path.name!r}")
    return path


def read_matches(path) -> dict:
    """Read a ``.json`` or ``.npz`` matches file back into arrays (``meta`` as a dict)."""
    path = Path(path)
    if path.suffix.lower() == ".npz":
        with np.load(path) as z:
            out = {k: z[k] for k in z.files}
        out["meta"] = json.loads(str(out["meta"]))
        return out
    data = json.loads(path.read_text())
    out = {"meta": data["meta"], "labels": np.array(data["labels"], dtype="U16"),
           "matches": np.array(data["matches"], np.intp).reshape(-1, 2),
           "distances": np.array(data["distances"], np.float64)}
    for k, v in data.items():
        if k.startswith("keypoints"):
            out[k] = np.array(v, np.float64).reshape(-1, 2)
    return out


def _depth_range(values):
    if values is None:
        return (0.0, np.inf)
    zmin, zmax = values
    from ._validation import as_depth_range

    as_depth_range((zmin, zmax), None, "--depth-range")
    return (zmin, zmax)


def _load_calib(path, img1, img2, console: _Console):
    from .calib import load_calibration

    calib = load_calibration(path, image_size1=_size(img1), image_size2=_size(img2))
    console.info(f"calibration {path}: image sizes {calib.image_size1} and {calib.image_size2}, "
                 f"distortion {'yes' if calib.has_distortion else 'no'}")
    return calib


# --------------------------------------------------------------------------------------
# demo
# --------------------------------------------------------------------------------------
def _spread_choice(points, n, size, rng):
    """Up to ``n`` indices of ``points`` spread over the image: one per cell of a grid, at random."""
    if len(points) == 0:
        return np.zeros(0, np.intp)
    cols = max(1, int(round(np.sqrt(n * size[0] / size[1]))))
    rows = max(1, int(np.ceil(n / cols)))
    cx = np.clip((points[:, 0] / size[0] * cols).astype(int), 0, cols - 1)
    cy = np.clip((points[:, 1] / size[1] * rows).astype(int), 0, rows - 1)
    cell = cy * cols + cx
    chosen = [rng.choice(np.flatnonzero(cell == c)) for c in np.unique(cell)]
    chosen = rng.permutation(np.array(chosen, np.intp))[:n]
    return np.sort(chosen)


def cmd_demo(args, console: _Console) -> int:
    from .datasets import load_default_pair
    from .drawing import draw_matches, draw_segment_figure, save_image
    from .opencv import SegmentMatcher, keypoints_to_array

    out = Path(args.out)
    prog = console.progress(7, "demo")
    pair = load_default_pair()
    geom = pair.geometry
    prog.step("loaded the default pair")
    sift, norm = make_detector("sift", args.max_features)
    kp1, des1 = detect(sift, pair.image1, args.max_features)
    kp2, des2 = detect(sift, pair.image2, args.max_features)
    p1, p2 = keypoints_to_array(kp1), keypoints_to_array(kp2)
    gt = pair.ground_truth(p1, p2)
    prog.step(f"SIFT: {len(kp1)} and {len(kp2)} keypoints")

    results = {}
    knn = cv2.BFMatcher(norm).knnMatch(des1, des2, k=2)
    bf = ratio_matches(knn, 0.8)
    results["BFMatcher + ratio 0.8"] = _pairs(bf)
    line_filter = SegmentMatcher(geom, norm, constraint="line", tol=args.tol)
    results["BFMatcher + ratio 0.8 + line filter"] = _pairs(line_filter.filter(bf, p1, p2))
    prog.step("BFMatcher baseline")
    t_line = time.perf_counter()
    results["line-guided (SegmentMatcher, constraint='line')"] = run_matching(geom, des1, des2, p1, p2, norm,
                                                                                constraint="line", tol=args.tol)
    t_line = time.perf_counter() - t_line
    prog.step("line-guided matching")
    t_seg = time.perf_counter()
    seg_pairs, seg_dist = run_matching(geom, des1, des2, p1, p2, norm, constraint="segment", tol=args.tol)
    t_seg = time.perf_counter() - t_seg
    results["segment-guided (SegmentMatcher, constraint='segment')"] = (seg_pairs, seg_dist)
    prog.step("segment-guided matching")
    console.info(f"line-guided {t_line:.2f}s, segment-guided {t_seg:.2f}s")

    rows = []
    for name, (pairs, _) in results.items():
        ok = gt.is_correct(pairs)
        rows.append((name, len(pairs), int(ok.sum()), ok.mean() if len(ok) else float("nan"),
                     ok.sum() / max(gt.num_matchable, 1)))
    console.print(f"Default pair '{pair.name}': {len(kp1)} / {len(kp2)} SIFT keypoints, "
                  f"{gt.num_matchable} with a true match (ground truth from the depth maps).")
    console.print(_table(["method", "matches", "correct", "precision", "recall"],
                         [(n, str(m), str(c), f"{p:.1%}", f"{r:.1%}") for n, m, c, p, r in rows]))

    # files
    seg_ok = gt.is_correct(seg_pairs)
    labels, counts = _labels(seg_pairs, p1, p2, geom, args.tol, (0.0, np.inf))
    meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "command": "demo", **_versions(),
            "image1": f"{pair.name}: image1", "image2": f"{pair.name}: image2", "calib": "bundled default pair",
            "convention": "X2 = R X1 + t; pixel centres at integer coordinates",
            "undistorted": False,
            "settings": {"detector": "sift", "max_features": args.max_features, "constraint": "segment",
                         "tol": args.tol, "depth_range": [0.0, None], "cross_check": False},
            "counts": {"keypoints1": len(p1), "keypoints2": len(p2), "matches": len(seg_pairs),
                       "correct": int(seg_ok.sum()), "matchable": gt.num_matchable, **counts},
            "comparison": [{"method": n, "matches": m, "correct": c, "precision": _json_number(p),
                            "recall": _json_number(r)} for n, m, c, p, r in rows]}
    written = [write_matches(out / "matches.json", meta, p1, p2, seg_pairs, seg_dist, labels)]
    written.append(save_image(out / "matches.png", draw_matches(pair.image1, pair.image2, p1, p2, seg_pairs, seg_ok,
                                                                 max_lines=MAX_LINES, rng=args.seed)))
    prog.step("matches figure")
    rng = np.random.default_rng(args.seed)
    pick = _spread_choice(p1[seg_pairs[:, 0]], args.points, geom.image_size1, rng) if len(seg_pairs) else []
    sel = seg_pairs[pick] if len(seg_pairs) else np.zeros((0, 2), np.intp)
    q1 = p1[sel[:, 0]]
    fig = draw_segment_figure(pair.image1, pair.image2, q1, geom.segments(q1), p2[sel[:, 1]], seg_ok[pick])
    written.append(save_image(out / "segments.png", fig))
    prog.step("segments figure")
    prog.close()
    for w in written:
        console.print(f"wrote {w}")
    return 0


def _table(header, rows) -> str:
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    fmt = lambda r: "  ".join(str(c).ljust(w) if i == 0 else str(c).rjust(w)  # noqa: E731
                              for i, (c, w) in enumerate(zip(r, widths)))
    return "\n".join([fmt(header), "  ".join("-" * w for w in widths), *map(fmt, rows)])


# --------------------------------------------------------------------------------------
# match
# --------------------------------------------------------------------------------------
def cmd_match(args, console: _Console) -> int:
    from .calib import undistort_points
    from .drawing import draw_matches, save_image
    from .opencv import keypoints_to_array

    if args.out is not None and Path(args.out).suffix.lower() not in (".json", ".npz", ".csv"):
        raise UserError(f"--out must end in .json, .npz or .csv, got {args.out!r}")
    from .matching import DEFAULT_RATIO

    depth_range = _depth_range(args.depth_range)
    ratio = DEFAULT_RATIO if args.ratio is None else args.ratio
    img1, img2 = _read_image(args.image1), _read_image(args.image2)
    calib = _load_calib(args.calib, img1, img2, console)
    geom = calib.geometry
    prog = console.progress(4 + (args.figure is not None), "match")
    det, norm = make_detector(args.detector, args.max_features)
    kp1, des1 = detect(det, img1, args.max_features)
    kp2, des2 = detect(det, img2, args.max_features)
    p1, p2 = keypoints_to_array(kp1), keypoints_to_array(kp2)
    prog.step(f"{args.detector}: {len(p1)} and {len(p2)} keypoints")
    u1, u2 = undistort_points(p1, calib.K1, calib.dist1), undistort_points(p2, calib.K2, calib.dist2)
    if calib.has_distortion:
        console.info("undistorted the keypoints with cv2.undistortPoints (P = K) before matching")
    prog.step("undistorted" if calib.has_distortion else "no distortion")
    pairs, dist = run_matching(geom, des1, des2, u1, u2, norm, constraint=args.constraint, tol=args.tol,
                               depth_range=depth_range, cross_check=args.cross_check, ratio=ratio)
    prog.step(f"{len(pairs)} matches")
    labels, counts = _labels(pairs, u1, u2, geom, args.tol, depth_range)
    prog.step("labelled")
    meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "command": "match", **_versions(),
            "image1": str(args.image1), "image2": str(args.image2), "calib": str(args.calib),
            "convention": "X2 = R X1 + t; pixel centres at integer coordinates",
            "undistorted": calib.has_distortion,
            "settings": {"detector": args.detector, "max_features": args.max_features, "constraint": args.constraint,
                         "tol": args.tol, "depth_range": [_json_number(z) for z in depth_range],
                         "cross_check": args.cross_check,
                         "ratio": None if args.constraint == "none" and args.cross_check else ratio},
            "counts": {"keypoints1": len(p1), "keypoints2": len(p2), "matches": len(pairs), **counts}}
    written = []
    if args.out is not None:
        extra = {"keypoints1_undistorted": u1, "keypoints2_undistorted": u2} if calib.has_distortion else None
        written.append(write_matches(args.out, meta, p1, p2, pairs, dist, labels, extra))
    if args.figure is not None:
        written.append(save_image(args.figure, draw_matches(img1, img2, p1, p2, pairs, max_lines=MAX_LINES, rng=0)))
        prog.step("figure")
    prog.close()
    on_line = counts["beyond_infinity"] + counts["beyond_epipole"] + counts["empty_segment"] + counts["out_of_range"]
    console.print(f"{len(p1)} / {len(p2)} keypoints ({args.detector}), {len(pairs)} matches "
                  f"(constraint {args.constraint}): {counts['on_segment']} on the segment, "
                  f"{on_line} on the line but off the segment, {counts['off_line']} off the line")
    for w in written:
        console.print(f"wrote {w}")
    if not written:
        console.print("(use --out matches.json|.npz|.csv and --figure FIG.png to save the result)")
    return 0


# --------------------------------------------------------------------------------------
# segments
# --------------------------------------------------------------------------------------
def _parse_point(text: str) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in text.replace(" ", "").split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a point must be written x,y (e.g. 120.5,80), got {text!r}") from None
    if not (np.isfinite(x) and np.isfinite(y)):
        raise argparse.ArgumentTypeError(f"a point must be finite, got {text!r}")
    return x, y


def cmd_segments(args, console: _Console) -> int:
    from .calib import undistort_points
    from .drawing import draw_segment_figure, save_image

    depth_range = _depth_range(args.depth_range)
    img1, img2 = _read_image(args.image1), _read_image(args.image2)
    calib = _load_calib(args.calib, img1, img2, console)
    geom = calib.geometry
    w, h = geom.image_size1
    if args.points:
        pts = np.array(args.points, dtype=np.float64).reshape(-1, 2)
        outside = ~((pts[:, 0] >= -0.5) & (pts[:, 0] <= w - 0.5) & (pts[:, 1] >= -0.5) & (pts[:, 1] <= h - 0.5))
        if outside.any():
            x, y = pts[outside][0]
            raise UserError(f"point {x:g},{y:g} is outside image 1 ({w}x{h})")
    else:
        rng = np.random.default_rng(args.seed)
        pts = np.column_stack([rng.uniform(0.05 * w, 0.95 * w, args.random), rng.uniform(0.05 * h, 0.95 * h, args.random)])
    if calib.has_distortion:  # the segments live in the pinhole images: draw on those
        pts = undistort_points(pts, calib.K1, calib.dist1)
        img1 = cv2.undistort(img1, calib.K1, calib.dist1, None, calib.K1) if calib.dist1 is not None else img1
        img2 = cv2.undistort(img2, calib.K2, calib.dist2, None, calib.K2) if calib.dist2 is not None else img2
        console.info("drew on the undistorted images (cv2.undistort with the same K)")
    seg = geom.segments(pts, depth_range)
    fig = draw_segment_figure(img1, img2, pts, seg)
    out = save_image(args.out, fig)
    rows = []
    for i, (p, ok, length, red) in enumerate(zip(pts, seg.valid, seg.length, seg.reduction)):
        rows.append((str(i + 1), f"{p[0]:.1f},{p[1]:.1f}", f"{length:.1f}" if ok else "empty",
                     f"{seg.line_length[i]:.1f}", "-" if not np.isfinite(red) else f"{red:.1%}"))
    console.print(_table(["#", "point (image 1)", "segment px", "line px", "excluded"], rows))
    e = seg.epipole
    console.print(f"epipole in image 2: {'at infinity' if not np.all(np.isfinite(e)) else f'{e[0]:.1f},{e[1]:.1f}'}")
    console.print(f"wrote {out}")
    return 0


# --------------------------------------------------------------------------------------
# bench
# --------------------------------------------------------------------------------------
def _benchmarks_dir(given) -> Path:
    if given is not None:
        d = Path(given)
    else:
        import episeg_cv

        d = Path(episeg_cv.__file__).resolve().parents[1] / "benchmarks"
    if not d.is_dir():
        raise UserError(f"benchmarks folder not found at {d}: 'episeg bench' needs a source checkout "
                        "(git clone, then pip install -e .), the benchmarks are not part of the wheel")
    return d


def _supports(script: Path, flag: str) -> bool:
    try:
        r = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired:
        return False
    return r.returncode == 0 and flag in r.stdout


def cmd_bench(args, console: _Console) -> int:
    d = _benchmarks_dir(args.dir)
    names = args.only or list(BENCH_SCRIPTS)
    scripts = [d / n for n in names if (d / n).is_file()]
    missing = [n for n in names if not (d / n).is_file()]
    for n in missing:
        print(f"{PROG}: warning: {d / n} not found, skipped", file=sys.stderr)
    if not scripts:
        raise UserError(f"no benchmark scripts ({', '.join(names)}) in {d}")
    results = d / "results"
    t0 = time.time()
    prog = console.progress(len(scripts), "bench")
    for s in scripts:
        cmd = [sys.executable, str(s)]
        if args.quick:
            if _supports(s, "--quick"):
                cmd.append("--quick")
            else:
                console.info(f"{s.name} has no --quick option; running it in full")
        console.info("running " + " ".join(cmd))
        if not console.quiet:
            print(f"== {s.name} ==", flush=True)
        r = subprocess.run(cmd, cwd=str(d.parent), stdout=subprocess.DEVNULL if console.quiet else None)
        if r.returncode != 0:
            raise UserError(f"{s.name} failed with exit code {r.returncode}")
        prog.step(s.name)
    prog.close()
    new = sorted(p for p in results.rglob("*") if p.is_file() and p.stat().st_mtime >= t0 - 1) if results.is_dir() else []
    console.print(f"results in {results}" + (":" if new else ""))
    for p in new:
        console.print(f"  {p}")
    return 0


# --------------------------------------------------------------------------------------
# Parser and entry point
# --------------------------------------------------------------------------------------
class _Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Shows each option's default, except None, the False of on/off flags, and defaults the help states."""

    def _get_help_string(self, action):
        if action.default is None or action.default is False or "default:" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


def _positive_int(text):
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def _nonneg_float(text):
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not np.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text!r}")
    return v


def _depth(text):
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a depth (number or inf), got {text!r}") from None
    if np.isnan(v) or v < 0:
        raise argparse.ArgumentTypeError(f"expected a depth >= 0, got {text!r}")
    return v


def _ratio(text):
    v = _nonneg_float(text)
    if not 0 < v <= 1:
        raise argparse.ArgumentTypeError(f"expected a ratio in (0, 1], got {text!r}")
    return v


def build_parser() -> argparse.ArgumentParser:
    from . import __version__
    from .matching import DEFAULT_RATIO

    common = argparse.ArgumentParser(add_help=False)
    g = common.add_mutually_exclusive_group()
    g.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors")
    g.add_argument("-v", "--verbose", action="store_true", help="more detail on stderr")

    parser = argparse.ArgumentParser(
        prog=PROG, formatter_class=_Formatter,
        description="Feature matching on the correct epipolar segment, for two views with a known pose "
                    "(X2 = R X1 + t).",
        epilog="examples:\n  episeg demo\n  episeg match left.png right.png --calib stereo.yml --out matches.json\n"
               "  episeg segments left.png right.png --calib calib.json --random 12\n\n"
               "Run 'episeg COMMAND --help' for the options of each command.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("demo", parents=[common], formatter_class=_Formatter,
                       help="segment- vs line-guided matching on the bundled pair",
                       description="Run segment-guided and line-guided matching (and BFMatcher + ratio, with and "
                                   "without the line filter) on the bundled synthetic pair, score them against its "
                                   "ground truth, and write DIR/matches.png, DIR/segments.png and DIR/matches.json.",
                       epilog="example:\n  episeg demo --out episeg_demo")
    p.add_argument("--out", default="episeg_demo", metavar="DIR", help="output folder")
    p.add_argument("--max-features", type=_positive_int, default=4000, metavar="N", help="SIFT keypoints per image")
    p.add_argument("--tol", type=_nonneg_float, default=2.0, metavar="PX", help="pixel tolerance of the constraint")
    p.add_argument("--points", type=_positive_int, default=12, metavar="N", help="points in segments.png")
    p.add_argument("--seed", type=int, default=0, help="seed for choosing the points of segments.png")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("match", parents=[common], formatter_class=_Formatter,
                       help="match two images with a known calibration",
                       description="Detect keypoints in both images, undistort them if the calibration has "
                                   "distortion coefficients, and match them on the epipolar segment (or line, or "
                                   "with plain cv2.BFMatcher for --constraint none: ratio test, or crossCheck with "
                                   "--cross-check). Write the matches (JSON/NPZ/CSV, see the module docstring of "
                                   "episeg_cv.cli for the layout) and a figure.",
                       epilog="examples:\n  episeg match left.png right.png --calib stereo.yml --out matches.json\n"
                              "  episeg match a.png b.png --calib calib.json --detector orb --constraint line "
                              "--figure m.png\n\ncalibration files: JSON (K1, K2, R, t, image_size1, image_size2; or "
                              "per-camera world poses; or P1, P2) or OpenCV YAML/XML (M1, D1, M2, D2, R, T); see "
                              "episeg_cv.load_calibration.")
    p.add_argument("image1", help="query image (view 1)")
    p.add_argument("image2", help="train image (view 2)")
    p.add_argument("--calib", required=True, metavar="FILE", help="calibration file (.json, .yml, .yaml, .xml)")
    p.add_argument("--detector", choices=("sift", "orb", "akaze"), default="sift", help="keypoint detector")
    p.add_argument("--constraint", choices=("segment", "line", "none"), default="segment",
                   help="search the correct segment, the whole epipolar line, or everywhere")
    p.add_argument("--tol", type=_nonneg_float, default=2.0, metavar="PX", help="pixel tolerance of the constraint")
    p.add_argument("--depth-range", type=_depth, nargs=2, metavar=("ZMIN", "ZMAX"), default=None,
                   help="depth bounds in camera 1, in the unit of t (ZMAX may be inf); default 0 inf")
    p.add_argument("--ratio", type=_ratio, default=None,
                   help=f"ratio test threshold (default: the matcher's, {DEFAULT_RATIO})")
    p.add_argument("--cross-check", action="store_true", help="keep only mutual nearest neighbours both ways")
    p.add_argument("--max-features", type=_positive_int, default=4000, metavar="N", help="keypoints per image")
    p.add_argument("--out", default=None, metavar="FILE", help="matches file: .json, .npz or .csv")
    p.add_argument("--figure", default=None, metavar="PNG", help="write a figure of the matches")
    p.set_defaults(func=cmd_match)

    p = sub.add_parser("segments", parents=[common], formatter_class=_Formatter,
                       help="draw the paper's figure of epipolar segments",
                       description="Draw image 1 with the chosen points, and image 2 with their epipolar lines: "
                                   "the correct visible segment in green, the excluded pieces in red, the epipole "
                                   "and the virtual infinity points marked. With distortion coefficients both "
                                   "images are undistorted (same K) and the points too.",
                       epilog="examples:\n  episeg segments left.png right.png --calib calib.json --random 12\n"
                              "  episeg segments a.png b.png --calib calib.json --points 100,80 320,240 --out fig.png")
    p.add_argument("image1")
    p.add_argument("image2")
    p.add_argument("--calib", required=True, metavar="FILE", help="calibration file (.json, .yml, .yaml, .xml)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--points", type=_parse_point, nargs="+", metavar="X,Y", help="points of image 1, in pixels")
    src.add_argument("--random", type=_positive_int, default=10, metavar="N",
                     help="number of random points (when --points is not given)")
    p.add_argument("--seed", type=int, default=0, help="seed for --random")
    p.add_argument("--depth-range", type=_depth, nargs=2, metavar=("ZMIN", "ZMAX"), default=None,
                   help="depth bounds in camera 1, in the unit of t; default 0 inf")
    p.add_argument("--out", default="segments.png", metavar="PNG", help="figure to write")
    p.set_defaults(func=cmd_segments)

    p = sub.add_parser("bench", parents=[common], formatter_class=_Formatter,
                       help="run the benchmarks (source checkout)",
                       description=f"Run the benchmark scripts {', '.join(BENCH_SCRIPTS)} of the repository's "
                                   "benchmarks/ folder with this Python, and list the files written to "
                                   "benchmarks/results/. Needs a source checkout, not a wheel.",
                       epilog="examples:\n  episeg bench --quick\n  episeg bench --only compare.py")
    p.add_argument("--quick", action="store_true", help="pass --quick to the scripts that accept it")
    p.add_argument("--only", nargs="+", choices=BENCH_SCRIPTS, default=None, metavar="SCRIPT",
                   help=f"run only these scripts ({', '.join(BENCH_SCRIPTS)})")
    p.add_argument("--dir", default=None, help="benchmarks folder (default: the repository's benchmarks/)")
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("colmap", parents=[common], formatter_class=_Formatter,
                       help="match a posed collection into a COLMAP database",
                       description="Compute features once per image (cached on disk), match every pair on its "
                                   "epipolar segments from the known poses, and write a COLMAP database (cameras, "
                                   "rigs, frames, images, keypoints, matches, CALIBRATED two-view geometries) that "
                                   "'colmap point_triangulator' or pycolmap.triangulate_points uses unchanged. "
                                   "MODEL is a COLMAP sparse model folder or a poses JSON (see "
                                   "episeg_cv.colmap.load_poses).",
                       epilog="examples:\n  episeg colmap sparse/0 images --database out.db --neighbors 10 "
                              "--triangulate tri\n  episeg colmap poses.json images --database out.db --workers 2\n"
                              "  episeg colmap sparse/0 images --database out.db --scheduler tcp://10.0.0.5:8786 "
                              "--resume")
    p.add_argument("model", help="COLMAP model folder (cameras, images, points3D; .bin or .txt) or poses JSON")
    p.add_argument("image_dir", help="folder of the images, named as in the model")
    p.add_argument("--database", required=True, metavar="DB", help="COLMAP database to write")
    pg = p.add_mutually_exclusive_group()
    pg.add_argument("--pairs", metavar="FILE", help="pairs file, one 'name1 name2' per line (COLMAP/hloc)")
    pg.add_argument("--neighbors", type=_positive_int, metavar="K",
                    help="each image's K best partners by view overlap (default, without --pairs: every pair)")
    p.add_argument("--detector", choices=("sift", "orb", "akaze"), default="sift", help="keypoint detector")
    p.add_argument("--max-features", type=_positive_int, default=8192, metavar="N", help="keypoints per image")
    p.add_argument("--constraint", choices=("segment", "line"), default="segment",
                   help="search the correct segment or the whole epipolar line")
    p.add_argument("--depth-range", nargs="+", default=["auto"], metavar="SPEC",
                   help="'auto': each image's depth range from the model's 3D points it sees; 'none': (0, inf); "
                        "or 'ZMIN ZMAX' for every image, in the unit of the poses (default: auto)")
    p.add_argument("--tol", type=_nonneg_float, default=2.0, metavar="PX", help="pixel tolerance of the constraint")
    p.add_argument("--ratio", type=_ratio, default=None,
                   help=f"ratio test of the guided matcher, with its mutual check (default: the matcher's, {DEFAULT_RATIO})")
    p.add_argument("--workers", type=_positive_int, default=1, metavar="N", help="local worker processes")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="Dask scheduler address, or local:N for a new LocalCluster (needs episeg_cv[dask])")
    p.add_argument("--cache", default=None, metavar="DIR",
                   help="feature cache folder (default: DB.features, next to the database)")
    p.add_argument("--triangulate", default=None, metavar="OUT_DIR",
                   help="then run pycolmap.triangulate_points and write the model to OUT_DIR")
    rg = p.add_mutually_exclusive_group()
    rg.add_argument("--resume", action="store_true", help="continue DB, skipping the pairs it holds")
    rg.add_argument("--overwrite", action="store_true", help="replace an existing DB")
    p.set_defaults(func=cmd_colmap)

    p = sub.add_parser("synthetic", parents=[common], formatter_class=_Formatter,
                       help="render a posed synthetic collection to try 'episeg colmap'",
                       description="Render views of a room with boxes along an arc (exact poses) and write "
                                   "DIR/images, a COLMAP model DIR/model (with 3D points sampled from the "
                                   "rendered depth) and DIR/poses.json.",
                       epilog="example:\n  episeg synthetic room && episeg colmap room/model room/images "
                              "--database room/episeg.db --triangulate room/triangulated")
    p.add_argument("out", metavar="DIR", help="output folder")
    p.add_argument("--views", type=_positive_int, default=12, metavar="N", help="number of views (>= 2)")
    p.add_argument("--size", type=_positive_int, nargs=2, default=[640, 480], metavar=("W", "H"), help="image size")
    p.add_argument("--seed", type=int, default=7, help="seed of the room")
    p.set_defaults(func=cmd_synthetic)
    return parser


def _colmap_depth(values):
    if len(values) == 1 and values[0] in ("auto", "none"):
        return values[0]
    if len(values) == 2:
        try:
            return (_depth(values[0]), _depth(values[1]))
        except argparse.ArgumentTypeError as e:
            raise UserError(f"--depth-range: {e}") from e
    raise UserError(f"--depth-range takes 'auto', 'none' or ZMIN ZMAX, got {' '.join(values)!r}")


def cmd_colmap(args, console: _Console) -> int:
    try:
        import pycolmap
    except ImportError as e:
        raise UserError('episeg colmap needs pycolmap: pip install "episeg_cv[colmap]"') from e
    from . import colmap

    if not console.verbose:
        pycolmap.logging.minloglevel = 2  # COLMAP's INFO and WARNING lines only with --verbose
    bars = {}

    def progress(stage, done, total):
        bar = bars.get(stage) or bars.setdefault(stage, console.progress(total, stage))
        dt = time.perf_counter() - bar.t0
        bar.step(f"{done / dt:.1f} {'images' if stage == 'features' else 'pairs'}/s" if dt > 0 else "")

    t0 = time.perf_counter()
    try:
        report = colmap.match_model(
            args.model, args.image_dir, args.database, pairs=args.pairs, neighbors=args.neighbors,
            detector=args.detector, max_features=args.max_features, constraint=args.constraint,
            depth_range=_colmap_depth(args.depth_range), tol=args.tol,
            **({} if args.ratio is None else {"ratio": args.ratio}), workers=args.workers,
            scheduler=args.scheduler, cache_dir=args.cache, resume=args.resume, overwrite=args.overwrite,
            progress=progress, log=lambda msg: print(f"{PROG}: {msg}", file=sys.stderr, flush=True))
    finally:
        for bar in bars.values():
            bar.close()
    console.print(report.summary())
    if args.triangulate:
        rec = colmap.triangulate(args.database, args.model, args.image_dir, args.triangulate)
        console.print(f"triangulated model in {args.triangulate}: {rec.num_points3D()} points, "
                      f"mean track length {rec.compute_mean_track_length():.2f}, "
                      f"mean reprojection error {rec.compute_mean_reprojection_error():.3f} px")
    console.info(f"done in {time.perf_counter() - t0:.1f} s")
    return 0


def cmd_synthetic(args, console: _Console) -> int:
    from . import scenes
    try:
        from .colmap import save_collection
    except ImportError as e:
        raise UserError('episeg synthetic needs pycolmap: pip install "episeg_cv[colmap]"') from e
    console.info(f"rendering {args.views} views at {args.size[0]}x{args.size[1]}")
    paths = save_collection(scenes.make_collection(args.views, tuple(args.size), seed=args.seed), args.out)
    console.print(f"wrote {args.views} images to {paths['images']}, a COLMAP model to {paths['model']} and "
                  f"{paths['poses']}\ntry: {PROG} colmap {paths['model']} {paths['images']} "
                  f"--database {Path(args.out) / 'episeg.db'} --triangulate {Path(args.out) / 'triangulated'}")
    return 0


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def main(argv=None) -> int:
    """Entry point of the ``episeg`` command; returns the exit code (0, 1 bad data, 2 usage).

    Parameters
    ----------
    argv : list of str, optional
        The arguments after ``episeg``; default ``sys.argv[1:]``.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    console = _Console(args.quiet, args.verbose)
    try:
        return int(args.func(args, console) or 0)
    except (UserError, ValueError, TypeError, OSError) as exc:
        # user errors: a missing file, a bad calibration, an unreadable image, bad values
        print(f"{PROG}: error: {_one_line(exc)}", file=sys.stderr, flush=True)
        if args.verbose and not isinstance(exc, (UserError, FileNotFoundError)):
            import traceback

            traceback.print_exc()
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
