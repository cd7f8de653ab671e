"""A Dask worker's preparation (:class:`._dask.WarmWorker`, and each task of :class:`.runner.Runner`).

One thread per worker for OpenCV, BLAS and the kernels, glibc's allocation thresholds back, the
compiled kernels loaded, and a watchdog that ends a local cluster's worker when the run that started
it is gone. Imported by the workers themselves; it knows nothing of Dask.
"""

from __future__ import annotations

import os
import threading
import time

import cv2

__all__ = ["single_thread", "undo_malloc_trim", "warm_up", "watch_parent", "MMAP_THRESHOLD", "TRIM_THRESHOLD"]

_WORKER_LIMITED = False



def single_thread():
    """One thread per worker process, for OpenCV, BLAS and the compiled kernels (idle threads spin and steal the core).

    Without it, two workers on two cores ran slower than one process.
    """
    global _WORKER_LIMITED
    if not _WORKER_LIMITED:
        from threadpoolctl import threadpool_limits

        from ..threads import set_num_threads

        cv2.setNumThreads(1)
        threadpool_limits(1)
        set_num_threads(1)
        _WORKER_LIMITED = True


#: glibc's ``mallopt`` parameters, and the values :func:`undo_malloc_trim` sets (those glibc's own dynamic
#: thresholds reach on 64-bit Linux: large arrays from the heap, not from fresh pages).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD = 32 << 20
TRIM_THRESHOLD = 64 << 20


def undo_malloc_trim() -> bool:
    """Give back glibc's large-allocation behaviour in a Dask worker; True when it was changed.

    Dask's nannies start workers with ``MALLOC_TRIM_THRESHOLD_=65536`` (so that freed memory goes back to
    the system). Setting it turns off glibc's dynamic mmap threshold, so every array above 128 KiB is a
    fresh mapping whose pages fault on first touch: matching a pair took 20 % longer, with about 180 page
    faults a pair against none (24-view room). Here both thresholds are set to what glibc reaches by
    itself (mmap above 32 MiB, trim above 64 MiB). Only where that variable is set and the C library is
    glibc; elsewhere nothing is changed.
    """
    if not os.environ.get("MALLOC_TRIM_THRESHOLD_"):
        return False
    import ctypes

    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))


def warm_up() -> None:
    """Load the compiled kernels a worker's tasks use (from numba's cache), with a few tiny matches: the
    small-pair path and the large-pair paths of :func:`~.job.match_pairs` (one compiled call on a
    worker's one kernel thread, :mod:`~episeg_cv.matching.fused`; and stage by stage: pairs, both
    directions, the padding), on read-only arrays as the feature store's. Without them a worker's first
    large pair took 13-35 ms longer than the next ones. (The band's sample pairs run in the driver:
    :meth:`Runner.imap_here`.)"""
    import numpy as np

    from ..geometry import TwoViewGeometry
    from ..matching import fused, guided, small
    from ..matching.config import AcceptRule, SearchConfig
    from ..matching.filtering import keep_mask

    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    g = TwoViewGeometry(K, K, np.eye(3), [-1.0, 0, 0], image_size1=(100, 100), image_size2=(100, 100))
    rng = np.random.default_rng(0)
    rule, inf = AcceptRule(), float("inf")
    for n in (2, 800):  # 800 x 800 keypoint pairs: above small.SMALL_PAIRS, the index path
        p = rng.uniform(0, 100, (n, 2))
        d = rng.random((n, 32)).astype(np.float32)
        p.flags.writeable = d.flags.writeable = False  # as the feature store's arrays (numba types them apart)
        inputs = guided.MatchInputs.check(d, d, p, p, "l2")
        for tol in (2.0, 64.0):
            pairs, _ = guided.match(inputs, g, SearchConfig(tol=tol), rule)
            guided.nearest(inputs, g, SearchConfig(tol=tol), rule, prefilter=True)
            keep_mask(pairs[:, ::-1], p, p, g.inverse(), SearchConfig(tol=tol))
            for loose in (None, 1.0):
                fused.match_pair(p, inputs.distances.a, p, inputs.distances.b, "l2", g, (0.0, inf), (0.0, inf),
                                 SearchConfig(tol=tol), rule, loose)
    a = inputs.distances.a[:2]  # the many-small-pairs kernel (serial: a worker runs one thread)
    small.many([small.SmallPair(p[:2], a, p[:2], a, g, 2.0, (0.0, inf), (0.0, inf))], rule, 1.0, "l2",
               lambda n2, n_pad: np.arange(n_pad))


def watch_parent(pid: int, interval: float = 1.0) -> None:
    """End this process (``os._exit``) as soon as process ``pid`` no longer exists or we were re-parented."""
    parent = os.getppid()

    def watch():
        while True:
            time.sleep(interval)
            gone = os.getppid() != parent
            if not gone:
                try:
                    os.kill(pid, 0)
                except ProcessLookupError:
                    gone = True
                except PermissionError:
                    pass
            if gone:
                os._exit(1)

    threading.Thread(target=watch, name="episeg-watchdog", daemon=True).start()
