"""Console output of the ``episeg`` command: results on stdout, notes and progress on stderr."""

from __future__ import annotations

import sys
import time

__all__ = ["PROG", "UserError", "Console", "Progress", "table", "one_line"]

PROG = "episeg"


class UserError(Exception):
    """Bad input from the user (exit code 1)."""


# --------------------------------------------------------------------------------------
# Console output
# --------------------------------------------------------------------------------------
class Console:
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

    def progress(self, total: int, desc: str) -> "Progress":
        return Progress(self, total, desc)


class Progress:
    """A small progress bar on stderr: redrawn in place on a terminal, one line per step with --verbose."""

    def __init__(self, console: Console, total: int, desc: str):
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


def table(header, rows) -> str:
    """A plain-text table, the first column left-aligned and the others right-aligned."""
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    fmt = lambda r: "  ".join(str(c).ljust(w) if i == 0 else str(c).rjust(w)  # noqa: E731
                              for i, (c, w) in enumerate(zip(r, widths)))
    return "\n".join([fmt(header), "  ".join("-" * w for w in widths), *map(fmt, rows)])


def one_line(exc: BaseException) -> str:
    """An exception's message on one line (its type name when it has none)."""
    return " ".join(str(exc).split()) or type(exc).__name__
