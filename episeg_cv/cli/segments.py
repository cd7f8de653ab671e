"""``episeg segments``: the paper's figure for chosen (or random) points, and a table of their segments."""

from __future__ import annotations

import cv2
import numpy as np

from ..distortion import undistort_points
from ..drawing import draw_segment_figure, save_image
from .args import Formatter, bounded_int, depth, depth_range_arg, image_file_arg, not_an_input, parse_point, seed_arg

#: Most random points of a figure (each is drawn; more would not be readable anyway).
MAX_RANDOM = 100_000
from .common import load_calib, read_image
from .console import Console, UserError, table


def add_parser(sub, parents) -> None:
    p = sub.add_parser("segments", parents=parents, formatter_class=Formatter,
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
    src.add_argument("--points", type=parse_point, nargs="+", metavar="X,Y", help="points of image 1, in pixels")
    src.add_argument("--random", type=bounded_int(1, MAX_RANDOM), default=10, metavar="N",
                     help="number of random points (when --points is not given)")
    p.add_argument("--seed", type=seed_arg, default=0, help="seed for --random")
    p.add_argument("--depth-range", type=depth, nargs=2, metavar=("ZMIN", "ZMAX"), default=None,
                   help="depth bounds in camera 1, in the unit of t; default 0 inf")
    p.add_argument("--out", type=image_file_arg, default="segments.png", metavar="PNG", help="figure to write")
    p.set_defaults(func=run)


def run(args, console: Console) -> int:
    not_an_input(args.out, [args.image1, args.image2, args.calib], "--out")
    depth_range = depth_range_arg(args.depth_range)
    img1, img2 = read_image(args.image1), read_image(args.image2)
    calib = load_calib(args.calib, img1, img2, console)
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
    line_length = seg.line_length  # (a property: computed once, not once per row)
    for i, (p, ok, length, red) in enumerate(zip(pts, seg.valid, seg.length, seg.reduction)):
        rows.append((str(i + 1), f"{p[0]:.1f},{p[1]:.1f}", f"{length:.1f}" if ok else "empty",
                     f"{line_length[i]:.1f}", "-" if not np.isfinite(red) else f"{red:.1%}"))
    console.print(table(["#", "point (image 1)", "segment px", "line px", "excluded"], rows))
    e = seg.epipole
    console.print(f"epipole in image 2: {'at infinity' if not np.all(np.isfinite(e)) else f'{e[0]:.1f},{e[1]:.1f}'}")
    console.print(f"wrote {out}")
    return 0
