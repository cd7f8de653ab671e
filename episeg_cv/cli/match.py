"""``episeg match``: detect, undistort, match on the segment (or line, or none), write the matches and a figure."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..distortion import undistort_points
from ..drawing import draw_matches, save_image
from ..estimation import GeometryEstimationError, match_without_pose
from ..features import PRESETS
from ..io.matches import FORMAT, FORMAT_VERSION, json_number, write_matches
from ..matching import AcceptRule, SearchConfig, consistent_pairs, estimate_band
from ..threads import set_num_threads
from .args import (Formatter, depth, depth_range_arg, image_file_arg, max_features_arg, not_an_input, positive_int,
                   ratio_arg, tol_arg)
from .common import MAX_LINES, detect, image_size, labels_of, load_calib, read_image, run_matching, versions
from .console import Console, UserError

MATCH_SUFFIXES = (".json", ".npz", ".csv")


def add_parser(sub, parents) -> None:
    p = sub.add_parser("match", parents=parents, formatter_class=Formatter,
                       help="match two images (with a calibration, or none)",
                       description="Detect keypoints in both images, undistort them if the calibration has "
                                   "distortion coefficients, and match them on the epipolar segment (or line, or "
                                   "with plain cv2.BFMatcher for --constraint none: ratio test, or crossCheck with "
                                   "--cross-check). Write the matches (JSON/NPZ/CSV, see episeg_cv.io.matches for "
                                   "the layout) and a figure. Without --calib, the geometry is estimated from the "
                                   "images (an oriented fundamental matrix: the half-line from the epipole); with a "
                                   "calibration that holds the intrinsics but no pose, the pose is estimated "
                                   "(essential matrix, then refined) and the full segments are used.",
                       epilog="examples:\n  episeg match left.png right.png --calib stereo.yml --out matches.json\n"
                              "  episeg match a.png b.png --calib calib.json --detector orb --constraint line "
                              "--figure m.png\n  episeg match a.png b.png --calib odometry.json --tol auto\n"
                              "  episeg match a.png b.png --out matches.json       (no calibration at all)\n\n"
                              "calibration files: JSON (K1, K2, R, t, image_size1, image_size2; or "
                              "per-camera world poses; or P1, P2) or OpenCV YAML/XML (M1, D1, M2, D2, R, T); see "
                              "episeg_cv.load_calibration. Leave the pose out (K1, K2 only) to estimate it.")
    p.add_argument("image1", help="query image (view 1)")
    p.add_argument("image2", help="train image (view 2)")
    p.add_argument("--calib", default=None, metavar="FILE",
                   help="calibration file (.json, .yml, .yaml, .xml); none: estimate the geometry from the images")
    p.add_argument("--detector", choices=("sift", "orb", "akaze"), default="sift", help="keypoint detector")
    p.add_argument("--constraint", choices=("segment", "line", "none"), default="segment",
                   help="search the correct segment, the whole epipolar line, or everywhere")
    p.add_argument("--tol", type=tol_arg, default=_default_tol(), metavar="PX|auto",
                   help="pixel tolerance of the constraint, or 'auto': estimated (and the pose corrected when that "
                        "matters) from the keypoints; an estimated geometry always gets its own")
    p.add_argument("--depth-range", type=depth, nargs=2, metavar=("ZMIN", "ZMAX"), default=None,
                   help="depth bounds in camera 1, in the unit of t (ZMAX may be inf); default 0 inf")
    p.add_argument("--ratio", type=ratio_arg, default=None,
                   help=f"ratio test threshold (default: the matcher's, {AcceptRule().ratio})")
    p.add_argument("--cross-check", action="store_true", help="keep only mutual nearest neighbours both ways")
    p.add_argument("--reject-repeats", action="store_true",
                   help="with an estimated geometry (no pose): leave out the matches whose keypoints have a near-copy "
                        "in their own image inside the same band (repeated texture; costs a few correct matches)")
    p.add_argument("--consistency", action="store_true",
                   help="leave out the matches that disagree with the affine map of their 10 nearest anchors (with "
                        "an estimated geometry: the first-pass matches; with a pose: all matches); for repeated "
                        "texture; costs a few %% of the correct matches of ordinary pairs")
    p.add_argument("--max-features", type=max_features_arg, default=4000, metavar="N", help="keypoints per image")
    p.add_argument("--threads", type=positive_int, default=None, metavar="N",
                   help="threads of the detector (cv2.setNumThreads) and of the matcher (episeg_cv.set_num_threads); "
                        "default: every core. The matches are the same for every count")
    p.add_argument("--out", default=None, metavar="FILE", help="matches file: .json, .npz or .csv")
    p.add_argument("--figure", type=image_file_arg, default=None, metavar="PNG", help="write a figure of the matches")
    p.set_defaults(func=run)


def _default_tol():
    tol = SearchConfig().tol
    return "auto" if SearchConfig().auto is not None else tol


def run(args, console: Console) -> int:
    if args.out is not None and Path(args.out).suffix.lower() not in MATCH_SUFFIXES:
        raise UserError(f"--out must end in .json, .npz or .csv, got {args.out!r}")
    for option, path in (("--out", args.out), ("--figure", args.figure)):
        not_an_input(path, [args.image1, args.image2, args.calib], option)
    search = SearchConfig(tol=args.tol, depth_range=depth_range_arg(args.depth_range), constraint=args.constraint)
    rule = AcceptRule(cross_check=args.cross_check, **({} if args.ratio is None else {"ratio": args.ratio}))
    if args.threads is not None:
        cv2.setNumThreads(args.threads)
        set_num_threads(args.threads)
    img1, img2 = read_image(args.image1), read_image(args.image2)
    calib = load_calib(args.calib, img1, img2, console) if args.calib is not None else None
    posed = calib is not None and calib.has_pose
    if not posed and args.constraint == "none":
        raise UserError("--constraint none matches with plain cv2.BFMatcher and needs no geometry; give a "
                        "calibration with a pose, or use --constraint segment or line")
    if calib is None and search.bounded:
        raise UserError("--depth-range needs a calibration (without one, depth has no unit)")
    if posed and args.reject_repeats:
        raise UserError("--reject-repeats applies when the geometry is estimated from the images (a --calib "
                        "without R and t, or none); this calibration holds a pose")
    prog = console.progress(4 + (args.figure is not None), "match")
    features = PRESETS["opencv"].replace(detector=args.detector, max_features=args.max_features)
    (p1, des1), (p2, des2) = detect(img1, features), detect(img2, features)
    prog.step(f"{args.detector}: {len(p1)} and {len(p2)} keypoints")
    if calib is not None:
        u1, u2 = undistort_points(p1, calib.K1, calib.dist1), undistort_points(p2, calib.K2, calib.dist2)
    else:
        u1, u2 = p1, p2
    if calib is not None and calib.has_distortion:
        console.info("undistorted the keypoints with cv2.undistortPoints (P = K) before matching")
    prog.step("undistorted" if calib is not None and calib.has_distortion else "no distortion")
    # keypoints where the distortion has no inverse (NaN) are left out; matches index all keypoints
    i1, i2 = (np.flatnonzero(np.all(np.isfinite(u), axis=1)) for u in (u1, u2))
    for name, idx, u in (("image 1", i1, u1), ("image 2", i2, u2)):
        if len(idx) < len(u):
            console.info(f"{name}: {len(u) - len(idx)} of {len(u)} keypoints lie where the lens distortion cannot be "
                         "inverted (it folds there); left out of the matching")
    f1, f2, v1, v2 = des1[i1], des2[i2], u1[i1], u2[i2]
    pose = {"source": "calibration"}
    if posed:
        geom = calib.geometry
        if search.auto is not None and search.constraint != "none" and len(des1) and len(des2):
            est = estimate_band(f1, f2, v1, v2, geom, norm=features.norm, search=search, rule=rule)
            geom, search = est.geometry, search.replace(tol=est.tol)
            pose.update(tol="auto", estimated_tol=est.tol, pose_kept=est.pose_kept,
                        rotation_change_deg=est.rotation_change_deg,
                        translation_change_deg=est.translation_change_deg)
            console.info(f"tol auto: {est.tol:.2f} px, pose {'kept' if est.pose_kept else 'corrected'} "
                         f"({est.rotation_change_deg:.3f} deg, t direction {est.translation_change_deg:.3f} deg)")
        pairs, dist = run_matching(geom, f1, f2, v1, v2, features.norm, search, rule)
        if args.consistency:
            keep = consistent_pairs(v1, v2, pairs, tol=search.tol if search.auto is None else search.auto.tol_min)
            pairs, dist = pairs[keep], dist[keep]
    else:
        sizes = dict(image_size1=image_size(img1), image_size2=image_size(img2))
        if calib is not None:
            sizes.update(K1=calib.K1, K2=calib.K2)
        try:
            pairs, dist, est = match_without_pose(f1, f2, v1, v2, norm=features.norm, search=search, rule=rule,
                                                  reject_repeats=args.reject_repeats,
                                                  consistency=args.consistency, **sizes)
        except GeometryEstimationError as exc:
            raise UserError(f"cannot estimate the geometry from the images: {exc}") from None
        geom, search = est.geometry, search.replace(tol=est.tol)
        pose = {"source": f"estimated ({est.method} matrix)", "estimated_tol": est.tol,
                "first_pass": len(est.first_pass), "inliers": len(est.inliers)}
        console.info(f"no pose: {est.method} matrix from {len(est.inliers)} of {len(est.first_pass)} first-pass "
                     f"matches; band {est.tol:.2f} px")
    prog.step(f"{len(pairs)} matches")
    labels, counts = labels_of(pairs, v1, v2, geom, search)
    pairs = np.column_stack([i1[pairs[:, 0]], i2[pairs[:, 1]]]).astype(np.intp)  # into all the keypoints
    prog.step("labelled")
    meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "command": "match", **versions(),
            "image1": str(args.image1), "image2": str(args.image2),
            "calib": None if args.calib is None else str(args.calib),
            "convention": "X2 = R X1 + t; pixel centres at integer coordinates",
            "undistorted": calib is not None and calib.has_distortion, "pose": pose,
            "settings": {"detector": args.detector, "max_features": args.max_features, "constraint": args.constraint,
                         "tol": args.tol if isinstance(args.tol, str) else float(args.tol),
                         "depth_range": [json_number(z) for z in search.depth_range],
                         "cross_check": args.cross_check, "reject_repeats": args.reject_repeats,
                         "consistency": args.consistency, "threads": args.threads,
                         "ratio": None if args.constraint == "none" and args.cross_check else rule.ratio},
            "counts": {"keypoints1": len(p1), "keypoints2": len(p2), "matches": len(pairs), **counts}}
    written = []
    if args.out is not None:
        extra = {"keypoints1_undistorted": u1, "keypoints2_undistorted": u2} \
            if calib is not None and calib.has_distortion else None
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
