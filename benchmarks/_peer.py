"""The segment-tree peer of ``benchmarks/speed.py``: "Pixel-Accurate Epipolar Guided Matching" (3DV 2026).

Its authors' public C++ code, built as the pybind11 module ``guided_desc_match``, is *not* part of this
repository and is never built by it. The benchmark imports it from the folder named by the environment
variable ``EPISEG_PEER_PATH`` (the folder holding ``guided_desc_match*.so``); when that fails,
:func:`why_unavailable` says why and :data:`RECIPE` says where it comes from (also in docs/benchmarks.md).

What it offers, in our formats:

- :func:`candidate_lists`: the peer's candidates (a list of train indices per query) from its segment tree
  (``"tree"``, the paper's method) or its angular hash (``"hash"``), with the time its C++ reports;
- :func:`to_csr`, :func:`knn2`: the lists as CSR arrays and a compiled (numba) nearest + second nearest over
  them (float32 squared L2, ties by the smaller index; on threads with ``parallel``);
- :func:`ratio_test`: Lowe's ratio on (nearest, second), a query needing two;
- :func:`match`: the whole peer pipeline of the race, with the time of each stage.

Conventions: pixel centres at integers (``cv2.KeyPoint.pt``), as ours; ``F`` maps image-1 points to lines of
image 2 (``x2^T F x1 = 0``), divided by its largest entry before the float32 cast. ``tol`` is a pixel
distance to the epipolar line for both of its methods (the tree's radius is that of the disk around each
keypoint of image 2 that the line must cut: the same test).
"""

from __future__ import annotations

import glob
import importlib.util
import itertools
import os
import time

import numba as nb
import numpy as np

ENV = "EPISEG_PEER_PATH"

RECIPE = """\
The segment-tree peer is not part of this repository, which neither holds nor builds its code.
  source: github.com/LexaNagiBator228/Pixel-Accurate-Epipolar-Guided-Matching, commit b3c05a9
          (the tree, the angular hash and the brute force), built with its own build script for this
          Python, without its -ffast-math flags (IEEE arithmetic, as ours; with them its tree lost candidates),
          against pybind11 >= 2.12 (pip: Debian 12's 2.10 predates NumPy 2 and its module crashes) and Eigen 3.
  Then set EPISEG_PEER_PATH to the folder of its built epipolar_matching package.
Its OpenMP threads are limited with threadpoolctl."""

_module = None
_why = None


def load(path: str | None = None):
    """The peer's module, or None (then :func:`why_unavailable` says why)."""
    global _module, _why
    if _module is not None:
        return _module
    path = path or os.environ.get(ENV)
    if not path:
        _why = f"the environment variable {ENV} is not set"
        return None
    files = sorted(glob.glob(os.path.join(path, "guided_desc_match*.so")) + glob.glob(os.path.join(path, "guided_desc_match*.pyd")))
    if not files:
        _why = f"no guided_desc_match*.so in {path} ({ENV})"
        return None
    try:
        spec = importlib.util.spec_from_file_location("guided_desc_match", files[0])
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    except Exception as e:  # noqa: BLE001 - any import failure means "not available here"
        _why = f"importing {files[0]} failed: {e!r}"
        return None
    _module = mod
    return mod


def why_unavailable() -> str | None:
    return None if load() is not None else _why


def openmp_limit(n: int):
    """A threadpoolctl context limiting OpenMP pools (the peer's libgomp, and numba's omp layer) to ``n``."""
    from threadpoolctl import threadpool_limits
    return threadpool_limits(limits=int(n), user_api="openmp")


def scaled_F(F) -> np.ndarray:
    F = np.asarray(F, dtype=np.float64)
    return np.ascontiguousarray(F / np.abs(F).max(), dtype=np.float32)


def candidate_lists(points1, points2, F, tol: float, method: str = "tree", bins: int = 45):
    """``(list of lists of train indices per query, milliseconds inside its C++)``."""
    mod = load()
    if mod is None:
        raise RuntimeError(f"segment-tree peer unavailable: {_why}")
    p1 = np.ascontiguousarray(points1, dtype=np.float32).reshape(-1, 2)
    p2 = np.ascontiguousarray(points2, dtype=np.float32).reshape(-1, 2)
    if method == "tree":
        return mod.epipolar_wedge_filter_with_segment_tree(p1, p2, scaled_F(F), float(tol))
    if method == "hash":
        return mod.epipolar_hash_filter_cpp(p1, p2, scaled_F(F), int(bins), float(tol), False, True, True)
    raise ValueError(f"unknown method {method!r}")


def to_csr(lists) -> tuple[np.ndarray, np.ndarray]:
    """List of lists -> ``(offsets (N + 1,), indices (K,))`` int64, row order kept."""
    lengths = np.fromiter(map(len, lists), dtype=np.int64, count=len(lists))
    offsets = np.zeros(len(lists) + 1, dtype=np.int64)
    np.cumsum(lengths, out=offsets[1:])
    indices = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=int(offsets[-1]))
    return offsets, indices


_FAST = {"reassoc", "contract", "nsz"}  # as episeg_cv's kernels: the scores rank


@nb.njit(cache=True, fastmath=_FAST)  # a plain call, never inline="always": numba's IR inlining drops the
def l2sqr(A, q, B, t):                # fast-math flags and the 128-term sum becomes a serial chain (7x slower)
    s = np.float32(0.0)
    for f in range(A.shape[1]):
        x = A[q, f] - B[t, f]
        s += x * x
    return s


@nb.njit(cache=True)
def _knn2_row(A, B, q, offsets, indices, idx, sc):
    b1, b2 = np.float32(np.inf), np.float32(np.inf)
    j1, j2 = -1, -1
    for p in range(offsets[q], offsets[q + 1]):
        t = indices[p]
        s = l2sqr(A, q, B, t)
        if s < b1 or (s == b1 and t < j1):
            if t != j1:  # a keypoint listed twice is not its own second
                b2, j2 = b1, j1
            b1, j1 = s, t
        elif t != j1 and (s < b2 or (s == b2 and t < j2)):
            b2, j2 = s, t
    idx[q, 0], idx[q, 1] = j1, j2
    sc[q, 0], sc[q, 1] = b1, b2


@nb.njit(cache=True, nogil=True)
def _knn2_serial(A, B, offsets, indices, idx, sc):
    for q in range(offsets.shape[0] - 1):
        _knn2_row(A, B, q, offsets, indices, idx, sc)


@nb.njit(cache=True, nogil=True, parallel=True)
def _knn2_parallel(A, B, offsets, indices, idx, sc):
    for q in nb.prange(offsets.shape[0] - 1):
        _knn2_row(A, B, q, offsets, indices, idx, sc)


def knn2(d1, d2, offsets, indices, parallel: bool = False):
    """``(idx (N1, 2) int64, squared scores (N1, 2) float32)``: nearest and second of each query; -1 / inf."""
    A = np.ascontiguousarray(d1, dtype=np.float32)
    B = np.ascontiguousarray(d2, dtype=np.float32)
    n1 = len(offsets) - 1
    idx = np.empty((n1, 2), dtype=np.int64)
    sc = np.empty((n1, 2), dtype=np.float32)
    (_knn2_parallel if parallel else _knn2_serial)(A, B, offsets, indices, idx, sc)
    return idx, sc


def ratio_test(idx, sc, ratio: float):
    """Lowe's ratio on squared scores (a query needs two neighbours): ``(pairs (K, 2) intp, distances (K,))``."""
    keep = (idx[:, 1] >= 0) & (sc[:, 0] < np.float32(ratio * ratio) * sc[:, 1])
    q = np.flatnonzero(keep)
    return np.column_stack([q, idx[q, 0]]).astype(np.intp), np.sqrt(sc[q, 0])


def match(d1, d2, points1, points2, F, tol: float, ratio: float, method: str = "tree", parallel: bool = False,
          timings: dict | None = None):
    """Peer candidates -> CSR -> compiled nearest two -> ratio: ``(pairs, distances)``. ``timings`` (a dict)
    receives seconds per stage (``peer`` the call with its Python lists, ``peer_cpp`` its own clock, ``csr``,
    ``knn``, ``ratio``) and ``candidates``."""
    t0 = time.perf_counter()
    lists, ms = candidate_lists(points1, points2, F, tol, method)
    t1 = time.perf_counter()
    offsets, indices = to_csr(lists)
    t2 = time.perf_counter()
    idx, sc = knn2(d1, d2, offsets, indices, parallel)
    t3 = time.perf_counter()
    out = ratio_test(idx, sc, ratio)
    if timings is not None:
        timings.update(peer=t1 - t0, peer_cpp=ms / 1e3, csr=t2 - t1, knn=t3 - t2, ratio=time.perf_counter() - t3,
                       candidates=int(len(indices)))
    return out
