"""Where the small-pair path pays: ``guided.nearest`` in one compiled call against the index path.

Usage::

    python benchmarks/small_pairs.py

Writes ``benchmarks/results/small_pairs.md``. One thread (kernels and BLAS), uniform random keypoints in
a 640 x 480 image and random integer 128-d descriptors, tol 2 px, depth range (0.5, 20) in the unit of
``t``, ratio 1 (every query's nearest candidate). Both paths give the same results (checked here, and in
``tests/core/test_small.py``); :data:`episeg_cv.matching.small.SMALL_PAIRS` is the size below which the
library takes the small path. Best of 7 calls per cell.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"  # one core, set before numpy is imported

import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_metadata  # noqa: E402

from episeg_cv import TwoViewGeometry, set_num_threads  # noqa: E402
from episeg_cv.matching import guided, small  # noqa: E402
from episeg_cv.matching.config import AcceptRule, SearchConfig  # noqa: E402

COMMAND = "python benchmarks/small_pairs.py"
SIZES = (250, 500, 1000, 2000, 4000)
POSES = {"lateral": [1.0, 0.0, 0.05], "forward": [0.1, 0.05, 1.0]}


def best_of(f, n=7) -> float:
    best = float("inf")
    for _ in range(n):
        t = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - t)
    return best


def main() -> int:
    set_num_threads(1)
    cv2.setNumThreads(1)
    rng = np.random.default_rng(0)
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    R = cv2.Rodrigues(np.array([0.02, 0.05, 0.01]))[0]
    search, rule = SearchConfig(tol=2.0, depth_range=(0.5, 20.0)), AcceptRule(ratio=1.0)
    rows = []
    for pose, t in POSES.items():
        g = TwoViewGeometry(K, K, R, t, image_size1=(640, 480), image_size2=(640, 480))
        for n in SIZES:
            p1, p2 = rng.uniform(0, [640, 480], (n, 2)), rng.uniform(0, [640, 480], (n, 2))
            d1 = rng.integers(0, 60, (n, 128)).astype(np.float32)
            d2 = rng.integers(0, 60, (n, 128)).astype(np.float32)
            inputs = guided.MatchInputs.check(d1, d2, p1, p2, "l2")
            call = lambda: guided.nearest(inputs, g, search, rule, prefilter=True)  # noqa: E731
            keep = small.SMALL_PAIRS
            try:
                small.SMALL_PAIRS = 1 << 62
                a, t_small = call(), best_of(call)
                small.SMALL_PAIRS = -1
                b, t_index = call(), best_of(call)
            finally:
                small.SMALL_PAIRS = keep
            same = all(np.array_equal(x, y) for x, y in zip(a, b))
            rows.append((pose, n, t_small, t_index, same, n * n <= keep))
            print(pose, n, f"small {t_small * 1e3:.2f} ms, index {t_index * 1e3:.2f} ms", flush=True)
    meta = machine_metadata()
    lines = ["# The small-pair path against the index path (`guided.nearest`, one thread)", "",
             f"Made by `{COMMAND}`. {meta if isinstance(meta, str) else ', '.join(f'{k} {v}' for k, v in meta.items())}",
             "", " ".join(next(p for p in __doc__.split("\n\n") if p.startswith("Writes")).split()), "",
             "| pose | keypoints a side | small path (ms) | index path (ms) | index / small | same results | library takes |",
             "|---|---:|---:|---:|---:|---|---|"]
    for pose, n, a, b, same, takes in rows:
        lines.append(f"| {pose} | {n} | {a * 1e3:.2f} | {b * 1e3:.2f} | {b / a:.2f}x | {'yes' if same else 'NO'} | "
                     f"{'small' if takes else 'index'} |")
    out = Path(__file__).resolve().parent / "results" / "small_pairs.md"
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")
    return 0 if all(r[4] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
