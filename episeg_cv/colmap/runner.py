"""Run jobs in this process, in local processes, or on a Dask cluster (it knows nothing of COLMAP)."""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing

import cv2

__all__ = ["Runner", "CONNECT_TIMEOUT"]

#: Seconds to wait for a Dask scheduler before giving up.
CONNECT_TIMEOUT = 10.0

_WORKER_LIMITED = False


def _single_thread():
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


def _run_in_worker(fn, item):
    _single_thread()
    return fn(item)


class Runner:
    """Run ``fn`` over items with at most ``window`` in flight; yields results as they finish.

    ``chunk`` is the number of pairs the caller should put in one task for this runner.
    """

    def __init__(self, workers: int = 1, scheduler: str | None = None):
        self._pool = self._client = self._cluster = None
        if scheduler is not None:
            try:
                import distributed
            except ImportError as e:
                raise ImportError('scheduler needs Dask: pip install "episeg_cv[dask]"') from e
            if scheduler.startswith("local:"):
                n = int(scheduler[6:]) if scheduler[6:].isdigit() else 0
                if n < 1:
                    raise ValueError(f"scheduler must be an address or local:N with N >= 1, got {scheduler!r}")
                self._cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                                         dashboard_address=None)
                self._client = distributed.Client(self._cluster)
                self.describe = f"a local Dask cluster of {n} workers"
            else:
                try:
                    self._client = distributed.Client(scheduler, timeout=f"{CONNECT_TIMEOUT}s")
                except (OSError, TimeoutError) as e:
                    raise ConnectionError(f"cannot reach the Dask scheduler at {scheduler!r}: {e}") from e
                self.describe = f"the Dask cluster at {scheduler}"
            self.window = 4 * max(1, len(self._client.scheduler_info().get("workers", {})) or 1)
            self.chunk = 8
        elif workers > 1:
            self._pool = cf.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                                initializer=_single_thread)
            self.describe = f"{workers} local processes"
            self.window = 4 * workers
            self.chunk = 4
        else:
            self.describe = "this process"
            self.window = self.chunk = 1

    def imap(self, fn, items):
        items = iter(items)
        if self._client is None and self._pool is None:
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
        pending = {self._pool.submit(fn, it) for _, it in zip(range(self.window), items)}
        while pending:
            finished, pending = cf.wait(pending, return_when=cf.FIRST_COMPLETED)
            for fut in finished:
                yield fut.result()
                nxt = next(items, None)
                if nxt is not None:
                    pending.add(self._pool.submit(fn, nxt))

    def close(self):
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        if self._client is not None:
            self._client.close()
        if self._cluster is not None:
            self._cluster.close()
