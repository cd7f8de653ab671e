"""The ``episeg`` parser, assembled from each command's module, and the entry point."""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys

from .. import __version__
from ..interrupts import Terminated, interrupt_in, terminate_as_interrupt
from . import bench, colmap, demo, match, segments, synthetic
from . import compile as compile_command  # (not to hide the builtin compile here)
from .args import Formatter, add_verbosity
from .console import PROG, Console, UserError, one_line

#: The commands, in the order ``episeg --help`` lists them.
COMMANDS = (demo, match, segments, bench, colmap, synthetic, compile_command)


def build_parser() -> argparse.ArgumentParser:
    """The whole parser: each command module adds its own subparser."""
    common = argparse.ArgumentParser(add_help=False)
    add_verbosity(common)
    parser = argparse.ArgumentParser(
        prog=PROG, formatter_class=Formatter,
        description="Feature matching on the correct epipolar segment, for two views with a known pose "
                    "(X2 = R X1 + t).",
        epilog="examples:\n  episeg demo\n  episeg match left.png right.png --calib stereo.yml --out matches.json\n"
               "  episeg segments left.png right.png --calib calib.json --random 12\n\n"
               "Run 'episeg COMMAND --help' for the options of each command.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    add_verbosity(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for command in COMMANDS:
        command.add_parser(sub, [common])
    return parser


def main(argv=None) -> int:
    """Entry point of the ``episeg`` command; returns the exit code (0, 1 bad data, 2 usage).

    Parameters
    ----------
    argv : list of str, optional
        The arguments after ``episeg``; default ``sys.argv[1:]``.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    quiet, verbose = getattr(args, "quiet", False), getattr(args, "verbose", False)
    console = Console(quiet, verbose)
    log = logging.getLogger("episeg_cv")
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(f"{PROG}: %(message)s"))
    handler.setLevel(logging.INFO if verbose and not quiet else logging.WARNING)
    log.addHandler(handler)  # the library's notes (e.g. a rounded rotation repaired) as 'episeg: ...' lines
    level = log.level
    if verbose and not quiet:
        log.setLevel(logging.INFO)
    try:
        with terminate_as_interrupt(), _compile_notice(quiet):  # SIGTERM, SIGHUP: as Ctrl-C, cleanly
            return int(args.func(args, console) or 0)
    except (UserError, ValueError, TypeError, OSError) as exc:
        # user errors: a missing file, a bad calibration, an unreadable image, bad values
        print(f"{PROG}: error: {one_line(exc)}", file=sys.stderr, flush=True)
        if verbose and not isinstance(exc, (UserError, FileNotFoundError)):
            import traceback

            traceback.print_exc()
        return 1
    except KeyboardInterrupt as exc:
        return _interrupted(exc)
    except SystemError as exc:  # an interrupt that landed inside compiled code comes out wrapped
        interrupt = interrupt_in(exc)
        if interrupt is None:
            raise
        return _interrupted(interrupt)
    finally:
        log.removeHandler(handler)
        log.setLevel(level)


def _compile_notice(quiet: bool):
    """One line on stderr when a kernel starts compiling (the first run after installing), unless quiet."""
    if quiet:
        return contextlib.nullcontext()
    from ..kernel_cache import on_first_compile

    return on_first_compile(lambda name: print(
        f"{PROG}: compiling the kernels on their first use (up to a minute, once; later runs load them from "
        f"numba's cache; '{PROG} compile' compiles them all ahead, on every core)", file=sys.stderr, flush=True))


def _interrupted(exc: KeyboardInterrupt) -> int:
    """One notice for an interrupt; the exit code of the signal (130 for Ctrl-C, 128 + N for signal N)."""
    if isinstance(exc, Terminated):
        print(f"{PROG}: {exc.args[0]}; nothing half-written was left", file=sys.stderr, flush=True)
        return 128 + exc.signum
    print(f"{PROG}: interrupted; nothing half-written was left", file=sys.stderr, flush=True)
    return 130
