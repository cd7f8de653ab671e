"""Run jobs in this process, in a pool of threads, or on a Dask cluster (it knows nothing of COLMAP).

- ``workers=N``: N cores of this process (default: every core it may run on,
  :func:`available_cores`). With N > 1, a pool of N threads: the matching
  kernels are compiled with ``nogil`` and OpenCV releases the GIL while it
  detects, so the threads run at the same time; they share the loaded kernels
  and the features in memory, and end with the process. Each pool thread's
  kernels run on one thread (:func:`episeg_cv.threads.limit_this_thread`): the
  cores are shared out by items. Items the caller marks ``inline`` run in the
  calling thread instead, their kernels on the N cores (many tiny items in one
  parallel call beat a pool, whose threads hand the GIL over every few
  milliseconds). With N = 1 everything runs in the calling thread on one core.
- ``scheduler="local:N"``: a new ``distributed.LocalCluster`` of N worker
  processes (one thread each). A worker plugin (:class:`._dask.WarmWorker`, :mod:`.worker`) prepares
  every worker once, when it starts: one thread for OpenCV and BLAS, the
  compiled kernels loaded, and a watchdog that ends the worker when this
  process is gone (killed, say), so no worker outlives it.
- ``scheduler=ADDRESS``: a running cluster (``dask scheduler`` and
  ``dask worker ADDRESS`` on any machines); the same plugin warms its workers,
  without the watchdog (they serve other clients too).

In every worker, the features of the last images used stay in memory
(:meth:`FeatureStore.load`), so the pairs of a task, which share an image,
read it once.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import os

from ..interrupts import interrupts_deferred
from ..threads import available_cores, limit_this_thread, limited
from .worker import single_thread

__all__ = ["Runner", "CONNECT_TIMEOUT", "available_cores"]

#: Seconds to wait for a Dask scheduler before giving up.
CONNECT_TIMEOUT = 10.0
#: Dask tasks per worker (:meth:`Runner.chunk`): enough to even out uneven tasks, few enough to cost little.
TASKS_PER_WORKER = 4
#: Pairs per task in this process, and per task of a pool of threads. A task's small pairs are one
#: compiled call (:func:`~.job.match_pairs`), whose Python is per task: on dinoSparseRing (120 pairs of
#: about 250 keypoints) 2 threads took 0.054 s with 8 pairs a task, 0.049 s with 16 and 0.045 s with 32;
#: on the 24-view room (276 pairs of about 4500 keypoints) 8, 16 and 32 gave the same pairs/s (280-290).
PROCESS_CHUNK, THREAD_CHUNK = 64, 32
#: Seconds of one wait for the pool's next result: how long an interrupt may wait to be delivered.
WAIT_SLICE = 0.1
#: Bounds on the pairs of one Dask task.
DASK_CHUNK_MIN, DASK_CHUNK_MAX = 8, 64

def _run_in_worker(fn, item):
    single_thread()
    return fn(item)


class Runner:
    """Run ``fn`` over items with at most ``window`` in flight; yields results as they finish.

    ``workers``: the cores of this process to use (None: :func:`available_cores`); with a
    ``scheduler``, the cores of this process for the caller's own work (``cores``).
    :meth:`chunk` is the number of pairs the caller should put in one task for this runner.
    :meth:`limits` caps the kernels of the calling thread at ``cores`` while it is open.
    """

    def __init__(self, workers: int | None = None, scheduler: str | None = None):
        self._pool = self._client = self._cluster = None
        #: The Dask scheduler's address (a local cluster's too), for other runs on the same workers; None without Dask.
        self.address = None
        self.cores = available_cores() if workers is None else int(workers)
        self._tornado_level = None
        if scheduler is not None:
            try:
                import distributed

                from ._dask import WarmWorker
            except ImportError as e:
                raise ImportError('scheduler needs Dask: pip install "episeg_cv[dask]"') from e
            if scheduler.startswith("local:"):
                n = int(scheduler[6:]) if scheduler[6:].isdigit() else 0
                if n < 1:
                    raise ValueError(f"scheduler must be a Dask address or local:N with N a positive integer, "
                                     f"got {scheduler!r}")
                # silence_logs: the workers' own warnings (a task cancelled by an interrupt, say) are noise.
                # The workers' statistical profiler (a stack sample every 10 ms) off: it cost ~10 % of the
                # matching time on 24 views (it takes the GIL from the task's Python between kernels).
                import dask

                with dask.config.set({"distributed.worker.profile.enabled": False}):
                    self._cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                                             host="127.0.0.1", dashboard_address="127.0.0.1:0",
                                                             silence_logs=logging.ERROR)
                self._client = distributed.Client(self._cluster)
                self._client.register_plugin(WarmWorker(os.getpid()))  # with the watchdog
                self.address = self._cluster.scheduler_address
                self.describe = f"a local Dask cluster of {n} workers"
            else:
                try:
                    self._client = distributed.Client(scheduler, timeout=f"{CONNECT_TIMEOUT}s")
                except (OSError, TimeoutError) as e:
                    raise ConnectionError(f"cannot reach the Dask scheduler at {scheduler!r}: {e}") from e
                # kept when there: a local cluster's (with its watchdog) that serves refine_poses' rounds (a
                # lambda travels by value: the scheduler's machine need not have episeg_cv)
                name = WarmWorker.name
                if not self._client.run_on_scheduler(lambda dask_scheduler: name in dask_scheduler.worker_plugins):
                    self._client.register_plugin(WarmWorker(None))
                self.describe = f"the Dask cluster at {scheduler}"
                self.address = scheduler
            # An interrupt inside one of Dask's blocking calls makes its cancel callback fail on the event
            # loop (distributed's sync: "cannot access free variable 'future'"), which tornado logs with a
            # traceback. The interrupt itself is reported, so that log is noise while Dask runs (until close).
            tornado_log = logging.getLogger("tornado.application")
            self._tornado_level = tornado_log.level
            tornado_log.setLevel(logging.CRITICAL)
            self._workers = max(1, len(self._client.scheduler_info().get("workers", {})))
            self.window = 4 * self._workers
        elif self.cores > 1:
            self.describe = f"{self.cores} threads"
            self.window = 4 * self.cores
        else:
            self.describe = "this process, one core"
            self.window = 1
        if self.cores > 1:
            # one kernel thread per worker: the pairs are spread over the cores, not each pair's queries
            # (on 24 views, 2 workers ran at 0.94x of one when every pair also forked kernel threads). With
            # Dask, for :meth:`imap_here` only (its threads start on first use).
            self._pool = cf.ThreadPoolExecutor(self.cores, thread_name_prefix="episeg-worker",
                                               initializer=limit_this_thread, initargs=(1,))

    def limits(self):
        """A context capping the compiled kernels called from this thread at :attr:`cores` threads."""
        return limited(self.cores)

    def chunk(self, n_items: int, inline: bool = False) -> int:
        """Items per task for ``n_items`` items.

        In this process (one core, or ``inline``): :data:`PROCESS_CHUNK` (a task's small pairs are one
        compiled call on every core, :func:`~.job.match_pairs`). Threads: :data:`THREAD_CHUNK`. Dask: about
        :data:`TASKS_PER_WORKER` tasks per worker, within ``[DASK_CHUNK_MIN, DASK_CHUNK_MAX]``:
        each task costs the scheduler and the driver's event loop a few milliseconds of Python, which
        took CPU from the workers (on 276 pairs and 2 workers, 8 pairs a task ran at 0.9x of 24-70).
        """
        if self._client is not None:
            per = -(-n_items // (TASKS_PER_WORKER * self._workers))
            return int(min(max(per, DASK_CHUNK_MIN), DASK_CHUNK_MAX))
        return THREAD_CHUNK if self._pool is not None and not inline else PROCESS_CHUNK

    def spread(self, n_items: int) -> int:
        """Items per task that give each worker about one task (for a few items that each cost about the
        same: a task per item would pay a task's latency per item)."""
        workers = self._workers if self._client is not None else self.cores
        return max(1, -(-n_items // workers))

    def imap(self, fn, items, inline: bool = False):
        """``fn(item)`` for each item, yielded as they finish. ``inline``: in the calling thread (whose
        kernels the caller caps at :attr:`cores` with :meth:`limits`), unless a Dask cluster runs the items."""
        items = iter(items)
        if self._client is None and (self._pool is None or inline):
            yield from map(fn, items)
            return
        if self._client is not None:
            import distributed

            submit = lambda it: self._client.submit(_run_in_worker, fn, it, pure=False)  # noqa: E731
            pending = [submit(it) for _, it in zip(range(self.window), items)]
            done = distributed.as_completed(pending)
            for fut in done:
                yield fut.result()
                nxt = next(items, None)
                if nxt is not None:
                    done.add(submit(nxt))
            return
        yield from self._threads(fn, items)

    def _threads(self, fn, items):
        """``fn(item)`` for each item on the pool of threads, at most :attr:`window` in flight.

        The waits hold Ctrl-C and SIGTERM (:func:`~episeg_cv.interrupts.interrupts_deferred`) and last at
        most :data:`WAIT_SLICE` seconds, so an interrupt lands between them: raised inside ``cf.wait``, it
        could leave a pending future's lock taken (``cf.wait`` takes every future's lock in turn), and the
        worker that then starts that future waited for it for ever, and so did the pool's shutdown (a
        SIGTERM test hung in a clean-clone CI run).
        """
        pending = {self._pool.submit(fn, it) for _, it in zip(range(self.window), items)}
        try:
            while pending:
                with interrupts_deferred():
                    finished, pending = cf.wait(pending, timeout=WAIT_SLICE, return_when=cf.FIRST_COMPLETED)
                for fut in finished:  # (a finished future's lock no worker takes again)
                    yield fut.result()
                    nxt = next(items, None)
                    if nxt is not None:
                        pending.add(self._pool.submit(fn, nxt))
        finally:
            with interrupts_deferred():
                for fut in pending:
                    fut.cancel()

    def imap_here(self, fn, items):
        """``fn(item)`` for each item in this process: on a pool of :attr:`cores` threads when ``cores > 1``
        (with Dask too), else in the calling thread. A Dask cluster is not used: for a few short items (the
        band's sample pairs) a task's latency and a worker's first reads of the features cost more than the
        items (24 views, ``local:2``: matching 0.99 -> 0.93 s, median of 4); and the driver's cores are
        idle meanwhile (24 views, ``local:2``: the band took 0.11 s in the calling thread, 0.07 s on the
        driver's two threads, as with ``workers=2``; scratch, 4 runs each)."""
        return self._threads(fn, iter(items)) if self._pool is not None else map(fn, items)

    def close(self):
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        quiet = logging.getLogger("distributed")
        level = quiet.level
        quiet.setLevel(logging.ERROR)  # closing after an interrupt cancels tasks: warnings that say nothing new
        try:
            if self._client is not None:
                self._client.close()
            if self._cluster is not None:
                self._cluster.close()
        finally:
            quiet.setLevel(level)
            if self._tornado_level is not None:
                logging.getLogger("tornado.application").setLevel(self._tornado_level)
