"""The Dask side of :mod:`.runner` (imported only when a scheduler is used: it imports ``distributed``)."""

from __future__ import annotations

from distributed.diagnostics.plugin import WorkerPlugin

from .worker import single_thread, undo_malloc_trim, warm_up, watch_parent

__all__ = ["WarmWorker"]


class WarmWorker(WorkerPlugin):
    """Dask worker plugin: prepare a worker once, when it starts.

    glibc's own large-allocation thresholds back (:func:`.worker.undo_malloc_trim`), one thread for
    OpenCV and BLAS, the compiled matching kernels loaded
    (:func:`.worker.warm_up`), and, with ``driver_pid``, a watchdog that ends
    the worker when that process is gone (for the workers of a local cluster,
    so that none outlives a killed run). ``driver_pid=None``: no watchdog (the
    workers of a cluster started with ``dask worker`` serve other clients too).
    """

    name = "episeg-warm-worker"

    def __init__(self, driver_pid: int | None = None):
        self.driver_pid = driver_pid

    def setup(self, worker=None):
        undo_malloc_trim()
        single_thread()
        if self.driver_pid is not None:
            watch_parent(self.driver_pid)
        warm_up()
