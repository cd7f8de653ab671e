"""Compiled loop of the per-query band scan (:mod:`.banded`): the exact band test, then the scores.

It walks the slices a :class:`~.candidates.CandidateIndex` lists (its public
``q_sorted``, ``q_start``, ``q_stop`` and ``t_sorted``), tests each keypoint
against the query's band (the half-width ``w(f)`` along the segment and
elliptical caps, :mod:`episeg_cv.uncertainty`; in float64, in the order
written) and, inside, scores the descriptors and merges the result into
the arrays it is given: the ``k`` best candidates of each query (ties: the
smaller keypoint index), the best query of each keypoint (ties: the smaller
query index) and the counts. The arrays accumulate across calls, so one call
per group of queries gives the global result.
"""

from __future__ import annotations

import numba as nb
import numpy as np

#: Norm codes (as :mod:`._kernels`).
L2SQR, L1, HAMMING = 0, 1, 2


@nb.njit(cache=True, inline="always")
def _popcount64(x):
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (x * np.uint64(0x0101010101010101)) >> np.uint64(56)


@nb.njit(cache=True, inline="always")
def _score(A, q, B, t, norm):
    if norm == HAMMING:
        h = 0
        for f in range(A.shape[1]):
            h += _popcount64(np.uint64(A[q, f]) ^ np.uint64(B[t, f]))
        return np.float32(h)
    s = np.float32(0.0)
    if norm == L1:
        for f in range(A.shape[1]):
            s += abs(np.float32(A[q, f]) - np.float32(B[t, f]))
        return s
    for f in range(A.shape[1]):
        x = np.float32(A[q, f]) - np.float32(B[t, f])
        s += x * x
    return s


@nb.njit(cache=True, inline="always")
def _inside(band, g, y0, y1):
    """``band[g] = (P0, P1, m0, m1, L, ws, we, es, ee, wc)``: is ``(y0, y1)`` in the band?"""
    r0 = y0 - band[g, 0]
    r1 = y1 - band[g, 1]
    u = r0 * band[g, 2] + r1 * band[g, 3]
    a = abs(r1 * band[g, 2] - r0 * band[g, 3])
    L = band[g, 4]
    ws, we = band[g, 5], band[g, 6]
    if u < 0.0:
        es = band[g, 7]
        return (a / ws) ** 2 + (u / es) ** 2 <= 1.0 + 1e-12 if ws > 0 and es > 0 else False
    if u > L:
        ee = band[g, 8]
        return (a / we) ** 2 + ((u - L) / ee) ** 2 <= 1.0 + 1e-12 if we > 0 and ee > 0 else False
    f = u / L if L > 0 else 0.0
    return a * a <= (1.0 - f) * (1.0 - f) * ws * ws + 2.0 * f * (1.0 - f) * band[g, 9] + f * f * we * we


@nb.njit(cache=True, nogil=True)
def band_scan(q_sorted, q_start, q_stop, t_sorted, queries, y, band, A, B, norm, idx, sc, counts, col_s, col_i):
    """Scan the slices of one index (module docstring).

    ``queries[q]`` is the global index of the index's query ``q``; ``y (N2, 2)``
    and ``B (N2, D)`` are the keypoints and their descriptors in their own
    order; ``band (N1, 10)`` the bands of the global queries. ``idx, sc (N1, k)``,
    ``counts (N1,)``, ``col_s, col_i (N2,)`` are updated in place (``sc``,
    ``col_s`` start at inf, ``idx``, ``col_i`` at -1).
    """
    k = idx.shape[1]
    for r in range(q_sorted.shape[0]):
        g = queries[q_sorted[r]]
        c = 0
        for p in range(q_start[r], q_stop[r]):
            t = t_sorted[p]
            if not _inside(band, g, y[t, 0], y[t, 1]):
                continue
            c += 1
            s = _score(A, g, B, t, norm)
            last = sc[g, k - 1]
            if s < last or (s == last and (idx[g, k - 1] < 0 or t < idx[g, k - 1])):
                m = k - 1
                while m > 0 and (sc[g, m - 1] > s or (sc[g, m - 1] == s and idx[g, m - 1] > t)):
                    sc[g, m] = sc[g, m - 1]
                    idx[g, m] = idx[g, m - 1]
                    m -= 1
                sc[g, m] = s
                idx[g, m] = t
            if s < col_s[t] or (s == col_s[t] and (col_i[t] < 0 or g < col_i[t])):
                col_s[t] = s
                col_i[t] = g
        counts[g] += c


@nb.njit(cache=True, nogil=True)
def band_pairs(q_sorted, q_start, q_stop, t_sorted, queries, y, band):
    """Every ``(global query, keypoint)`` pair inside its band, in scan order (callers sort)."""
    total = 0
    for r in range(q_sorted.shape[0]):
        total += q_stop[r] - q_start[r]
    i = np.empty(total, dtype=np.int64)
    j = np.empty(total, dtype=np.int64)
    n = 0
    for r in range(q_sorted.shape[0]):
        g = queries[q_sorted[r]]
        for p in range(q_start[r], q_stop[r]):
            t = t_sorted[p]
            if _inside(band, g, y[t, 0], y[t, 1]):
                i[n] = g
                j[n] = t
                n += 1
    return i[:n], j[:n]
