"""``episeg demo``: segment- vs line-guided matching on the bundled pair, scored against its ground truth."""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np

from ..datasets import load_default_pair
from ..drawing import draw_matches, draw_segment_figure, save_image
from ..features import PRESETS
from ..io.matches import FORMAT, FORMAT_VERSION, json_number, write_matches
from ..matching import AcceptRule, SearchConfig
from ..opencv import SegmentMatcher, pairs_of
from .args import Formatter, max_features_arg, seed_arg, nonneg_float, positive_int
from .common import MAX_LINES, detect, labels_of, run_matching, versions
from .console import Console, table

#: The ratio of the BFMatcher baseline (Lowe's value).
BASELINE_RATIO = 0.8


def add_parser(sub, parents) -> None:
    p = sub.add_parser("demo", parents=parents, formatter_class=Formatter,
                       help="segment- vs line-guided matching on the bundled pair",
                       description="Run segment-guided and line-guided matching (and BFMatcher + ratio, with and "
                                   "without the line filter) on the bundled synthetic pair, score them against its "
                                   "ground truth, and write DIR/matches.png, DIR/segments.png and DIR/matches.json.",
                       epilog="example:\n  episeg demo --out episeg_demo")
    p.add_argument("--out", default="episeg_demo", metavar="DIR", help="output folder")
    p.add_argument("--max-features", type=max_features_arg, default=4000, metavar="N", help="SIFT keypoints per image")
    p.add_argument("--tol", type=nonneg_float, default=2.0, metavar="PX", help="pixel tolerance of the constraint")
    p.add_argument("--points", type=positive_int, default=12, metavar="N", help="points in segments.png")
    p.add_argument("--seed", type=seed_arg, default=0, help="seed for choosing the points of segments.png")
    p.set_defaults(func=run)


def spread_choice(points, n, size, rng):
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


def run(args, console: Console) -> int:
    out = Path(args.out)
    prog = console.progress(7, "demo")
    pair = load_default_pair()
    geom = pair.geometry
    prog.step("loaded the default pair")
    features = PRESETS["opencv"].replace(max_features=args.max_features)
    (p1, des1), (p2, des2) = detect(pair.image1, features), detect(pair.image2, features)
    norm = cv2.NORM_L2
    gt = pair.ground_truth(p1, p2)
    prog.step(f"SIFT: {len(p1)} and {len(p2)} keypoints")

    segment = SearchConfig(tol=args.tol)
    line = segment.replace(constraint="line")
    rule = AcceptRule()
    results = {}
    knn = cv2.BFMatcher(norm).knnMatch(des1, des2, k=2)
    bf = [m[0] for m in knn if len(m) >= 2 and m[0].distance < BASELINE_RATIO * m[1].distance]
    results[f"BFMatcher + ratio {BASELINE_RATIO}"] = pairs_of(bf)
    results[f"BFMatcher + ratio {BASELINE_RATIO} + line filter"] = pairs_of(
        SegmentMatcher(geom, norm, search=line).filter(bf, p1, p2))
    prog.step("BFMatcher baseline")
    t_line = time.perf_counter()
    results["line-guided (SegmentMatcher, constraint='line')"] = run_matching(geom, des1, des2, p1, p2, norm, line,
                                                                                rule)[0]
    t_line = time.perf_counter() - t_line
    prog.step("line-guided matching")
    t_seg = time.perf_counter()
    seg_pairs, seg_dist = run_matching(geom, des1, des2, p1, p2, norm, segment, rule)
    t_seg = time.perf_counter() - t_seg
    results["segment-guided (SegmentMatcher, constraint='segment')"] = seg_pairs
    prog.step("segment-guided matching")
    console.info(f"line-guided {t_line:.2f}s, segment-guided {t_seg:.2f}s")

    rows = []
    for name, pairs in results.items():
        ok = gt.is_correct(pairs)
        rows.append((name, len(pairs), int(ok.sum()), ok.mean() if len(ok) else float("nan"),
                     ok.sum() / max(gt.num_matchable, 1)))
    console.print(f"Default pair '{pair.name}': {len(p1)} / {len(p2)} SIFT keypoints, "
                  f"{gt.num_matchable} with a true match (ground truth from the depth maps).")
    console.print(table(["method", "matches", "correct", "precision", "recall"],
                        [(n, str(m), str(c), f"{p:.1%}", f"{r:.1%}") for n, m, c, p, r in rows]))

    # files
    seg_ok = gt.is_correct(seg_pairs)
    labels, counts = labels_of(seg_pairs, p1, p2, geom, segment)
    meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "command": "demo", **versions(),
            "image1": f"{pair.name}: image1", "image2": f"{pair.name}: image2", "calib": "bundled default pair",
            "convention": "X2 = R X1 + t; pixel centres at integer coordinates",
            "undistorted": False,
            "settings": {"detector": "sift", "max_features": args.max_features, "constraint": "segment",
                         "tol": args.tol, "depth_range": [0.0, None], "cross_check": False},
            "counts": {"keypoints1": len(p1), "keypoints2": len(p2), "matches": len(seg_pairs),
                       "correct": int(seg_ok.sum()), "matchable": gt.num_matchable, **counts},
            "comparison": [{"method": n, "matches": m, "correct": c, "precision": json_number(p),
                            "recall": json_number(r)} for n, m, c, p, r in rows]}
    written = [write_matches(out / "matches.json", meta, p1, p2, seg_pairs, seg_dist, labels)]
    written.append(save_image(out / "matches.png", draw_matches(pair.image1, pair.image2, p1, p2, seg_pairs, seg_ok,
                                                                 max_lines=MAX_LINES, rng=args.seed)))
    prog.step("matches figure")
    rng = np.random.default_rng(args.seed)
    pick = spread_choice(p1[seg_pairs[:, 0]], args.points, geom.image_size1, rng) if len(seg_pairs) else []
    sel = seg_pairs[pick] if len(seg_pairs) else np.zeros((0, 2), np.intp)
    q1 = p1[sel[:, 0]]
    fig = draw_segment_figure(pair.image1, pair.image2, q1, geom.segments(q1), p2[sel[:, 1]], seg_ok[pick])
    written.append(save_image(out / "segments.png", fig))
    prog.step("segments figure")
    prog.close()
    for w in written:
        console.print(f"wrote {w}")
    return 0
