"""Compiled inner loops (numba): the work done once per candidate pair.

Guided matching spends its time on pairs ``(query, keypoint)``: testing
whether the keypoint lies within ``tol`` of the query's segment (or line),
and, if it does, scoring the two descriptors. In numpy that work has to be
padded into dense blocks, so a constraint that finds fewer candidates does not
get faster. Here it is one loop per query over a contiguous slice of the
keypoints sorted by :class:`~episeg_cv.candidates.CandidateIndex`, so the time
follows the number of candidates.

Every function takes plain arrays, so that the callers own all validation:

- ``q_sorted (S,)``, ``q_start (S,)``, ``q_stop (S,)``: query ``q_sorted[r]`` is
  compared with the keypoints ``t_sorted[q_start[r]:q_stop[r]]``;
- ``geo (N1, 7)`` float64: per query, the unit normal ``(n0, n1)`` and offset
  ``off`` of its segment's line, its unit direction ``(d0, d1)``, the position
  ``mid`` of its middle along that direction and its half-length ``half``;
- ``y (S, 2)`` float64: the keypoint pixels of image 2 in the order of
  ``t_sorted`` (``y[p]`` is keypoint ``t_sorted[p]``), so that a slice is read
  from contiguous memory; so are the descriptors ``B`` of :func:`knn_scan`.

A keypoint ``y`` is a candidate when its distance to the segment,
``hypot(across, max(along, 0))`` with ``across = n.y - off`` and
``along = |d.y - mid| - half``, is at most ``tol`` (line: ``|across| <= tol``).
The arithmetic is done in float64 without fast-math, in the order written.

Scores are the squared L2 distance (``"l2"``, ``"l2sqr"``), the L1 distance,
or the Hamming distance of packed bits (uint8 descriptors), in float32. They
rank candidates; the distances reported to users are recomputed as ``cv2``
computes them (:func:`episeg_cv.matching._exact`).
"""

from __future__ import annotations

import numba as nb
import numpy as np

#: Norm codes of the kernels.
L2SQR, L1, HAMMING = 0, 1, 2
NORM_CODES = {"l2": L2SQR, "l2sqr": L2SQR, "l1": L1, "hamming": HAMMING}

_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)
# Summation order may change (SIMD); the result is a score used for ranking only.
_SUM_FAST = {"reassoc", "contract", "nsz"}


@nb.njit(inline="always")
def _is_candidate(geo, q, y0, y1, is_line, tol, tol2):
    across = geo[q, 0] * y0 + geo[q, 1] * y1 - geo[q, 2]
    if is_line:
        return abs(across) <= tol
    along = abs(geo[q, 3] * y0 + geo[q, 4] * y1 - geo[q, 5]) - geo[q, 6]
    if along < 0.0:
        along = 0.0
    return across * across + along * along <= tol2


@nb.njit(cache=True, fastmath=_SUM_FAST)
def _l2sqr(A, q, B, t):
    s = np.float32(0.0)
    for f in range(A.shape[1]):
        x = np.float32(A[q, f]) - np.float32(B[t, f])
        s += x * x
    return s


@nb.njit(cache=True, fastmath=_SUM_FAST)
def _l1(A, q, B, t):
    s = np.float32(0.0)
    for f in range(A.shape[1]):
        s += abs(np.float32(A[q, f]) - np.float32(B[t, f]))
    return s


@nb.njit(cache=True)
def _hamming(A, q, B, t):
    s = 0
    for f in range(A.shape[1]):
        s += _POPCOUNT[np.uint8(A[q, f]) ^ np.uint8(B[t, f])]
    return np.float32(s)


# Inlined into each kernel, so that the norm is one predictable branch and each distance loop keeps
# its own (fast-math) compilation.
@nb.njit(inline="always")
def _score(A, q, B, t, norm):
    if norm == HAMMING:
        return _hamming(A, q, B, t)
    if norm == L1:
        return _l1(A, q, B, t)
    return _l2sqr(A, q, B, t)


@nb.njit(cache=True, nogil=True)
def knn_scan(q_sorted, q_start, q_stop, t_sorted, geo, y, is_line, tol, tol2, A, B, norm,
             idx, sc, counts, col_s, col_i):
    """The ``k`` best candidates of each query, the best query of each keypoint, and candidate counts.

    ``A (N1, D)`` are the query descriptors and ``B (S, D)`` those of the keypoints in slice order.

    Writes ``idx (N1, k)`` / ``sc (N1, k)`` (best first; ties by the smaller
    keypoint index; untouched where a query has fewer than ``k``),
    ``counts (N1,)``, and ``col_i (N2,)`` / ``col_s (N2,)``: the nearest query
    among those having the keypoint as a candidate (ties by the smaller query
    index). ``sc`` and ``col_s`` must start at inf, ``idx`` and ``col_i`` at -1.
    """
    k = idx.shape[1]
    for r in range(q_sorted.shape[0]):
        q = q_sorted[r]
        c = 0
        for p in range(q_start[r], q_stop[r]):
            if not _is_candidate(geo, q, y[p, 0], y[p, 1], is_line, tol, tol2):
                continue
            c += 1
            t = t_sorted[p]
            s = _score(A, q, B, p, norm)
            last = sc[q, k - 1]
            if s < last or (s == last and (idx[q, k - 1] < 0 or t < idx[q, k - 1])):
                m = k - 1
                while m > 0 and (sc[q, m - 1] > s or (sc[q, m - 1] == s and idx[q, m - 1] > t)):
                    sc[q, m] = sc[q, m - 1]
                    idx[q, m] = idx[q, m - 1]
                    m -= 1
                sc[q, m] = s
                idx[q, m] = t
            if s < col_s[t] or (s == col_s[t] and (col_i[t] < 0 or q < col_i[t])):
                col_s[t] = s
                col_i[t] = q
        counts[q] += c


@nb.njit(cache=True, nogil=True)
def candidate_pairs(q_sorted, q_start, q_stop, t_sorted, geo, y, is_line, tol, tol2):
    """Every candidate pair: ``(i, j)`` int64 arrays, in scan order (callers sort)."""
    total = 0
    for r in range(q_sorted.shape[0]):
        total += q_stop[r] - q_start[r]
    i = np.empty(total, dtype=np.int64)
    j = np.empty(total, dtype=np.int64)
    n = 0
    for r in range(q_sorted.shape[0]):
        q = q_sorted[r]
        for p in range(q_start[r], q_stop[r]):
            if _is_candidate(geo, q, y[p, 0], y[p, 1], is_line, tol, tol2):
                i[n] = q
                j[n] = t_sorted[p]
                n += 1
    return i[:n], j[:n]


@nb.njit(cache=True, nogil=True)
def paired_scores(A, B, i, j, norm):
    """``(K,)`` float32 scores of the pairs ``(i[k], j[k])``."""
    out = np.empty(i.shape[0], dtype=np.float32)
    for n in range(i.shape[0]):
        out[n] = _score(A, i[n], B, j[n], norm)
    return out


@nb.njit(cache=True, nogil=True)
def nearest_excluding(A, B, qi, tj, exclude, norm):
    """``(len(qi),)`` smallest score of query ``qi[r]`` over the keypoints ``tj``, leaving out ``exclude[r]``
    (inf when nothing is left)."""
    out = np.full(qi.shape[0], np.inf, dtype=np.float32)
    for r in range(qi.shape[0]):
        best = np.float32(np.inf)
        for c in range(tj.shape[0]):
            if tj[c] == exclude[r]:
                continue
            s = _score(A, qi[r], B, tj[c], norm)
            if s < best:
                best = s
        out[r] = best
    return out
