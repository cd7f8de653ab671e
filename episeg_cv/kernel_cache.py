"""The first run after installing compiles the kernels: a hook to say so before the wait.

The compiled kernels use ``numba.njit(cache=True)``: the first call of each compiles it and writes it
to numba's cache (``__pycache__`` beside the package, or ``NUMBA_CACHE_DIR``); later processes load it
from there. Compiling costs 23-29 s for a two-view command and about a minute for ``episeg colmap``,
on one core of this project's 2-core test machine, once (``benchmarks/results/first_run.md``); later
runs take 1.4-2.8 s in all. A program that wants to say so, as ``episeg`` does, wraps its work in
:func:`on_first_compile`.
"""

from __future__ import annotations

import contextlib
import threading

from numba.core import event

__all__ = ["on_first_compile"]


class _FirstCompile(event.Listener):
    def __init__(self, callback, package: str):
        self.callback, self.package = callback, package
        self.lock, self.called = threading.Lock(), False

    def on_start(self, ev):
        func = getattr(ev.data.get("dispatcher"), "py_func", None)
        module = getattr(func, "__module__", None) or ""
        if func is None or not (module == self.package or module.startswith(self.package + ".")):
            return
        with self.lock:
            if self.called:
                return
            self.called = True
        self.callback(f"{module}.{func.__qualname__}")

    def on_end(self, ev):
        pass


@contextlib.contextmanager
def on_first_compile(callback, package: str = "episeg_cv"):
    """Call ``callback(name)`` once, when the first kernel of ``package`` starts compiling in the block.

    A kernel that numba's cache already holds is loaded, not compiled, and calls nothing; so the
    callback runs only on a first use (after installing, after a kernel's source changed, or with an
    empty ``NUMBA_CACHE_DIR``), on the thread that compiles, before the compilation.

    Parameters
    ----------
    callback : callable
        Called with the kernel's ``"module.function"`` name, at most once per block.
    package : str
        Only kernels of modules under this name count (default: this library's).

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv._finite_kernels import largest_magnitude
    >>> seen = []
    >>> with on_first_compile(seen.append):
    ...     _ = largest_magnitude(np.ones(3, np.float32))
    >>> seen in ([], ["episeg_cv._finite_kernels.magnitude_bits"])  # [] when it was cached already
    True
    """
    if not callable(callback):
        raise TypeError(f"callback must be callable, got {type(callback).__name__}")
    with event.install_listener("numba:compile", _FirstCompile(callback, package)):
        yield
