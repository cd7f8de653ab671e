"""``episeg compile``: compile every kernel of the commands into numba's cache now, on every core."""

from __future__ import annotations

from .args import Formatter, positive_int
from .console import PROG, Console, UserError


def add_parser(sub, parents) -> None:
    p = sub.add_parser("compile", parents=parents, formatter_class=Formatter,
                       help="compile the kernels ahead of the first run, on every core",
                       description="The first run of each command compiles the kernels it needs, one at a time "
                                   "on one core, and caches them (numba's cache: __pycache__ beside the package, "
                                   "or NUMBA_CACHE_DIR). This compiles all of them now, in several processes at "
                                   "once; the commands then load them. Run it once after installing or "
                                   "upgrading; kernels the cache holds already are only loaded.",
                       epilog="example:\n  pip install -e . && episeg compile && episeg demo")
    p.add_argument("--processes", type=positive_int, default=None, metavar="N",
                   help="processes to compile in (default: the cores this process may run on)")
    p.set_defaults(func=run)


def run(args, console: Console) -> int:
    from ..kernel_cache import compile_kernels

    try:
        out = compile_kernels(args.processes)
    except RuntimeError as exc:
        raise UserError(str(exc)) from exc
    console.print(f"compiled or loaded {out['kernels']} kernels ({out['signatures']} signatures) in "
                  f"{out['seconds']:.1f} s on {out['processes']} process(es)")
    for note in out["skipped"]:
        console.info(f"skipped {note}")
    if out["skipped"]:
        console.print(f"{PROG}: {len(out['skipped'])} kernel signature(s) skipped (they compile on first use; "
                      "-v lists them)")
    return 0
