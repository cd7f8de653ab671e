"""One large pair of a collection in one compiled call: :func:`episeg_cv.colmap.job.match_pair` on one thread.

A pool of Python threads matches a collection's pairs, one pair per thread (``episeg colmap --workers
N``). The kernels release the GIL, but the Python between them holds it: on a 24-view room (about 4500
keypoints an image) 19-24 % of a pair's CPU time (about 0.9 of 4.4 ms) was Python between the kernels
(``benchmarks/_gil.py``), so N threads could not run the pairs more than about 5x faster than one,
whatever N. :func:`match_pair` is the whole pair in one ``nogil`` call on the serial kernels: the
queries' segments, the :class:`~episeg_cv.matching.candidates.CandidateIndex` build (query frames,
pencil angles and buckets, keypoint intervals, slices), the scan (the two best candidates of each query,
the best query of each keypoint), the reverse index and scan of ``cross_check``, the mutual flags, the
padding of the pairs the rule keeps (:func:`._small_kernels.nearest_ratios`), the ratios, the rule, and
the reverse test with view 2's depth range (:func:`._small_kernels.reverse_keep`).

It calls the same compiled functions in the same order as the Python path
(:func:`~episeg_cv.matching.guided.nearest`, :func:`~episeg_cv.matching.filtering.keep_mask`), and
the Python arithmetic of the index (the pencil basis, the bucket edges, the key span) is written
out in the same order, so the pairs, their order and their ratios are the same bits
(``tests/colmap/test_pair_kernel.py``). One difference is not in the results: queries with the same
pencil angle (SIFT's keypoints of several orientations at one place) may come in another order within
their bucket, as numpy's ``argsort`` is not stable and this one is. The scan's orders are total, so
that order does not change its results; on the 24-view room every query also had the same slice
(the same bucket directions and keys) in all 276 pairs.

This call takes 95-96 % of a pair's CPU time (the kernels took 76-81 % when Python called them one
by one), so the GIL no longer holds a pool of N threads back before about 20x.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .. import _geometry_kernels as _gk
from . import _index_kernels as _ik
from . import _kernels
from . import _small_kernels as _sk
from ._kernels import NORM_CODES

__all__ = ["match_pair", "NORM_CODES"]


@nb.njit(cache=True, nogil=True)
def _rect(w, h, margin):
    """``geometry._rect``: the image ``(w, h)`` grown by ``margin``, as ``(xmin, xmax, ymin, ymax)``."""
    return np.array([-0.5 - margin, w - 0.5 + margin, -0.5 - margin, h - 0.5 + margin])


@nb.njit(cache=True, nogil=True)
def _cross(a, b):
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


@nb.njit(cache=True, nogil=True)
def _norm3(a):
    """``sqrt(a @ a)`` of a 3-vector, summed in numpy's order."""
    return np.sqrt((a[0] * a[0] + a[1] * a[1]) + a[2] * a[2])


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _pencil(b, w, h):
    """``CandidateIndex._pencil``: ``(c0, c1, s, e, u, v, found)``, the image centre and scale and the
    orthonormal pencil basis; ``found`` False for ``t = 0`` (then ``e, u, v`` are not used)."""
    c0, c1 = (w - 1) / 2.0, (h - 1) / 2.0
    s = np.hypot(w, h)
    e = np.array([(b[0] - c0 * b[2]) / s, (b[1] - c1 * b[2]) / s, b[2]])
    ne = _norm3(e)
    if ne == 0:
        return c0, c1, s, e, e, e, False
    e = e / ne
    axis = np.zeros(3)
    axis[np.argmin(np.abs(e))] = 1.0
    u = _cross(e, axis)
    u = u / _norm3(u)
    return c0, c1, s, e, u, _cross(e, u), True


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _index(x1, x2, H, b, zmin, zmax, w2, h2, eps, tol, is_line, bucket_size):
    """``CandidateIndex.build`` on one thread: ``(q_sorted, q_start, q_stop, t_sorted, geo, y_sorted)``, the
    arrays that :func:`._kernels.knn_scan` takes, for the queries ``x1`` against the keypoints ``x2``
    (``H``, ``b``: the geometry; ``zmin`` / ``zmax`` ``(1,)``; image 2 of ``(w2, h2)`` pixels)."""
    n1, n2 = x1.shape[0], x2.shape[0]
    rect = _rect(w2, h2, tol)
    start, end, line = np.empty((n1, 2)), np.empty((n1, 2)), np.empty((n1, 3))
    p_inf, a, valid = np.empty((n1, 2)), np.empty((n1, 3)), np.empty(n1, dtype=np.bool_)
    x = np.empty((n1, 2))  # a writable copy, as reverse_keep's and the Python API's points: numba compiles
    for q in range(n1):  # _segments once per read-only flag (the feature store's arrays are read-only)
        x[q, 0], x[q, 1] = x1[q, 0], x1[q, 1]
    _gk._segments(np.int64(0), n1, x, H, b, zmin, zmax, rect, eps, start, end, valid, line, p_inf, a)
    if is_line:
        P, Q = np.empty((n1, 2)), np.empty((n1, 2))
        _gk._line_clip(np.int64(0), n1, line, rect, P, Q)
        ok = np.empty(n1, dtype=np.bool_)
        for q in range(n1):
            ok[q] = np.isfinite(P[q, 0]) and np.isfinite(P[q, 1])
    else:
        P, Q, ok = start, end, valid
    for q in range(n1):  # undefined lines as zeros
        for c in range(3):
            if not np.isfinite(line[q, c]):
                line[q, c] = 0.0
    geo = np.empty((n1, 7))
    _ik._frames(np.int64(0), n1, P, Q, line, is_line, geo)
    q_ok = np.flatnonzero(ok)
    if n2 == 0 or q_ok.shape[0] == 0:
        z = np.zeros(0, dtype=np.int64)
        return z, z, z, z, geo, np.empty((0, 2))
    c0, c1, s, e, u, v, pencil = _pencil(b, w2, h2)
    if not pencil:  # pure rotation: every segment is a point; one bucket, rho along x
        q_sorted, qb = q_ok, np.zeros(q_ok.shape[0], dtype=np.int64)
        edges = np.array([0.0, _ik.PERIOD])
        lo, width = np.zeros(n2), np.full(n2, _ik.PERIOD)
    else:
        q_phi = _ik.query_phi(line, q_ok, s, c0, c1, u, v)
        order = np.argsort(q_phi, kind="mergesort")
        q_sorted, q_phi = q_ok[order], q_phi[order]
        n_ok = q_ok.shape[0]
        n_b = max(1, -(-n_ok // bucket_size))
        edges = np.empty(n_b + 1)
        edges[0], edges[n_b] = 0.0, _ik.PERIOD
        for k in range(1, n_b):
            edges[k] = q_phi[(k * n_ok) // n_b]
        qb = np.searchsorted(edges, q_phi, side="right") - 1
        for r in range(n_ok):
            qb[r] = min(max(qb[r], 0), n_b - 1)
        lo, width = _ik.pencil_intervals(e, u, v, c0, c1, s, tol, x2)
    n_b = edges.shape[0] - 1
    bstart = np.searchsorted(qb, np.arange(n_b + 1), side="left")
    span = 2.0 * (s + 2 * tol + 1.0)
    directions, klo, khi, hull = _ik.bucket_frames(q_sorted, bstart, line, P, Q, pencil, c0, c1, span, tol)
    t_sorted, key_t, tstart = _ik.spread_keys(lo, width, edges, x2, directions, c0, c1, span, hull)
    q_start, q_stop = _ik.slice_bounds(key_t, tstart, qb, klo, khi)
    keep = q_stop > q_start
    y_sorted = np.empty((t_sorted.shape[0], 2))
    _kernels.gather_rows(x2, t_sorted, y_sorted)
    return q_sorted[keep], q_start[keep], q_stop[keep], t_sorted, geo, y_sorted


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _scan(x1, x2, A, B, norm, H, b, zmin, zmax, w2, h2, eps, tol, is_line, bucket_size, k):
    """The ``k`` best candidates of each query and the best query of each keypoint: ``(idx, sc, col_i)``
    (``CandidateIndex.scan`` into fresh accumulators)."""
    q_sorted, q_start, q_stop, t_sorted, geo, y_sorted = _index(x1, x2, H, b, zmin, zmax, w2, h2, eps, tol,
                                                                is_line, bucket_size)
    n1, n2 = x1.shape[0], x2.shape[0]
    idx, sc = np.full((n1, k), -1, dtype=np.int64), np.full((n1, k), np.inf, dtype=np.float32)
    col_i, col_s = np.full(n2, -1, dtype=np.int64), np.full(n2, np.inf, dtype=np.float32)
    _kernels.knn_scan(q_sorted, q_start, q_stop, t_sorted, geo, y_sorted, is_line, tol, tol * tol * (1 + 1e-9) + 1e-12,
                      A, B, norm, idx, sc, np.zeros(n1, dtype=np.int64), col_s, col_i)
    return idx, sc, col_i


@nb.njit(cache=True, nogil=True, error_model="numpy")
def match_pair(x1, x2, A, B, norm, root, H, b, Hi, bi, z1, z2, size1, size2, eps, tol, is_line, bucket_size, pad_j,
               ratio, mutual_rule, cross_check, strict, chunk, round_to):
    """One pair matched both ways: ``(pairs (M, 2) int64, ratios (M,) float64, inlier (M,) bool)``.

    ``pairs`` are the rows ``(i, j)`` of ``x1 (N1, 2)`` / ``x2 (N2, 2)`` (float64 pixels) whose nearest
    candidate passes the rule, by query, as :func:`~episeg_cv.matching.guided.nearest` (with
    ``prefilter``) and the rule find them; ``inlier``: the pair passes the reverse test (image 2 to
    image 1, view 2's depth range), as :func:`~episeg_cv.matching.filtering.keep_mask` tests it.

    ``A`` / ``B``: the scoring rows (:class:`~.distances.Distances`), ``norm`` its kernel code, ``root``:
    squared L2 scores reported as L2. ``H, b`` / ``Hi, bi``: the infinite homography and homogeneous
    epipole of the geometry and of its inverse; ``z1`` / ``z2`` ``(2,)``: the two views' depth ranges;
    ``size1`` / ``size2`` ``(w, h)`` as floats; ``eps`` the cheirality tolerance; ``tol`` the band,
    ``is_line`` the line constraint (else the segment), ``bucket_size`` the index's. ``pad_j``: the
    sorted padding references (empty: none). The rule: ``ratio`` (a ratio of 1 or more keeps every
    pair unless ``strict``), ``mutual_rule``, ``cross_check`` (mutual through a reverse scan over the
    whole ray). ``chunk`` / ``round_to``: the padding's BLAS blocks (:data:`~.distances.PAD_CHUNK`,
    :data:`~.distances.PAD_ROUND`).
    """
    idx, sc, best = _scan(x1, x2, A, B, norm, H, b, z1[0:1], z1[1:2], size2[0], size2[1], eps, tol, is_line,
                          bucket_size, np.int64(2))  # (not literals: one compiled _scan for both calls)
    if cross_check:  # bounds on z1 are not bounds on z2: the reverse pass uses the whole half-line (0, inf)
        back, _, _ = _scan(x2, x1, B, A, norm, Hi, bi, np.zeros(1), np.full(1, np.inf), size1[0], size1[1], eps, tol,
                           is_line, bucket_size, np.int64(1))
        best = np.ascontiguousarray(back[:, 0])
    i, j, r, mutual = _sk.nearest_ratios(idx, sc, best, A, B, norm, root, pad_j, ratio, mutual_rule, True, chunk,
                                         round_to)
    ok = _sk.rule_passes(r, mutual, ratio, mutual_rule, strict)
    ki, kj = i[ok], j[ok]
    inlier = _sk.reverse_keep(x1, x2, ki, kj, Hi, bi, z2[0:1], z2[1:2], _rect(size1[0], size1[1], tol), eps, tol,
                              is_line)
    pairs = np.empty((ki.shape[0], 2), dtype=np.int64)
    for m in range(ki.shape[0]):  # (a loop: slice assignments compile numba's shape-error formatting, about 3 s)
        pairs[m, 0], pairs[m, 1] = ki[m], kj[m]
    return pairs, r[ok], inlier
