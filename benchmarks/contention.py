"""Threads next to a busy process, and short parallel loops: OpenMP's wait policy for the library's kernels.

Usage::

    python benchmarks/contention.py [--calls N] [--n N] [--image-size WxH] [--out DIR]

Two measurements, each in fresh child processes, one per wait policy of numba's OpenMP threads (GNU
OpenMP reads it once, when it is loaded): the library's default (a short spin, ``GOMP_SPINCOUNT`` =
``episeg_cv.threads.SPIN_COUNT``, unless the environment sets a policy: :mod:`episeg_cv.threads`), sleeping
at once (``OMP_WAIT_POLICY=PASSIVE``), and GNU OpenMP's own default (``GOMP_SPINCOUNT=300000``, what libgomp
uses when nothing is set). Each row prints the spin count libgomp reported (``OMP_DISPLAY_ENV=VERBOSE``).

1. ``SegmentMatcher.match`` on the pair of ``benchmarks/speed.py`` at n = 10k (pose ``forward``, 1600 x 1200
   render, the 10k strongest SIFT keypoints of each image), the machine idle or with one more process that
   spins in a Python loop (a stand-in for any other work: a detector, a second matcher, a build);
   ``episeg_cv.set_num_threads(n)`` and ``cv2.setNumThreads(n)`` for n = 1 and 2 (interleaved, ``--calls``
   calls each, after a warm-up), and ``cv2.BFMatcher.knnMatch(k=2)`` at the same thread counts and load
   (3 calls each) for the ratio.
2. The track consensus (``MatchReport.seconds_verify`` of ``colmap.match_model``, features cached) on a
   synthetic 24-view room (``scenes.make_collection(24, (640, 480), seed=7)``), ``workers=1`` and ``2``,
   the median of 3 runs after a first one; the machine idle. Its big component runs thousands of short
   parallel loops.

Writes ``contention.md`` and ``contention.json`` into ``--out`` (default ``benchmarks/results``).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_metadata, package_dirty  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
N, POSE, IMAGE_SIZE = 10_000, "forward", (1600, 1200)
POLICIES = {"library default (short spin)": {}, "passive": {"OMP_WAIT_POLICY": "PASSIVE"},
            "GNU OpenMP's default (long spin)": {"GOMP_SPINCOUNT": "300000"}}
COLLECTION = (24, (640, 480), 7)
LOADS = ("idle", "one busy process")
BUSY = "while True: pass"


def make_input(path: Path, n: int = N, image_size=IMAGE_SIZE) -> None:
    """The forward pair of ``speed.py`` (``n`` strongest keypoints), saved for the children (geometry pickled
    with the arrays)."""
    import pickle

    import speed

    pair, kp1, d1, kp2, d2 = speed.setup(POSE, image_size)
    kp1, d1, _ = speed.strongest(kp1, d1, n)
    kp2, d2, _ = speed.strongest(kp2, d2, n)
    cols = lambda kps: np.array([(*k.pt, k.size, k.angle, k.response, k.octave) for k in kps])  # noqa: E731
    with open(path, "wb") as fh:
        pickle.dump({"geometry": pair.geometry, "k1": cols(kp1), "k2": cols(kp2), "d1": d1, "d2": d2}, fh)


def child(path: str, calls: int) -> dict:
    """Times in this process (its environment sets the policy): median and 90th percentile, ms."""
    import pickle

    import cv2

    import episeg_cv
    from episeg_cv import SegmentMatcher

    episeg_cv.get_num_threads()  # numba's threads start here, as at the library's first parallel kernel
    with open(path, "rb") as fh:
        data = pickle.load(fh)
    kps = [[cv2.KeyPoint(float(x), float(y), float(s), float(a), float(r), int(o)) for x, y, s, a, r, o in k]
           for k in (data["k1"], data["k2"])]
    d1, d2 = data["d1"], data["d2"]
    matcher, bf = SegmentMatcher(data["geometry"], cv2.NORM_L2), cv2.BFMatcher(cv2.NORM_L2)
    times = {1: [], 2: []}
    for n in (1, 2):
        episeg_cv.set_num_threads(n)
        cv2.setNumThreads(n)
        for _ in range(3):
            matcher.match(d1, d2, *kps)
    for _ in range(calls):
        for n in (1, 2):
            episeg_cv.set_num_threads(n)
            cv2.setNumThreads(n)
            t0 = time.perf_counter()
            matcher.match(d1, d2, *kps)
            times[n].append(time.perf_counter() - t0)
    bft = {}
    for n in (1, 2):
        cv2.setNumThreads(n)
        ts = []
        for _ in range(3):
            t0 = time.perf_counter()
            bf.knnMatch(d1, d2, k=2)
            ts.append(time.perf_counter() - t0)
        bft[n] = float(np.median(ts))
    out = {}
    for n in (1, 2):
        t = np.array(times[n])
        out[str(n)] = {"median_ms": float(np.median(t) * 1e3), "p90_ms": float(np.percentile(t, 90) * 1e3),
                       "bf_ms": bft[n] * 1e3, "x_bf": float(bft[n] / np.median(t))}
    return out


def child_consensus(folder: str) -> dict:
    """``seconds_verify`` of ``match_model`` with 1 and 2 workers (median of 3 after a first run)."""
    import episeg_cv

    episeg_cv.get_num_threads()  # numba's threads start first: the first libgomp report is theirs (pycolmap
    from episeg_cv import colmap  # loads a libgomp of its own, which reports too)

    folder = Path(folder)
    out = {}
    for workers in (1, 2):
        times = []
        for _ in range(4):
            rep = colmap.match_model(folder / "model", folder / "images", folder / f"w{workers}.db",
                                     cache_dir=folder / "cache", overwrite=True, log=lambda m: None, workers=workers)
            times.append(rep.seconds_verify)
        out[str(workers)] = {"median_s": float(np.median(times[1:])), "runs_s": times}
    return out


def run_cell(path: Path, calls: int, env_extra: dict, busy: bool, mode: str = "--child") -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    env.update(env_extra)
    env["OMP_DISPLAY_ENV"] = "VERBOSE"
    hog = subprocess.Popen([sys.executable, "-c", BUSY]) if busy else None
    try:
        time.sleep(0.2 if busy else 0.0)
        out = subprocess.run([sys.executable, __file__, mode, str(path), "--calls", str(calls)], env=env,
                             capture_output=True, text=True, timeout=1800)
    finally:
        if hog is not None:
            hog.kill()
            hog.wait()
    if out.returncode != 0:
        raise RuntimeError(out.stderr)
    spin = [line.split("=", 1)[1].strip().strip("'") for line in out.stderr.splitlines()
            if line.strip().startswith("GOMP_SPINCOUNT")]  # the first: numba's (the children start it first)
    res = json.loads(out.stdout.strip().splitlines()[-1])
    res["gomp_spincount"] = spin[0] if spin else None
    return res


def write(results: dict, meta: dict, command: str, out: Path, seconds: float) -> None:
    lines = [
        "# Threads next to a busy process, and short parallel loops: OpenMP's wait policy",
        "",
        f"Made by `{command}` on {meta['date']} in {seconds:.0f} s ({meta['cpu']}, {meta['cpu_count']} cores, "
        f"python {meta['python']}, cv2 {meta['cv2']}, episeg_cv {meta['episeg_cv']}, git {meta['git_commit']}"
        f"{', with uncommitted changes in episeg_cv/' if meta.get('dirty') else ''}). Raw numbers in "
        "`contention.json`.",
        "",
        f"`SegmentMatcher.match` at n = {results['n']} (pose `forward`, {results['image_size']} render, the pair "
        "of `speed.py`), in a fresh process per row; "
        f"{results['calls']} calls per thread count, interleaved; ms, median (90th percentile); `x BF`: "
        "`cv2.BFMatcher.knnMatch(k=2)` at the same thread count and load, divided by the median. "
        "`spin count`: what GNU OpenMP reported for the row (`OMP_DISPLAY_ENV=VERBOSE`; 0 = passive).",
        "",
        "| numba's OpenMP threads | load | spin count | 1 thread, ms | 2 threads, ms | 2 threads vs 1 | x BF, 1 thread |"
        " x BF, 2 threads |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for row in results["rows"]:
        one, two = row["times"]["1"], row["times"]["2"]
        lines.append(f"| {row['policy']} | {row['load']} | {row['times']['gomp_spincount']} | "
                     f"{one['median_ms']:.1f} ({one['p90_ms']:.1f}) | {two['median_ms']:.1f} ({two['p90_ms']:.1f}) | "
                     f"{one['median_ms'] / two['median_ms']:.2f} | {one['x_bf']:.1f} | {two['x_bf']:.1f} |")
    if results["consensus"]:
        n_views, image_size, seed = COLLECTION
        lines += ["", f"The track consensus of `colmap.match_model` on a synthetic {n_views}-view room "
                  f"(`scenes.make_collection({n_views}, {image_size}, seed={seed})`, features cached): "
                  "`MatchReport.seconds_verify`, median of 3 runs after a first one, the machine idle.", "",
                  "| numba's OpenMP threads | spin count | workers=1, s | workers=2, s | 2 vs 1 |", "|---|---:|---:|---:|---:|"]
        for row in results["consensus"]:
            one, two = row["times"]["1"]["median_s"], row["times"]["2"]["median_s"]
            lines.append(f"| {row['policy']} | {row['times']['gomp_spincount']} | {one:.3f} | {two:.3f} | "
                         f"{one / two:.2f} |")
    lines += [
        "",
        "The busy process is one Python loop at the same priority, so the machine has one core less than the "
        "matcher asks for. A thread that waits for the others at the end of a parallel loop spins on the core "
        "that the thread it waits for may need: GNU OpenMP's default spins 300000 times (milliseconds) before "
        "it sleeps, and a `match` runs about a dozen parallel loops. A passive thread sleeps at once and frees "
        "its core, but each parallel loop then pays a wake-up (tens of microseconds): nothing for `match`, much "
        "for the track consensus, whose big component runs a parallel loop per batch of eight rounds. The "
        "library's short spin sleeps after tens of microseconds.",
        "",
    ]
    (out / "contention.md").write_text("\n".join(lines))
    (out / "contention.json").write_text(json.dumps({"meta": meta, **results}, indent=1))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=40, help="calls per thread count in each row (default 40)")
    ap.add_argument("--n", type=int, default=N, help=f"keypoints per image (default {N})")
    ap.add_argument("--image-size", default="x".join(map(str, IMAGE_SIZE)), help="render size WxH (default 1600x1200)")
    ap.add_argument("--out", type=Path, default=RESULTS, help="output directory (default benchmarks/results)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--child-consensus", help=argparse.SUPPRESS)
    ap.add_argument("--no-consensus", action="store_true", help="leave out the track consensus (needs pycolmap)")
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child, args.calls)))
        return 0
    if args.child_consensus:
        print(json.dumps(child_consensus(args.child_consensus)))
        return 0
    t0 = time.perf_counter()
    meta = machine_metadata()
    meta["dirty"] = package_dirty()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "pair.pkl"
        size = tuple(int(v) for v in args.image_size.lower().split("x"))
        make_input(path, args.n, size)
        for load in LOADS:
            for policy, env in POLICIES.items():
                times = run_cell(path, args.calls, env, load != "idle")
                rows.append({"policy": policy, "load": load, "times": times})
                print(policy, load, {k: round(v["median_ms"], 1) for k, v in times.items() if k in "12"}, flush=True)
        consensus = []
        if not args.no_consensus:
            from episeg_cv import colmap, scenes

            n_views, image_size, seed = COLLECTION
            folder = Path(tmp) / "room"
            colmap.save_collection(scenes.make_collection(n_views, image_size, seed=seed), folder)
            colmap.match_model(folder / "model", folder / "images", folder / "warm.db", cache_dir=folder / "cache",
                               overwrite=True, log=lambda m: None)
            for policy, env in POLICIES.items():
                times = run_cell(folder, args.calls, env, False, "--child-consensus")
                consensus.append({"policy": policy, "times": times})
                print(policy, "consensus", {k: round(v["median_s"], 3) for k, v in times.items() if k in "12"},
                      flush=True)
    command = "python benchmarks/contention.py" + (f" --calls {args.calls}" if args.calls != 40 else "") + \
        (f" --n {args.n}" if args.n != N else "") + (f" --image-size {args.image_size}" if size != IMAGE_SIZE else "")
    args.out.mkdir(parents=True, exist_ok=True)
    command += " --no-consensus" if args.no_consensus else ""
    write({"calls": args.calls, "n": args.n, "image_size": "x".join(map(str, size)), "rows": rows,
           "consensus": consensus}, meta, command, args.out, time.perf_counter() - t0)
    print(shlex.quote(str(args.out / "contention.md")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
