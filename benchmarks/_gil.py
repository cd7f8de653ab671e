"""How much of a collection's pair matching is Python (GIL held), for ``benchmarks/colmap.py``.

The pairs of ``match_model`` (its own jobs, captured from a run on one core) are matched again on one
thread, with every compiled kernel of the matching modules wrapped to sum the calling thread's CPU time
spent inside it. The rest of the pairs' CPU time is Python (and numpy calls) between the kernels: it
holds the GIL, so a pool of N threads runs the pairs at most ``1 / share`` times faster than one thread,
whatever N. (The kernels' own argument checks at entry hold the GIL too and are counted as kernel time:
the share is a lower bound.)
"""

from __future__ import annotations

import importlib
import time

KERNEL_MODULES = ("episeg_cv.matching._kernels", "episeg_cv.matching._index_kernels",
                  "episeg_cv.matching._small_kernels", "episeg_cv.matching._pair_kernel",
                  "episeg_cv.matching._band_kernels", "episeg_cv._geometry_kernels")


def python_share(model, image_dir, work, cache, repeats: int = 3) -> dict:
    """``{"pairs", "cpu_s", "kernels_s", "python_share", "ceiling"}`` (medians over ``repeats``)."""
    import numpy as np
    from numba.core.registry import CPUDispatcher

    from episeg_cv import colmap, threads
    from episeg_cv.colmap import pipeline

    jobs = []
    original = pipeline._match_chunk

    def capture(chunk):
        jobs.extend(chunk)
        return original(chunk)

    pipeline._match_chunk = capture
    try:
        colmap.match_model(model, image_dir, work / "gil.db", cache_dir=cache, overwrite=True, log=lambda m: None,
                           workers=1)
    finally:
        pipeline._match_chunk = original
    inside = [0.0]
    saved = []
    for name in KERNEL_MODULES:
        mod = importlib.import_module(name)
        for attr in dir(mod):
            f = getattr(mod, attr)
            if isinstance(f, CPUDispatcher):
                def timed(*a, _f=f, **k):
                    t0 = time.thread_time()
                    try:
                        return _f(*a, **k)
                    finally:
                        inside[0] += time.thread_time() - t0
                saved.append((mod, attr, f))
                setattr(mod, attr, timed)
    cpu, kern = [], []
    try:
        with threads.limited(1):
            original(jobs[:32])  # warm
            for _ in range(repeats):
                inside[0] = 0.0
                t0 = time.thread_time()
                original(jobs)
                cpu.append(time.thread_time() - t0)
                kern.append(inside[0])
    finally:
        for mod, attr, f in saved:
            setattr(mod, attr, f)
    c, k = float(np.median(cpu)), float(np.median(kern))
    share = (c - k) / c if c > 0 else float("nan")
    return {"pairs": len(jobs), "cpu_s": c, "kernels_s": k, "python_share": share,
            "ceiling": 1.0 / share if share > 0 else float("inf")}
