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
or the Hamming distance of packed bits, in float32. Binary descriptors come as
``uint64`` words (rows zero-padded to a multiple of 8 bytes; see
:func:`as_words`), counted with the CPU's population count. They
rank candidates; the distances reported to users are recomputed as ``cv2``
computes them (:func:`episeg_cv.matching._exact`).
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numba import types
from numba.extending import intrinsic

#: Norm codes of the kernels.
L2SQR, L1, HAMMING = 0, 1, 2
NORM_CODES = {"l2": L2SQR, "l2sqr": L2SQR, "l1": L1, "hamming": HAMMING}

# Summation order may change (SIMD); the result is a score used for ranking only.
_SUM_FAST = {"reassoc", "contract", "nsz"}


@nb.njit(cache=True)
def _is_candidate(n0, n1, off, d0, d1, mid, half, y0, y1, is_line, tol, tol2):
    """The exact test, in float64, in the order written (scalar arguments: no reference counting)."""
    across = n0 * y0 + n1 * y1 - off
    if is_line:
        return abs(across) <= tol
    along = abs(d0 * y0 + d1 * y1 - mid) - half
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


def as_words(d: np.ndarray) -> np.ndarray:
    """``(N, W)`` uint64 view of ``(N, D)`` uint8 packed bits, rows zero-padded to ``W = ceil(D / 8)`` words."""
    pad = -d.shape[1] % 8
    if pad:
        d = np.concatenate([d, np.zeros((d.shape[0], pad), dtype=np.uint8)], axis=1)
    return np.ascontiguousarray(d).view(np.uint64)


@intrinsic
def _popcount(typingctx, x):
    """Number of set bits of a uint64 (LLVM's ctpop: one instruction on current CPUs)."""
    if x != types.uint64:
        return None

    def codegen(context, builder, signature, args):
        return builder.ctpop(args[0])
    return types.uint64(types.uint64), codegen


@nb.njit(cache=True)
def _hamming(A, q, B, t):
    h = 0
    for f in range(A.shape[1]):  # (the casts let the float kernels type this branch too; no-ops on words)
        h += _popcount(np.uint64(A[q, f]) ^ np.uint64(B[t, f]))
    return np.float32(h)


# Inlined (numba IR) into each kernel: the norm is one predictable branch, and each sum keeps its own
# fast-math compilation (the kernels themselves are compiled without it).
@nb.njit(inline="always")
def _score(A, q, B, t, norm):
    """Score of ``A[q]`` against ``B[t]``, float32."""
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
        n0, n1, off, d0, d1, mid, half = geo[q, 0], geo[q, 1], geo[q, 2], geo[q, 3], geo[q, 4], geo[q, 5], geo[q, 6]
        c = 0
        for p in range(q_start[r], q_stop[r]):
            if not _is_candidate(n0, n1, off, d0, d1, mid, half, y[p, 0], y[p, 1], is_line, tol, tol2):
                continue
            c += 1
            t = t_sorted[p]
            if norm == HAMMING:  # (_score, written out: numba's inlining of it costs ~15 % here)
                s = _hamming(A, q, B, p)
            elif norm == L1:
                s = _l1(A, q, B, p)
            else:
                s = _l2sqr(A, q, B, p)
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
        n0, n1, off, d0, d1, mid, half = geo[q, 0], geo[q, 1], geo[q, 2], geo[q, 3], geo[q, 4], geo[q, 5], geo[q, 6]
        for p in range(q_start[r], q_stop[r]):
            if _is_candidate(n0, n1, off, d0, d1, mid, half, y[p, 0], y[p, 1], is_line, tol, tol2):
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


# -- building the index -----------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def query_frames(P, Q, line, is_line):
    """``geo (N, 7)`` (see the module docstring) for segments ``P -> Q (N, 2)`` and unit lines ``(N, 3)``.

    The segment's own unit normal and offset, or for the line constraint the line's; a
    zero-length segment (a point) gets the direction ``(1, 0)``.
    """
    n = P.shape[0]
    geo = np.empty((n, 7))
    for q in range(n):
        D0 = Q[q, 0] - P[q, 0]
        D1 = Q[q, 1] - P[q, 1]
        length = np.hypot(D0, D1)
        d0, d1 = (D0 / length, D1 / length) if length > 0 else (1.0, 0.0)
        if is_line:
            n0, n1, off = line[q, 0], line[q, 1], -line[q, 2]
        else:
            n0, n1 = -d1, d0
            off = n0 * P[q, 0] + n1 * P[q, 1]
        geo[q, 0], geo[q, 1], geo[q, 2] = n0, n1, off
        geo[q, 3], geo[q, 4] = d0, d1
        geo[q, 5] = d0 * P[q, 0] + d1 * P[q, 1] + 0.5 * length
        geo[q, 6] = 0.5 * length
    return geo


@nb.njit(cache=True, nogil=True)
def slice_bounds(key_t, q_sorted, bucket, P, Q, directions, c0, c1, span, tol):
    """``(start, stop)`` per query: the keys ``key_t`` (sorted ``bucket + rho / span + 1/2`` of the
    keypoints) within ``tol`` of the ``rho`` interval of segment ``P[q] -> Q[q]``, ``q = q_sorted[r]``,
    in bucket ``bucket[r]``; ``rho`` is the projection of ``x - c`` on the bucket's direction."""
    n = q_sorted.shape[0]
    start = np.empty(n, dtype=np.int64)
    stop = np.empty(n, dtype=np.int64)
    for r in range(n):
        q, b = q_sorted[r], bucket[r]
        r1 = (P[q, 0] - c0) * directions[b, 0] + (P[q, 1] - c1) * directions[b, 1]
        r2 = (Q[q, 0] - c0) * directions[b, 0] + (Q[q, 1] - c1) * directions[b, 1]
        start[r] = np.searchsorted(key_t, b + ((min(r1, r2) - tol) / span + 0.5), side="left")
        stop[r] = np.searchsorted(key_t, b + ((max(r1, r2) + tol) / span + 0.5), side="right")
    return start, stop


@nb.njit(inline="always")
def _pencil_angle(e, u, v, c0, c1, s, x0, x1):
    """Angle in ``[0, pi)`` of the line through the epipole ``e`` and pixel ``(x0, x1)``, in the pencil
    basis ``(u, v)``, and the first two coefficients of that line (normalised coordinates
    ``(x - c) / s``)."""
    y0 = (x0 - c0) / s
    y1 = (x1 - c1) / s
    l0 = e[1] - e[2] * y1
    l1 = e[2] * y0 - e[0]
    l2 = e[0] * y1 - e[1] * y0
    a = l0 * u[0] + l1 * u[1] + l2 * u[2]
    b = l0 * v[0] + l1 * v[1] + l2 * v[2]
    return np.arctan2(b, a) % np.pi, l0, l1


@nb.njit(cache=True, nogil=True)
def pencil_intervals(e, u, v, c0, c1, s, tol, y):
    """For each pixel ``y (N, 2)``: the interval ``[lo, lo + width]`` (mod pi) of pencil angles of the
    lines through the epipole that pass within ``tol`` of it (``width = pi``: all of them).

    The lines through the epipole at distance ``tol`` from ``y`` touch the circle of radius ``tol``
    around it; they are found as the lines through the points ``y +- tau n``, with ``n`` the normal
    of the line through ``y`` and ``tau = tol / sqrt(1 - (tol / r)^2)``, ``r`` the distance from ``y``
    to the epipole. Both are grown slightly, for rounding.
    """
    n = y.shape[0]
    lo = np.empty(n)
    width = np.empty(n)
    for k in range(n):
        phi, l0, l1 = _pencil_angle(e, u, v, c0, c1, s, y[k, 0], y[k, 1])
        h = max(np.hypot(l0, l1), 1e-300)
        # tol / r (r infinite for an epipole at infinity)
        r = np.hypot(e[0] - (y[k, 0] - c0) / s * e[2], e[1] - (y[k, 1] - c1) / s * e[2])
        ratio = (tol / s) * abs(e[2]) / r if r > 0 else np.inf
        if ratio >= 1 - 1e-9:  # y is within tol of the epipole: every line
            lo[k] = 0.0
            width[k] = np.pi
            continue
        tau = tol / np.sqrt(max(1.0 - ratio * ratio, 1e-18)) * (1 + 1e-9) + 1e-9
        a, _, _ = _pencil_angle(e, u, v, c0, c1, s, y[k, 0] - tau * l0 / h, y[k, 1] - tau * l1 / h)
        b, _, _ = _pencil_angle(e, u, v, c0, c1, s, y[k, 0] + tau * l0 / h, y[k, 1] + tau * l1 / h)
        w = (b - a) % np.pi
        if (phi - a) % np.pi > w:  # the arc from a to b must contain phi; otherwise it is the other one
            lo[k] = b
            width[k] = np.pi - w
        else:
            lo[k] = a
            width[k] = w
    return lo, width


@nb.njit(cache=True, nogil=True)
def spread(lo, hi, edges):
    """Every bucket ``[edges[b], edges[b + 1])`` that each angle interval ``[lo, hi]`` overlaps (``hi``
    may pass pi: the rest continues at 0). Returns ``(item, bucket)`` int64 arrays, each pair once."""
    n_b = edges.shape[0] - 1
    n = lo.shape[0]
    first = np.empty(n, dtype=np.int64)
    last = np.empty(n, dtype=np.int64)
    wrap_last = np.full(n, -1, dtype=np.int64)
    total = 0
    for k in range(n):
        h = min(hi[k], lo[k] + np.pi)
        k0 = min(max(np.searchsorted(edges, lo[k], side="right") - 1, 0), n_b - 1)
        k1 = min(max(np.searchsorted(edges, min(h, np.pi), side="right") - 1, 0), n_b - 1)
        first[k], last[k] = k0, k1
        total += max(k1 - k0 + 1, 0)
        if h > np.pi:  # up to (not into) the buckets already covered
            w1 = min(max(np.searchsorted(edges, h - np.pi, side="right") - 1, 0), n_b - 1)
            wrap_last[k] = min(w1, k0 - 1)
            total += wrap_last[k] + 1
    item = np.empty(total, dtype=np.int64)
    bucket = np.empty(total, dtype=np.int64)
    m = 0
    for k in range(n):
        for b in range(first[k], last[k] + 1):
            item[m], bucket[m] = k, b
            m += 1
        for b in range(0, wrap_last[k] + 1):
            item[m], bucket[m] = k, b
            m += 1
    return item, bucket
