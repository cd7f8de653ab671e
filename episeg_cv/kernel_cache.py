"""The first run after installing compiles the kernels: a hook to say so before the wait.

The compiled kernels use ``numba.njit(cache=True)``: the first call of each compiles it and writes it
to numba's cache (``__pycache__`` beside the package, or ``NUMBA_CACHE_DIR``); later processes load it
from there. Compiling costs 23-29 s for a two-view command and about a minute for ``episeg colmap``,
on one core of this project's 2-core test machine, once (``benchmarks/results/first_run.md``); later
runs take 1.4-2.8 s in all. A program that wants to say so, as ``episeg`` does, wraps its work in
:func:`on_first_compile`.

Numba compiles one function at a time, on one core. :func:`compile_kernels` (``episeg compile``)
compiles every kernel the ``episeg`` commands use, ahead of their first run, in several processes at
once: each takes a share of the kernels listed in :data:`SIGNATURES` (their argument types, recorded
from the commands by ``python benchmarks/first_run.py --record``), the longest first, and writes them
to the same cache. The commands then load them. With one process it is the same work as the first
runs; with more it is bounded by the longest kernel (``benchmarks/results/first_run.md``).
"""

from __future__ import annotations

import contextlib
import importlib
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import numba
from numba.core import event

__all__ = ["on_first_compile", "compile_kernels", "deal", "SIGNATURES"]

#: The kernels the ``episeg`` commands compile, with their argument types and compile times (JSON),
#: recorded by ``python benchmarks/first_run.py --record``.
SIGNATURES = Path(__file__).with_name("kernel_signatures.json")


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


def compile_kernels(processes: int | None = None, functions=None, signatures=SIGNATURES) -> dict:
    """Compile the kernels of :data:`SIGNATURES` into numba's cache now, on ``processes`` processes at once.

    Each process takes a share of the kernels, the longest to compile first (by their recorded times,
    each to the process with the least work so far), compiles every recorded signature of them and writes
    it to numba's cache (``__pycache__`` beside the package, or ``NUMBA_CACHE_DIR``: the processes inherit
    the environment). Kernels the cache holds already are loaded, not compiled again. On a machine with
    one core the parallel twins of the kernels (``parallel=True``) are left out: nothing calls them there.

    Parameters
    ----------
    processes : int >= 1 or None, optional
        Processes to compile in. Default: the cores this process may run on.
    functions : sequence of str or None, optional
        Only these kernels, as ``"module:function"`` names of :data:`SIGNATURES`. Default: all.
    signatures : path, optional
        Another list of kernels in the format of :data:`SIGNATURES` (for tests).

    Returns
    -------
    dict
        ``seconds`` (wall time), ``processes`` (started), ``kernels`` and ``signatures`` (compiled or loaded),
        ``skipped`` (``"module:function"`` names that this version does not have, or whose recorded
        signature no longer compiles, with the reason: recompiled on first use as without this step).

    Raises
    ------
    TypeError
        ``processes`` not an int, ``functions`` not a sequence of str.
    ValueError
        ``processes < 1``; a name of ``functions`` not in :data:`SIGNATURES`.
    RuntimeError
        A compiling process failed (its error output is in the message).

    Examples
    --------
    ``compile_kernels()`` compiles every kernel, one process per core (``episeg compile``). With no
    kernel to compile, no process starts:

    >>> out = compile_kernels(functions=[])
    >>> out["processes"], out["kernels"], out["skipped"]
    (0, 0, [])
    """
    from .threads import available_cores

    if processes is not None and (isinstance(processes, bool) or not isinstance(processes, int)):
        raise TypeError(f"processes must be an int >= 1 or None, got {type(processes).__name__}")
    if processes is not None and processes < 1:
        raise ValueError(f"processes must be an int >= 1 or None, got {processes}")
    signatures = Path(signatures)
    listed = json.loads(signatures.read_text())["kernels"]
    if functions is None:
        names = list(listed)
    else:
        if isinstance(functions, str) or not all(isinstance(f, str) for f in functions):
            raise TypeError("functions must be a sequence of 'module:function' names")
        names = list(dict.fromkeys(functions))
        unknown = [f for f in names if f not in listed]
        if unknown:
            raise ValueError(f"functions: {unknown[0]!r} is not a kernel of {signatures.name}")
    if numba.config.NUMBA_NUM_THREADS == 1:  # one core: only the serial kernels run
        names = [f for f in names if not listed[f]["parallel"]]
    if processes is None:
        processes = available_cores()
    shares = deal({f: listed[f]["seconds"] for f in names}, processes)
    t0 = time.perf_counter()
    procs = [subprocess.Popen([sys.executable, "-m", __name__, str(signatures), *share], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for share in shares if share]
    out = {"processes": len(procs), "kernels": 0, "signatures": 0, "skipped": []}
    errors = []
    try:
        for proc in procs:
            stdout, stderr = proc.communicate()
            if proc.returncode != 0:
                errors.append(stderr.strip().splitlines()[-1] if stderr.strip() else f"exit code {proc.returncode}")
                continue
            done = json.loads(stdout.strip().splitlines()[-1])
            out["kernels"] += done["kernels"]
            out["signatures"] += done["signatures"]
            out["skipped"] += done["skipped"]
    finally:  # interrupted (Ctrl-C, SIGTERM through the CLI): no process outlives the call
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    if errors:
        raise RuntimeError(f"compiling the kernels failed in {len(errors)} of {len(procs)} processes: {errors[0]}")
    out["seconds"] = time.perf_counter() - t0
    return out


def deal(seconds: dict, processes: int) -> list:
    """``processes`` lists of the keys of ``seconds`` (kernel -> its compile time): the longest first, each to
    the list with the least time so far (longest processing time first, within 4/3 of the best split).

    >>> deal({"a": 5.0, "b": 3.0, "c": 2.0, "d": 1.0}, 2)
    [['a', 'd'], ['b', 'c']]
    """
    shares, load = [[] for _ in range(processes)], [0.0] * processes
    for f in sorted(seconds, key=lambda f: -seconds[f]):
        k = load.index(min(load))
        shares[k].append(f)
        load[k] += seconds[f]
    return shares


def _argument_type(text: str):
    """A numba type from its ``repr`` as :data:`SIGNATURES` records it (``Array(float64, 1, 'C', ...)``,
    ``int64``, ``Literal[bool](True)``)."""
    from numba.core import types

    if text.startswith("Literal[") and text.endswith(")"):
        return types.literal(eval(text[text.index("(") + 1:-1], {"__builtins__": {}}))
    return eval(text, {"__builtins__": {}}, vars(types))


def _compile_share(signatures, names) -> dict:
    """Compile the recorded signatures of the kernels ``names`` in this process (:func:`compile_kernels`)."""
    from numba.core.dispatcher import Dispatcher

    listed = json.loads(Path(signatures).read_text())["kernels"]
    out = {"kernels": 0, "signatures": 0, "skipped": []}
    for name in names:
        module, _, qualname = name.partition(":")
        try:
            kernel = getattr(importlib.import_module(module), qualname)
            types = [tuple(_argument_type(t) for t in sig) for sig in listed[name]["signatures"]]
        except (ImportError, AttributeError, SyntaxError, NameError, TypeError) as exc:
            out["skipped"].append(f"{name}: {type(exc).__name__}: {exc}")
            continue
        if not isinstance(kernel, Dispatcher):
            out["skipped"].append(f"{name}: not a compiled kernel")
            continue
        for sig in types:
            try:
                kernel.compile(sig)
            except Exception as exc:  # a recorded type that this version's kernel no longer takes
                out["skipped"].append(f"{name}{sig}: {type(exc).__name__}")
                continue
            out["signatures"] += 1
        out["kernels"] += 1
    return out


if __name__ == "__main__":  # one process of compile_kernels: the list, then its kernels' names
    print(json.dumps(_compile_share(sys.argv[1], sys.argv[2:])))
