"""How many threads the compiled kernels use: :func:`set_num_threads`, :func:`get_num_threads`.

Like ``cv2.setNumThreads``: one setting for the whole process, every core by
default. It governs the library's numba kernels (the descriptors' finiteness
check, the segments, the candidate index, the candidate scan, the padding of
the acceptance rule) and the BLAS product that scores the padding references
(limited through threadpoolctl for the length of that product only).

Results do not depend on the thread count: every parallel loop either
computes items independently, or keeps per-thread minima under a total order
and merges them (see :mod:`episeg_cv.matching._kernels`).

Numba's own ``numba.set_num_threads`` is *per calling Python thread*: a
thread pool started by the user would not see a value set in the main thread.
So the setting here is kept by the library and applied, around each parallel
kernel, in whichever Python thread calls it (and numba's value restored
after). Until :func:`set_num_threads` is called, the library follows numba's
value of the calling thread (``numba.get_num_threads()``, all cores unless
changed).

**Idle threads spin briefly, then sleep.** Numba's OpenMP threads start, on
the library's first use of them, with GNU OpenMP's spin count set to
:data:`SPIN_COUNT` (``GOMP_SPINCOUNT``, set only while they start, and only
when the environment sets neither it nor ``OMP_WAIT_POLICY`` and nothing
started them before). GNU OpenMP's own default spins 300000 times before a
waiting thread sleeps: at the end of every kernel, a waiting thread spins on
the core that the thread it waits for may need. Next to one busy process a
10k ``match`` on two threads then had a 90th percentile of 113 ms against
15 ms with the short spin (``benchmarks/results/contention.md``). Sleeping at
once (``OMP_WAIT_POLICY=PASSIVE``) costs a wake-up per parallel loop: the track
consensus, which runs thousands of short parallel loops, was then slower on two
threads than on one (0.81x; 1.27x with the short spin). Set either variable
yourself before the first call to choose otherwise.
"""

from __future__ import annotations

import contextlib
import operator
import os
import threading

import numba
import numpy as np

from .interrupts import interrupt_in

__all__ = ["set_num_threads", "get_num_threads", "available_cores", "limit_this_thread", "limited", "use_parallel",
           "call_parallel", "run", "blas_limit", "Scratch", "blocks", "MIN_PARALLEL_ITEMS", "BLOCKS_PER_THREAD"]

#: Below this many items (rows, points, keypoints) a kernel runs its serial variant: forking threads
#: costs more than it saves (a few microseconds on an idle machine, milliseconds on an oversubscribed one).
MIN_PARALLEL_ITEMS = 2048
#: Work blocks per thread in a parallel kernel (uneven blocks even out).
BLOCKS_PER_THREAD = 8

_requested: int | None = None
_this_thread = threading.local()  # .limit: the cap of limit_this_thread in this Python thread, if any
_layer: str | None = None
_launch_lock = threading.Lock()
_blas = None
_blas_lock = threading.Lock()
_started = False
_start_lock = threading.Lock()
#: GNU OpenMP's spin count for numba's threads when the environment sets no wait policy (see the module's
#: notes): a waiting thread spins this many times (tens of microseconds), then sleeps.
SPIN_COUNT = 3000
_OMP_WAIT = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")


def _numba_threads() -> int:
    """``numba.get_num_threads()``; the first call starts numba's threads with :data:`SPIN_COUNT`
    (GNU OpenMP reads ``GOMP_SPINCOUNT`` once, when numba loads it at that start)."""
    global _started
    if not _started:
        with _start_lock:
            if not _started:
                _start_threads()
                _started = True
    return numba.get_num_threads()


def _start_threads() -> None:
    try:
        numba.threading_layer()
        return  # started before (by the program, or another library): its policy stays
    except ValueError:
        pass
    ours = not any(k in os.environ for k in _OMP_WAIT)  # a policy the environment sets is kept
    if ours:
        os.environ["GOMP_SPINCOUNT"] = str(SPIN_COUNT)
    try:
        numba.get_num_threads()
    finally:
        if ours:
            os.environ.pop("GOMP_SPINCOUNT", None)


def set_num_threads(n: int | None) -> None:
    """Use ``n`` threads in the library's compiled kernels (``None``: the default, every core).

    Parameters
    ----------
    n : int >= 1 or None
        Threads per call. Values above the number numba started with
        (``numba.config.NUMBA_NUM_THREADS``, the number of cores unless the
        ``NUMBA_NUM_THREADS`` environment variable says otherwise) are clipped
        to it. ``None`` restores the default: numba's setting of the calling
        thread, every core unless changed with ``numba.set_num_threads``.

    Notes
    -----
    Process-wide, like ``cv2.setNumThreads``: it holds for calls from every
    Python thread. Results are identical for every thread count. Matching
    from several Python threads at once (one image pair each) works; then
    ``set_num_threads(1)`` avoids running more threads than cores.

    Examples
    --------
    >>> import episeg_cv
    >>> episeg_cv.set_num_threads(1)
    >>> episeg_cv.get_num_threads()
    1
    >>> episeg_cv.set_num_threads(None)   # back to every core
    """
    global _requested
    if n is None:
        _requested = None
        return
    if isinstance(n, bool) or not hasattr(n, "__index__"):
        raise TypeError(f"n must be an int >= 1 or None, got {type(n).__name__}")
    n = operator.index(n)
    if n < 1:
        raise ValueError(f"n must be an int >= 1 or None, got {n}")
    _requested = min(n, numba.config.NUMBA_NUM_THREADS)


def get_num_threads() -> int:
    """The number of threads a call made now, from this Python thread, would use (>= 1).

    Examples
    --------
    >>> import episeg_cv
    >>> episeg_cv.get_num_threads() >= 1
    True
    """
    n = _numba_threads() if _requested is None else _requested
    limit = getattr(_this_thread, "limit", None)
    return n if limit is None else min(n, limit)


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity), at most numba's thread count: the default
    number of workers of a collection (:func:`episeg_cv.colmap.match_model`) and of compiling processes
    (:func:`episeg_cv.kernel_cache.compile_kernels`).

    Examples
    --------
    >>> available_cores() >= 1
    True
    """
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        n = os.cpu_count() or 1
    return max(1, min(n, numba.config.NUMBA_NUM_THREADS))


def limit_this_thread(n: int | None) -> None:
    """Cap the kernels' threads for calls made from *this* Python thread at ``n`` (None: no cap).

    For a pool of Python threads that each match their own pairs (the COLMAP runner's
    ``workers=N``): with ``limit_this_thread(1)`` as the pool's initializer, the pairs are spread
    over the cores and no pair forks threads of its own, while the rest of the program keeps
    :func:`set_num_threads`. Results do not change.

    Examples
    --------
    >>> import threading, episeg_cv
    >>> from episeg_cv.threads import limit_this_thread
    >>> seen = []
    >>> def worker():
    ...     limit_this_thread(1)
    ...     seen.append(episeg_cv.get_num_threads())
    >>> t = threading.Thread(target=worker); t.start(); t.join()
    >>> seen
    [1]
    """
    if n is not None:
        if isinstance(n, bool) or not hasattr(n, "__index__"):
            raise TypeError(f"n must be an int >= 1 or None, got {type(n).__name__}")
        n = operator.index(n)
        if n < 1:
            raise ValueError(f"n must be an int >= 1 or None, got {n}")
    _this_thread.limit = n


@contextlib.contextmanager
def limited(n: int | None):
    """A context that caps this Python thread's kernels at ``n`` threads (:func:`limit_this_thread`) and
    puts back the cap it had before, when it closes.

    Examples
    --------
    >>> import episeg_cv
    >>> with limited(1):
    ...     episeg_cv.get_num_threads()
    1
    """
    before = getattr(_this_thread, "limit", None)
    limit_this_thread(n)
    try:
        yield
    finally:
        _this_thread.limit = before


def use_parallel(items: int) -> bool:
    """Whether a kernel over ``items`` items should run its parallel variant now."""
    return items >= MIN_PARALLEL_ITEMS and get_num_threads() > 1


def call_parallel(kernel, *args):
    """``kernel(*args)`` with numba's thread count of the calling Python thread set to
    :func:`get_num_threads` (and restored after).

    Under numba's ``workqueue`` threading layer (used when neither TBB nor OpenMP is available),
    two parallel launches at once from two Python threads abort the process; there the launches are
    serialised by a lock. The ``omp`` and ``tbb`` layers take concurrent launches.
    """
    n = get_num_threads()
    before = _numba_threads()
    with (_launch_lock if _serialise_launches() else contextlib.nullcontext()):
        if before == n:
            return _launch(kernel, args)
        numba.set_num_threads(n)
        try:
            return _launch(kernel, args)
        finally:
            numba.set_num_threads(before)


def _launch(kernel, args):
    """``kernel(*args)``; an interrupt that lands while a compiled kernel runs comes out of numba wrapped
    in a ``SystemError`` (:func:`episeg_cv.interrupts.interrupt_in`): raise the interrupt itself, so that
    callers stop as they do for Ctrl-C."""
    try:
        return kernel(*args)
    except SystemError as exc:
        interrupt = interrupt_in(exc)
        if interrupt is None:
            raise
        raise interrupt from None


def _serialise_launches() -> bool:
    global _layer
    if _layer is None:
        try:
            _layer = numba.threading_layer()
        except ValueError:  # no parallel launch yet: the layer is not chosen
            return True
    return _layer == "workqueue"


def blocks() -> int:
    """Work blocks of a parallel kernel: a few per thread, so that uneven blocks even out."""
    return BLOCKS_PER_THREAD * get_num_threads()


def run(serial, parallel, items: int, *args):
    """``parallel(*args, blocks())`` through :func:`call_parallel` when :func:`use_parallel` says so, else
    ``serial(*args)`` (one thread, or fewer than :data:`MIN_PARALLEL_ITEMS` items). By convention the
    parallel twin of a kernel takes the number of work blocks as its last argument."""
    return call_parallel(parallel, *args, blocks()) if use_parallel(items) else _launch(serial, args)


class _NoLimit:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def blas_limit(n: int | None = None):
    """A context that limits BLAS to ``n`` threads (default :func:`get_num_threads`) while it is open (a
    no-op when BLAS already uses no more). BLAS libraries keep one process-wide setting, so the limit
    also holds for BLAS calls made by other Python threads meanwhile."""
    global _blas
    if _blas is None:
        with _blas_lock:
            if _blas is None:
                import scipy.linalg.cython_blas  # noqa: F401 (numba's np.dot calls this BLAS: load it to see it)
                from threadpoolctl import ThreadpoolController
                _blas = ThreadpoolController().select(user_api="blas")
    n = get_num_threads() if n is None else n
    if not _blas.lib_controllers or all(c.num_threads <= n for c in _blas.lib_controllers):
        return _NoLimit()
    return _blas.limit(limits=n)


class Scratch(threading.local):
    """Work buffers kept from one call to the next, one set per Python thread.

    A large fresh array costs page faults on first touch (at 50k keypoints, gathering the
    descriptors into a fresh array took three times as long as into a reused one). Only for arrays
    that do not outlive the call that asked for them: the next call overwrites them. Each buffer
    keeps the size of the largest request so far.
    """

    def __init__(self):
        self.buffers = {}

    def get(self, name: str, shape: tuple, dtype) -> np.ndarray:
        """An uninitialised C-contiguous ``shape`` array of ``dtype``, in the buffer ``name``."""
        dtype = np.dtype(dtype)
        need = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        buf = self.buffers.get(name)
        if buf is None or buf.nbytes < need:
            buf = self.buffers[name] = np.empty(max(need, 64), dtype=np.uint8)
        return buf[:need].view(dtype).reshape(shape)
