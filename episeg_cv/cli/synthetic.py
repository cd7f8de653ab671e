"""``episeg synthetic``: render a posed synthetic collection (images, COLMAP model, poses JSON)."""

from __future__ import annotations

from pathlib import Path

from .. import scenes
from ..scenes.collection import MAX_HELD_BYTES
from .args import Formatter, bounded_int, seed_arg
from .console import PROG, Console, UserError


def add_parser(sub, parents) -> None:
    p = sub.add_parser("synthetic", parents=parents, formatter_class=Formatter,
                       help="render a posed synthetic collection to try 'episeg colmap'",
                       description="Render views of a room with boxes along an arc (exact poses) and write "
                                   "DIR/images, a COLMAP model DIR/model (with 3D points sampled from the "
                                   "rendered depth) and DIR/poses.json.",
                       epilog="example:\n  episeg synthetic room && episeg colmap room/model room/images "
                              "--database room/episeg.db --triangulate room/triangulated")
    p.add_argument("out", metavar="DIR", help="output folder")
    p.add_argument("--views", type=bounded_int(2, 10_000), default=12, metavar="N", help="number of views")
    p.add_argument("--size", type=bounded_int(16, 8192), nargs=2, default=[640, 480], metavar=("W", "H"),
                   help="image size")
    p.add_argument("--seed", type=seed_arg, default=7, help="seed of the room")
    p.set_defaults(func=run)


def run(args, console: Console) -> int:
    try:
        import pycolmap  # noqa: F401
    except ImportError as e:
        raise UserError('episeg synthetic needs pycolmap: pip install "episeg_cv[colmap]"') from e
    from ..colmap import save_collection

    held = args.views * args.size[0] * args.size[1] * 9
    if held > MAX_HELD_BYTES:
        raise UserError(f"--views {args.views} at --size {args.size[0]} {args.size[1]} would hold {held / 2**30:.1f} GiB "
                        f"of images and depth maps (at most {MAX_HELD_BYTES / 2**30:.0f} GiB): use fewer views or "
                        "smaller images")
    out = Path(args.out)
    for sub in ("model", "images"):
        if (out / sub).is_dir() and any((out / sub).iterdir()):
            raise UserError(f"{str(out / sub)!r} already holds files; give a new or empty folder (nothing is replaced)")
    console.info(f"rendering {args.views} views at {args.size[0]}x{args.size[1]}")
    paths = save_collection(scenes.make_collection(args.views, tuple(args.size), seed=args.seed), args.out)
    console.print(f"wrote {args.views} images to {paths['images']}, a COLMAP model to {paths['model']} and "
                  f"{paths['poses']}\ntry: {PROG} colmap {paths['model']} {paths['images']} "
                  f"--database {Path(args.out) / 'episeg.db'} --triangulate {Path(args.out) / 'triangulated'}")
    return 0
