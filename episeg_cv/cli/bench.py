"""``episeg bench``: run the scripts of the repository's ``benchmarks/`` folder (source checkout only)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

from .args import Formatter
from .console import PROG, Console, UserError

BENCH_SCRIPTS = ("table1.py", "compare.py", "speed.py")


def add_parser(sub, parents) -> None:
    p = sub.add_parser("bench", parents=parents, formatter_class=Formatter,
                       help="run the benchmarks (source checkout)",
                       description=f"Run the benchmark scripts {', '.join(BENCH_SCRIPTS)} of the repository's "
                                   "benchmarks/ folder with this Python, and list the files written to "
                                   "benchmarks/results/. Needs a source checkout, not a wheel.",
                       epilog="examples:\n  episeg bench --quick\n  episeg bench --only compare.py")
    p.add_argument("--quick", action="store_true", help="pass --quick to the scripts that accept it")
    p.add_argument("--only", nargs="+", choices=BENCH_SCRIPTS, default=None, metavar="SCRIPT",
                   help=f"run only these scripts ({', '.join(BENCH_SCRIPTS)})")
    p.add_argument("--dir", default=None, help="benchmarks folder (default: the repository's benchmarks/)")
    p.set_defaults(func=run)


def benchmarks_dir(given) -> Path:
    """The benchmarks folder: ``given``, or the source checkout's."""
    d = Path(given) if given is not None else Path(__file__).resolve().parents[2] / "benchmarks"
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


def run(args, console: Console) -> int:
    d = benchmarks_dir(args.dir)
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
