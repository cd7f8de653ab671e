"""Threads next to a busy process: OpenMP's wait policy for the library's kernels.

Usage::

    python benchmarks/contention.py [--calls N] [--n N] [--image-size WxH] [--out DIR]

The pair of ``benchmarks/speed.py`` at n = 10k (pose ``forward``, 1600 x 1200 render, the 10k strongest
SIFT keypoints of each image) is matched by ``SegmentMatcher.match`` in fresh child processes, one per
cell of the table: numba's OpenMP threads as the library starts them (``OMP_WAIT_POLICY=PASSIVE`` unless
the environment sets one: :mod:`episeg_cv.threads`) or spinning as GNU OpenMP's default does (the child
gets ``OMP_WAIT_POLICY`` unset and ``GOMP_SPINCOUNT=300000``, which is what libgomp uses when no policy is
set: see the ``OMP_DISPLAY_ENV=VERBOSE`` line in the output); the machine idle, or with one more process
that spins in a Python loop (a stand-in for any other work: a detector, a second matcher, a build). In
each child, ``episeg_cv.set_num_threads(n)`` and ``cv2.setNumThreads(n)`` for n = 1 and 2 (interleaved,
``--calls`` calls each, after a warm-up), and ``cv2.BFMatcher.knnMatch(k=2)`` at the same thread
counts (3 calls each, same load) for the ratio.

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
POLICIES = {"library default (passive)": {}, "spinning (GNU OpenMP's default)": {"GOMP_SPINCOUNT": "300000"}}
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


def run_cell(path: Path, calls: int, env_extra: dict, busy: bool) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    env.update(env_extra)
    env["OMP_DISPLAY_ENV"] = "VERBOSE"
    hog = subprocess.Popen([sys.executable, "-c", BUSY]) if busy else None
    try:
        time.sleep(0.2 if busy else 0.0)
        out = subprocess.run([sys.executable, __file__, "--child", str(path), "--calls", str(calls)], env=env,
                             capture_output=True, text=True, timeout=1800)
    finally:
        if hog is not None:
            hog.kill()
            hog.wait()
    if out.returncode != 0:
        raise RuntimeError(out.stderr)
    spin = [line.split("=", 1)[1].strip().strip("'") for line in out.stderr.splitlines()
            if line.strip().startswith("GOMP_SPINCOUNT")]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    res["gomp_spincount"] = spin[0] if spin else None
    return res


def write(results: dict, meta: dict, command: str, out: Path, seconds: float) -> None:
    lines = [
        "# Threads next to a busy process: OpenMP's wait policy",
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
    lines += [
        "",
        "The busy process is one Python loop at the same priority, so the machine has one core less than the "
        "matcher asks for. GNU OpenMP's default lets a thread that waits for the others spin for 300000 "
        "iterations before it sleeps: at the end of every kernel the matcher's thread spins while the thread it "
        "waits for is off its core, and a `match` runs about a dozen kernels. Passive threads sleep at once and "
        "cost a wake-up per kernel instead (the idle rows).",
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
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child, args.calls)))
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
    command = "python benchmarks/contention.py" + (f" --calls {args.calls}" if args.calls != 40 else "") + \
        (f" --n {args.n}" if args.n != N else "") + (f" --image-size {args.image_size}" if size != IMAGE_SIZE else "")
    args.out.mkdir(parents=True, exist_ok=True)
    write({"calls": args.calls, "n": args.n, "image_size": "x".join(map(str, size)), "rows": rows}, meta, command,
          args.out, time.perf_counter() - t0)
    print(shlex.quote(str(args.out / "contention.md")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
