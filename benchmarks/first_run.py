"""The first run after installing: how long each main command takes while numba compiles its kernels.

Usage::

    python benchmarks/first_run.py            # 3 warm runs per command, all in order, then `episeg compile` first
    python benchmarks/first_run.py --quick    # demo and the posed match only, 1 warm run
    python benchmarks/first_run.py --record   # rewrite episeg_cv/kernel_signatures.json (after changing kernels)

Writes ``benchmarks/results/first_run.md`` and ``first_run.json``.

The kernels are compiled with ``cache=True``: the first call of each compiles it (seconds to a minute
for the largest, whatever the input size) and writes it to numba's cache; every later process loads it.
Each command here runs as a user runs it (``python -m episeg_cv.cli ...``, a new process) with a cache
of its own, empty at first (``NUMBA_CACHE_DIR``): so **cold** is the command's first run on a fresh
install, with nothing compiled by another command, and **warm** (the median of the later runs with the
same cache) is every run after it. Cold minus warm is what the first run pays for compiling. Then all
the commands run once more, in order, sharing one new cache, as on a real install. The
inputs (Motorcycle from scikit-image, a synthetic collection from ``episeg synthetic``) are made before
any timing, in a process of their own.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_metadata, package_dirty  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
COMMAND = "python benchmarks/first_run.py"
VIEWS = 8  # of the synthetic collection


def episeg(*args) -> list[str]:
    return [sys.executable, "-m", "episeg_cv.cli", "-q", *map(str, args)]


def prepare(work: Path) -> dict:
    """Motorcycle as two PNGs and a synthetic collection of :data:`VIEWS` views; the commands to time."""
    subprocess.run([sys.executable, "-c", (
        "import cv2, skimage.data as d, sys; l, r, _ = d.stereo_motorcycle(); "
        "cv2.imwrite(sys.argv[1], l[:, :, ::-1]); cv2.imwrite(sys.argv[2], r[:, :, ::-1])"),
        work / "left.png", work / "right.png"], check=True)
    subprocess.run(episeg("synthetic", work / "room", "--views", VIEWS), check=True)
    left, right, room = work / "left.png", work / "right.png", work / "room"
    calib = ROOT / "data" / "motorcycle" / "calib.json"
    return {
        "episeg demo": lambda out: episeg("demo", "--out", out),
        "episeg match (Motorcycle, posed)": lambda out: episeg("match", left, right, "--calib", calib,
                                                               "--out", out / "m.json"),
        "episeg match (Motorcycle, no pose)": lambda out: episeg("match", left, right, "--out", out / "m.json"),
        f"episeg colmap --triangulate ({VIEWS} synthetic views, all cores)": lambda out: episeg(
            "colmap", room / "model", room / "images", "--database", out / "x.db", "--cache", out / "features",
            "--triangulate", out / "tri"),
        f"episeg colmap ({VIEWS} synthetic views, --workers 1)": lambda out: episeg(
            "colmap", room / "model", room / "images", "--database", out / "x.db", "--cache", out / "features",
            "--workers", 1),
    }


def record(path: Path) -> None:
    """Write :data:`episeg_cv.kernel_cache.SIGNATURES`: run the commands of :func:`prepare` in one process
    on an empty cache, and keep each kernel that one of them compiled (not as another kernel's callee),
    with its argument types and the seconds its compiling took (``compile_kernels`` schedules by them)."""
    with tempfile.TemporaryDirectory(prefix="episeg_record_") as tmp:
        env = dict(os.environ, NUMBA_CACHE_DIR=str(Path(tmp) / "cache"))
        subprocess.run([sys.executable, __file__, "--record-child", str(path), tmp], check=True, env=env)


def _record_child(path: Path, work: Path) -> None:
    from numba.core import event

    from episeg_cv.cli import main as episeg_main

    seconds, kernels, stack = {}, {}, []

    class Listener(event.Listener):
        def on_start(self, ev):
            stack.append(time.perf_counter())

        def on_end(self, ev):
            t0 = stack.pop()
            d = ev.data.get("dispatcher")
            f = getattr(d, "py_func", None)
            if stack or f is None or not f.__module__.startswith("episeg_cv"):
                return
            name = f"{f.__module__}:{f.__qualname__}"
            seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - t0
            kernels[name] = d

    cmds = prepare(work)
    with event.install_listener("numba:compile", Listener()):
        for k, make in enumerate(cmds.values()):
            out = work / f"record_{k}"
            out.mkdir()
            argv = make(out)[3:]  # after "python -m episeg_cv.cli"
            if episeg_main(argv) != 0:
                raise SystemExit(f"{argv} failed")
    listed = {name: {"seconds": round(seconds[name], 3), "parallel": bool(d.targetoptions.get("parallel")),
                     "signatures": [[repr(t) for t in sig] for sig in d.signatures]}
              for name, d in sorted(kernels.items())}
    import numba

    path.write_text(json.dumps({"made_by": f"{COMMAND} --record", "numba": numba.__version__,
                                "commands": list(cmds), "kernels": listed}, indent=1) + "\n")
    print(f"wrote {path}: {len(listed)} kernels, {sum(len(v['signatures']) for v in listed.values())} signatures, "
          f"{sum(seconds.values()):.1f} s of compiling")


def timed(cmd: list[str], cache: Path) -> float:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def run_one(make_cmd, work: Path, warm_runs: int) -> dict:
    cache = Path(tempfile.mkdtemp(prefix="numba_", dir=work))
    times = []
    for k in range(1 + warm_runs):
        out = work / f"out_{cache.name}_{k}"
        out.mkdir()
        times.append(timed(make_cmd(out), cache))
        shutil.rmtree(out)
    size = sum(f.stat().st_size for f in cache.rglob("*") if f.is_file())
    cold, warm = times[0], statistics.median(times[1:])
    return {"cold_s": cold, "warm_s": warm, "warm_runs_s": times[1:], "compile_s": cold - warm,
            "cache_mib": size / 2**20, "cache_files": sum(1 for f in cache.rglob("*.nbc"))}


def run_sequence(cmds: dict, work: Path, cache: Path | None = None) -> dict:
    """Every command once, in order, sharing one cache (default: a new, empty one: a fresh install)."""
    cache = Path(tempfile.mkdtemp(prefix="numba_seq_", dir=work)) if cache is None else cache
    out = {}
    for k, (name, make) in enumerate(cmds.items()):
        folder = work / f"seq_{k}"
        folder.mkdir()
        out[name] = timed(make(folder), cache)
        shutil.rmtree(folder)
    return out


def run_ahead(cmds: dict, work: Path, processes: int) -> dict:
    """``episeg compile --processes N`` on an empty cache, then :func:`run_sequence` on that cache."""
    cache = Path(tempfile.mkdtemp(prefix=f"numba_ahead{processes}_", dir=work))
    return {"compile_s": timed(episeg("compile", "--processes", processes), cache),
            "commands": run_sequence(cmds, work, cache)}


def lpt_makespan(seconds: list, processes: int) -> float:
    """The longest share when ``seconds`` are dealt out to ``processes`` as
    :func:`episeg_cv.kernel_cache.compile_kernels` deals the kernels (:func:`~episeg_cv.kernel_cache.deal`)."""
    from episeg_cv.kernel_cache import deal

    shares = deal(dict(enumerate(seconds)), processes)
    return max(sum(seconds[k] for k in share) for share in shares)


def markdown(res: dict) -> str:
    m = res["machine"]
    L = ["# The first run after installing: compile time of each command", "",
         f"Made by `{res['command']}` on {m['date']} in {res['seconds']:.0f} s ({m['cpu']}, {m['cpu_count']} cores, "
         f"python {m['python']}, numpy {m['numpy']}, cv2 {m['cv2']}, numba {res['numba']}, episeg_cv "
         f"{m['episeg_cv']}, git HEAD {m['git_commit']}{' + uncommitted changes' if res['dirty'] else ''}). "
         "Raw numbers in `first_run.json`.", "",
         "Each command runs in a new process, as from a shell, with a numba cache of its own that is empty at its "
         "first run (`NUMBA_CACHE_DIR`): **cold** is that first run (everything it needs compiled, as on a fresh "
         f"install), **warm** the median of the next {res['warm_runs']} run(s), which load the compiled kernels "
         "from the cache. Cold minus warm is the one-time cost of compiling. Commands that share kernels share "
         "the cost on a real install (one cache beside the package): the first command a user runs pays most "
         "of it, so the per-command figures overlap and do not add up.", "",
         "| command | cold (s) | warm (s) | compiling (s) | cache (MiB, files) |", "|---|---:|---:|---:|---:|"]
    for name, r in res["commands"].items():
        L.append(f"| `{name}` | {r['cold_s']:.1f} | {r['warm_s']:.1f} | {r['compile_s']:.1f} | "
                 f"{r['cache_mib']:.1f}, {r['cache_files']} |")
    seq = res["sequence"]
    L += ["", "**One install, the commands in this order** (one cache, empty at the start, shared as on a real "
          "install: each command compiles only what the ones before it did not):", "",
          "| command, in order | first run (s) | warm (s, from above) |", "|---|---:|---:|"]
    for name, t in seq.items():
        L.append(f"| `{name}` | {t:.1f} | {res['commands'][name]['warm_s']:.1f} |")
    L.append(f"| all | {sum(seq.values()):.1f} | {sum(r['warm_s'] for r in res['commands'].values()):.1f} |")
    L += ["", "Compiling runs on one core per process (numba compiles one function at a time): the first runs "
          "above use one core, whatever the machine has.", ""]
    ahead = res.get("ahead")
    if ahead:
        L += ["## Ahead of the first run: `episeg compile`", "",
              "`episeg compile --processes N` on an empty cache compiles every kernel of "
              "`episeg_cv/kernel_signatures.json` (the kernels these commands compile, recorded from them by "
              "`python benchmarks/first_run.py --record`), dealt out to N processes, the longest first; then "
              "each command runs once, in order, on that cache:", "",
              "| | " + " | ".join(f"--processes {n}" for n in ahead) + " |",
              "|---|" + "---:|" * len(ahead),
              "| `episeg compile` (s) | " + " | ".join(f"{a['compile_s']:.1f}" for a in ahead.values()) + " |"]
        names = list(next(iter(ahead.values()))["commands"])
        for name in names:
            L.append(f"| then `{name}` (s) | " + " | ".join(f"{a['commands'][name]:.1f}" for a in ahead.values())
                     + " |")
        L.append("| all, compile included (s) | " + " | ".join(
            f"{a['compile_s'] + sum(a['commands'].values()):.1f}" for a in ahead.values()) + " |")
        rec = res["recorded"]
        model = {n: lpt_makespan(rec["seconds"], n) for n in (1, 2, 4, 8, 16)}
        measured = "; ".join(f"{n} process(es): {a['compile_s']:.1f} s measured, {lpt_makespan(rec['seconds'], int(n)):.1f} s "
                             "in the model" for n, a in ahead.items())
        L += ["", f"Against {sum(seq.values()):.1f} s for the commands' first runs in order (the table above). The "
              f"list holds {rec['kernels']} kernels; compiled one after the other in the recording process they took "
              f"{sum(rec['seconds']):.1f} s, the longest {max(rec['seconds']):.1f} s (`{rec['longest']}`; the "
              "commands before it had compiled some of its callees). Compiling all of them takes longer than one "
              "command's first run compiles for itself, so on "
              "few cores `episeg compile` pays when several commands will run (or to make an install warm "
              "before it is used, as a Docker image or a Dask worker's machine).", "",
              "**What to expect on more cores** (a model, not a measurement): the recorded times dealt out as "
              "`episeg compile` deals them give a longest share of "
              + ", ".join(f"{t:.1f} s on {n}" for n, t in model.items()) + " processes. No share is shorter than "
              "the longest kernel, so from a few cores on that kernel sets the time. The runs take longer than the "
              f"model ({measured}): each process starts Python and numba, and compiles the callees its kernels share "
              "with another process's kernels unless that process has cached them first. "
              + (f"So the model's floor is too low: `{rec['longest']}` alone, compiled by itself on an empty cache "
                 f"(all its callees too), took **{rec['longest_alone_s']:.1f} s**, which is about what `episeg "
                 "compile` can take on any number of cores." if "longest_alone_s" in rec else ""), ""]
    L += ["The cache is keyed by the source files: reinstalling the same version keeps it, editing a kernel's "
          "module recompiles that module's kernels.", ""]
    return "\n".join(L)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="the demo and the posed match only, one warm run")
    p.add_argument("--out", type=Path, default=OUT, help="folder for first_run.md / .json")
    p.add_argument("--record", action="store_true",
                   help="write episeg_cv/kernel_signatures.json (the kernels the commands compile) and stop")
    p.add_argument("--record-child", nargs=2, type=Path, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.record_child:
        _record_child(*args.record_child)
        return 0
    if args.record:
        from episeg_cv.kernel_cache import SIGNATURES

        record(SIGNATURES)
        return 0
    import numba

    t0 = time.perf_counter()
    warm_runs = 1 if args.quick else 3
    with tempfile.TemporaryDirectory(prefix="episeg_first_run_") as tmp:
        work = Path(tmp)
        cmds = prepare(work)
        if args.quick:
            cmds = dict(list(cmds.items())[:2])
        res = {"commands": {}}
        for name, make in cmds.items():
            print(f"{name} ...", flush=True)
            res["commands"][name] = r = run_one(make, work, warm_runs)
            print(f"  cold {r['cold_s']:.1f} s, warm {r['warm_s']:.1f} s", flush=True)
        print("all in order, one cache ...", flush=True)
        res["sequence"] = run_sequence(cmds, work)
        if not args.quick:
            from episeg_cv.kernel_cache import SIGNATURES
            from episeg_cv.threads import available_cores

            res["ahead"] = {}
            for n in sorted({1, available_cores()}):
                print(f"episeg compile --processes {n}, then all in order ...", flush=True)
                res["ahead"][n] = run_ahead(cmds, work, n)
            listed = json.loads(SIGNATURES.read_text())["kernels"]
            longest = max(listed, key=lambda k: listed[k]["seconds"])
            print(f"{longest} alone ...", flush=True)
            alone = timed([sys.executable, "-c", "import sys; from episeg_cv.kernel_cache import compile_kernels; "
                           "compile_kernels(1, functions=[sys.argv[1]])", longest],
                          Path(tempfile.mkdtemp(prefix="numba_alone_", dir=work)))
            res["recorded"] = {"kernels": len(listed), "seconds": [k["seconds"] for k in listed.values()],
                               "longest": longest, "longest_alone_s": alone}
    res.update(command=COMMAND + (" --quick" if args.quick else ""), machine=machine_metadata(),
               numba=numba.__version__, dirty=package_dirty(), warm_runs=warm_runs,
               seconds=time.perf_counter() - t0)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "first_run.json").write_text(json.dumps(res, indent=1))
    (args.out / "first_run.md").write_text(markdown(res))
    print(f"wrote {args.out / 'first_run.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
