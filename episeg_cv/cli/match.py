"""``episeg match``: detect, undistort, match on the segment (or line, or none), write the matches and a figure."""

from __future__ import annotations

from pathlib import Path

from ..distortion import undistort_points
from ..drawing import draw_matches, save_image
from ..features import PRESETS
from ..io.matches import FORMAT, FORMAT_VERSION, json_number, write_matches
from ..matching import AcceptRule, SearchConfig
from .args import Formatter, depth, depth_range_arg, nonneg_float, positive_int, ratio_arg
from .common import MAX_LINES, detect, labels_of, load_calib, read_image, run_matching, versions
from .console import Console, UserError

MATCH_SUFFIXES = (".json", ".npz", ".csv")


def add_parser(sub, parents) -> None:
    p = sub.add_parser("match", parents=parents, formatter_class=Formatter,
                       help="match two images with a known calibration",
                       description="Detect keypoints in both images, undistort them if the calibration has "
                                   "distortion coefficients, and match them on the epipolar segment (or line, or "
                                   "with plain cv2.BFMatcher for --constraint none: ratio test, or crossCheck with "
                                   "--cross-check). Write the matches (JSON/NPZ/CSV, see episeg_cv.io.matches for "
                                   "the layout) and a figure.",
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
    p.add_argument("--tol", type=nonneg_float, default=SearchConfig().tol, metavar="PX",
                   help="pixel tolerance of the constraint")
    p.add_argument("--depth-range", type=depth, nargs=2, metavar=("ZMIN", "ZMAX"), default=None,
                   help="depth bounds in camera 1, in the unit of t (ZMAX may be inf); default 0 inf")
    p.add_argument("--ratio", type=ratio_arg, default=None,
                   help=f"ratio test threshold (default: the matcher's, {AcceptRule().ratio})")
    p.add_argument("--cross-check", action="store_true", help="keep only mutual nearest neighbours both ways")
    p.add_argument("--max-features", type=positive_int, default=4000, metavar="N", help="keypoints per image")
    p.add_argument("--out", default=None, metavar="FILE", help="matches file: .json, .npz or .csv")
    p.add_argument("--figure", default=None, metavar="PNG", help="write a figure of the matches")
    p.set_defaults(func=run)


def run(args, console: Console) -> int:
    if args.out is not None and Path(args.out).suffix.lower() not in MATCH_SUFFIXES:
        raise UserError(f"--out must end in .json, .npz or .csv, got {args.out!r}")
    search = SearchConfig(tol=args.tol, depth_range=depth_range_arg(args.depth_range), constraint=args.constraint)
    rule = AcceptRule(cross_check=args.cross_check, **({} if args.ratio is None else {"ratio": args.ratio}))
    img1, img2 = read_image(args.image1), read_image(args.image2)
    calib = load_calib(args.calib, img1, img2, console)
    geom = calib.geometry
    prog = console.progress(4 + (args.figure is not None), "match")
    features = PRESETS["opencv"].replace(detector=args.detector, max_features=args.max_features)
    (p1, des1), (p2, des2) = detect(img1, features), detect(img2, features)
    prog.step(f"{args.detector}: {len(p1)} and {len(p2)} keypoints")
    u1, u2 = undistort_points(p1, calib.K1, calib.dist1), undistort_points(p2, calib.K2, calib.dist2)
    if calib.has_distortion:
        console.info("undistorted the keypoints with cv2.undistortPoints (P = K) before matching")
    prog.step("undistorted" if calib.has_distortion else "no distortion")
    pairs, dist = run_matching(geom, des1, des2, u1, u2, features.norm, search, rule)
    prog.step(f"{len(pairs)} matches")
    labels, counts = labels_of(pairs, u1, u2, geom, search)
    prog.step("labelled")
    meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "command": "match", **versions(),
            "image1": str(args.image1), "image2": str(args.image2), "calib": str(args.calib),
            "convention": "X2 = R X1 + t; pixel centres at integer coordinates",
            "undistorted": calib.has_distortion,
            "settings": {"detector": args.detector, "max_features": args.max_features, "constraint": args.constraint,
                         "tol": args.tol, "depth_range": [json_number(z) for z in search.depth_range],
                         "cross_check": args.cross_check,
                         "ratio": None if args.constraint == "none" and args.cross_check else rule.ratio},
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
