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
computes them (:meth:`episeg_cv.matching.distances.Distances.exact`).

The kernels that run on several threads have a serial twin (``name`` and
``name_parallel``); :func:`episeg_cv.threads.run` picks one. Both give the
same bits; the index build is in :mod:`._index_kernels`.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numba import prange, types
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
    along = max(abs(d0 * y0 + d1 * y1 - mid) - half, 0.0)  # (a select, not a branch)
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


# -- the candidate scan ---------------------------------------------------------------------
# Every kernel that runs on several threads has a serial twin, compiled separately (a parallel region
# costs a fork and a join, so the serial one serves one thread and small inputs: episeg_cv.threads.run).
# Results are the same bits for every thread count: each item is computed by the same code from the same
# inputs, and the minima below are taken under total orders, whose minimum does not depend on how the
# items are split among threads or merged.


@nb.njit(cache=True, nogil=True)
def _scan_rows(r0, r1, q_sorted, q_start, q_stop, t_sorted, geo, y, is_line, tol, tol2, A, B, norm,
               idx, sc, counts, col_s, col_i, buf_p, buf_s):
    """Rows ``r0:r1`` of :func:`knn_scan`, the column best merged into ``col_s / col_i``.

    Per row: (1) the slice's candidates (keypoint indices) compacted into ``buf_p`` without a
    data-dependent branch, (2) their scores into ``buf_s``, (3) the top-k of the query and the column
    best of each keypoint updated with selects (k <= 2) or by insertion (k > 2). ``B`` is indexed by
    keypoint. Orders: a query's neighbours by (score, keypoint index), a keypoint's best query
    by (score, query index); index -1 is "none" and loses every tie.
    """
    k = idx.shape[1]
    for r in range(r0, r1):
        q = q_sorted[r]
        n0, n1, off, d0, d1, mid, half = geo[q, 0], geo[q, 1], geo[q, 2], geo[q, 3], geo[q, 4], geo[q, 5], geo[q, 6]
        m = 0
        # (1) (unsigned positions: no negative-index wrap-around per read of y and t_sorted; 4-6 % of the scan)
        for p in range(np.uint64(q_start[r]), np.uint64(q_stop[r])):
            buf_p[m] = t_sorted[p]
            m += _is_candidate(n0, n1, off, d0, d1, mid, half, y[p, 0], y[p, 1], is_line, tol, tol2)
        if norm == HAMMING:  # (2) (a loop per norm: the score functions keep their fast-math sums)
            for c in range(m):
                buf_s[c] = _hamming(A, q, B, buf_p[c])
        elif norm == L1:
            for c in range(m):
                buf_s[c] = _l1(A, q, B, buf_p[c])
        else:
            for c in range(m):
                buf_s[c] = _l2sqr(A, q, B, buf_p[c])
        counts[q] += m
        if k <= 2:  # (3)
            s1, t1 = sc[q, 0], idx[q, 0]
            s2, t2 = (sc[q, 1], idx[q, 1]) if k == 2 else (np.float32(np.inf), -1)
            for c in range(m):
                t = buf_p[c]
                s = buf_s[c]
                lt1 = (s < s1) | ((s == s1) & ((t1 < 0) | (t < t1)))
                lt2 = (s < s2) | ((s == s2) & ((t2 < 0) | (t < t2)))
                ns2 = s1 if lt1 else (s if lt2 else s2)
                nt2 = t1 if lt1 else (t if lt2 else t2)
                s1 = s if lt1 else s1
                t1 = t if lt1 else t1
                s2, t2 = ns2, nt2
                o_s, o_i = col_s[t], col_i[t]
                b = (s < o_s) | ((s == o_s) & ((o_i < 0) | (q < o_i)))
                col_s[t] = s if b else o_s
                col_i[t] = q if b else o_i
            sc[q, 0], idx[q, 0] = s1, t1
            if k == 2:
                sc[q, 1], idx[q, 1] = s2, t2
        else:
            for c in range(m):
                t = buf_p[c]
                s = buf_s[c]
                last = sc[q, k - 1]
                if s < last or (s == last and (idx[q, k - 1] < 0 or t < idx[q, k - 1])):
                    j = k - 1
                    while j > 0 and (sc[q, j - 1] > s or (sc[q, j - 1] == s and (idx[q, j - 1] < 0 or idx[q, j - 1] > t))):
                        sc[q, j] = sc[q, j - 1]
                        idx[q, j] = idx[q, j - 1]
                        j -= 1
                    sc[q, j] = s
                    idx[q, j] = t
                o_s, o_i = col_s[t], col_i[t]
                if s < o_s or (s == o_s and (o_i < 0 or q < o_i)):
                    col_s[t] = s
                    col_i[t] = q


@nb.njit(cache=True, nogil=True)
def _longest(q_start, q_stop, r0, r1):
    n = 0
    for r in range(r0, r1):
        n = max(n, q_stop[r] - q_start[r])
    return n


@nb.njit(cache=True, nogil=True)
def knn_scan(q_sorted, q_start, q_stop, t_sorted, geo, y, is_line, tol, tol2, A, B, norm,
             idx, sc, counts, col_s, col_i):
    """The ``k`` best candidates of each query, the best query of each keypoint, and candidate counts.

    ``A (N1, D)`` are the query descriptors and ``B (N2, D)`` those of the keypoints (read in place: the
    queries of a bucket share most of their candidates, so their rows stay in cache).

    *Accumulates* into what it is given, so that several indexes (groups of queries) can be scanned
    into the same arrays: ``idx (N1, k)`` / ``sc (N1, k)`` (best first; ties by the smaller keypoint
    index; -1 / inf where a query has fewer than ``k``), ``counts (N1,)`` (added to), and
    ``col_i (N2,)`` / ``col_s (N2,)``: the nearest query among those having the keypoint as a
    candidate (ties by the smaller query index). Start them at -1 / inf / 0 / inf / -1.
    """
    n = q_sorted.shape[0]
    m = _longest(q_start, q_stop, 0, n)
    _scan_rows(np.int64(0), n, q_sorted, q_start, q_stop, t_sorted, geo, y, is_line, tol, tol2, A, B, norm,
               idx, sc, counts, col_s, col_i, np.empty(m, np.int64), np.empty(m, np.float32))


@nb.njit(cache=True, nogil=True, parallel=True)
def knn_scan_parallel(q_sorted, q_start, q_stop, t_sorted, geo, y, is_line, tol, tol2, A, B, norm,
                      idx, sc, counts, col_s, col_i, bounds, tcol_s, tcol_i):
    """:func:`knn_scan` on threads, over the row blocks ``bounds[c]:bounds[c + 1]``.

    A query has one row, so its ``idx``, ``sc`` and ``counts`` are written by one block only. The
    column best goes to per-thread arrays ``tcol_s / tcol_i (n_threads, N2)``, indexed by
    ``numba.get_thread_id()`` (any content on entry; ``n_threads`` must be numba's thread count of the
    launch, see :func:`episeg_cv.threads.call_parallel`), then is merged into ``col_s / col_i`` by the
    same order.
    """
    nt = tcol_s.shape[0]
    for h in prange(nt):
        tcol_s[h, :] = np.inf
        tcol_i[h, :] = -1
    for c in prange(bounds.shape[0] - 1):
        h = nb.get_thread_id()
        m = _longest(q_start, q_stop, bounds[c], bounds[c + 1])
        _scan_rows(bounds[c], bounds[c + 1], q_sorted, q_start, q_stop, t_sorted, geo, y, is_line, tol, tol2,
                   A, B, norm, idx, sc, counts, tcol_s[h], tcol_i[h], np.empty(m, np.int64), np.empty(m, np.float32))
    for t in prange(col_s.shape[0]):
        bs, bq = col_s[t], col_i[t]
        for h in range(nt):
            s, q = tcol_s[h, t], tcol_i[h, t]
            if q >= 0 and (s < bs or (s == bs and (bq < 0 or q < bq))):
                bs, bq = s, q
        col_s[t], col_i[t] = bs, bq


def work_bounds(q_start: np.ndarray, q_stop: np.ndarray, blocks: int, per_row: int = 16) -> np.ndarray:
    """``(blocks + 1,)`` row bounds cutting the rows into blocks of about equal work (slice length plus
    ``per_row`` per row)."""
    work = np.cumsum(q_stop - q_start + per_row)
    total = int(work[-1]) if len(work) else 0
    cuts = np.searchsorted(work, total * np.arange(1, blocks) / blocks, side="left") + 1
    return np.concatenate([[0], np.minimum(cuts, len(work)), [len(work)]]).astype(np.int64)


@nb.njit(cache=True, nogil=True)
def _count_rows(r0, r1, q_sorted, q_start, q_stop, geo, y, is_line, tol, tol2, out):
    for r in range(r0, r1):
        q = q_sorted[r]
        n0, n1, off, d0, d1, mid, half = geo[q, 0], geo[q, 1], geo[q, 2], geo[q, 3], geo[q, 4], geo[q, 5], geo[q, 6]
        c = 0
        for p in range(q_start[r], q_stop[r]):
            c += _is_candidate(n0, n1, off, d0, d1, mid, half, y[p, 0], y[p, 1], is_line, tol, tol2)
        out[r] = c


@nb.njit(cache=True, nogil=True)
def _fill_rows(r0, r1, q_sorted, q_start, q_stop, t_sorted, geo, y, is_line, tol, tol2, first, i, j):
    for r in range(r0, r1):
        q = q_sorted[r]
        n0, n1, off, d0, d1, mid, half = geo[q, 0], geo[q, 1], geo[q, 2], geo[q, 3], geo[q, 4], geo[q, 5], geo[q, 6]
        n = first[r]
        for p in range(q_start[r], q_stop[r]):
            if _is_candidate(n0, n1, off, d0, d1, mid, half, y[p, 0], y[p, 1], is_line, tol, tol2):
                i[n] = q
                j[n] = t_sorted[p]
                n += 1


@nb.njit(cache=True, nogil=True)
def candidate_pairs(q_sorted, q_start, q_stop, t_sorted, geo, y, is_line, tol, tol2):
    """Every candidate pair: ``(i, j)`` int64 arrays, in scan order (callers sort)."""
    n = q_sorted.shape[0]
    total = 0
    for r in range(n):
        total += q_stop[r] - q_start[r]
    i = np.empty(total, dtype=np.int64)
    j = np.empty(total, dtype=np.int64)
    m = 0
    for r in range(n):
        q = q_sorted[r]
        n0, n1, off, d0, d1, mid, half = geo[q, 0], geo[q, 1], geo[q, 2], geo[q, 3], geo[q, 4], geo[q, 5], geo[q, 6]
        for p in range(q_start[r], q_stop[r]):
            if _is_candidate(n0, n1, off, d0, d1, mid, half, y[p, 0], y[p, 1], is_line, tol, tol2):
                i[m] = q
                j[m] = t_sorted[p]
                m += 1
    return i[:m], j[:m]


@nb.njit(cache=True, nogil=True, parallel=True)
def candidate_pairs_parallel(q_sorted, q_start, q_stop, t_sorted, geo, y, is_line, tol, tol2, blocks):
    """:func:`candidate_pairs` on threads (a count per row, its prefix sum, then each row's pairs in
    place): the same arrays in the same order."""
    n = q_sorted.shape[0]
    nblk = blocks
    cnt = np.empty(n, dtype=np.int64)
    for c in prange(nblk):
        _count_rows(c * n // nblk, (c + 1) * n // nblk, q_sorted, q_start, q_stop, geo, y, is_line, tol, tol2, cnt)
    first = np.empty(n + 1, dtype=np.int64)
    first[0] = 0
    for r in range(n):
        first[r + 1] = first[r] + cnt[r]
    i = np.empty(first[n], dtype=np.int64)
    j = np.empty(first[n], dtype=np.int64)
    for c in prange(nblk):
        _fill_rows(c * n // nblk, (c + 1) * n // nblk, q_sorted, q_start, q_stop, t_sorted, geo, y, is_line, tol,
                   tol2, first, i, j)
    return i, j


@nb.njit(cache=True, nogil=True)
def paired_scores(A, B, i, j, norm):
    """``(K,)`` float32 scores of the pairs ``(i[k], j[k])``."""
    out = np.empty(i.shape[0], dtype=np.float32)
    for n in range(i.shape[0]):
        out[n] = _score(A, i[n], B, j[n], norm)
    return out


@nb.njit(cache=True, nogil=True, parallel=True)
def paired_scores_parallel(A, B, i, j, norm, blocks):
    """:func:`paired_scores` on threads (each pair independent)."""
    n = i.shape[0]
    out = np.empty(n, dtype=np.float32)
    nblk = blocks
    for c in prange(nblk):
        for m in range(c * n // nblk, (c + 1) * n // nblk):
            out[m] = _score(A, i[m], B, j[m], norm)
    return out


@nb.njit(cache=True, nogil=True)
def _nearest_rows(r0, r1, A, B, qi, tj, exclude, norm, out):
    for r in range(r0, r1):
        best = np.float32(np.inf)
        for c in range(tj.shape[0]):
            if tj[c] == exclude[r]:
                continue
            s = _score(A, qi[r], B, tj[c], norm)
            if s < best:
                best = s
        out[r] = best


@nb.njit(cache=True, nogil=True)
def nearest_excluding(A, B, qi, tj, exclude, norm):
    """``(len(qi),)`` smallest score of query ``qi[r]`` over the keypoints ``tj``, leaving out ``exclude[r]``
    (inf when nothing is left)."""
    out = np.empty(qi.shape[0], dtype=np.float32)
    _nearest_rows(np.int64(0), qi.shape[0], A, B, qi, tj, exclude, norm, out)
    return out


@nb.njit(cache=True, nogil=True, parallel=True)
def nearest_excluding_parallel(A, B, qi, tj, exclude, norm, blocks):
    """:func:`nearest_excluding` on threads (each query independent)."""
    n = qi.shape[0]
    out = np.empty(n, dtype=np.float32)
    nblk = blocks
    for c in prange(nblk):
        _nearest_rows(c * n // nblk, (c + 1) * n // nblk, A, B, qi, tj, exclude, norm, out)
    return out


@nb.njit(cache=True, nogil=True)
def padding_operands(B, tj):
    """``(BT2 (D, C), bb (C,))`` float32 of the padding references ``B[tj]`` for :func:`padding_l2`: their
    descriptors times ``-2`` (exact: a power of two), transposed, and their squared norms summed in
    order (the same bits wherever they are computed)."""
    C, D = tj.shape[0], B.shape[1]
    bt2 = np.empty((D, C), dtype=np.float32)
    bb = np.empty(C, dtype=np.float32)
    for c in range(C):
        s = np.float32(0.0)
        for f in range(D):
            x = np.float32(B[tj[c], f])
            bt2[f, c] = x * np.float32(-2.0)
            s += x * x
        bb[c] = s
    return bt2, bb


@nb.njit(cache=True, nogil=True)
def padding_l2(A, qi, BT2, bb, tj, exclude, r0, r1, rows, prod, out, round_to):
    """``out[r]``, for ``r`` in ``r0:r1``: the smallest squared L2 distance from ``A[qi[r]]`` to the
    keypoints ``tj`` but ``exclude[r]`` (inf when none is left), as ``|a|^2 + min_c (|b_c|^2 - 2 a.b_c)``
    clamped at 0.

    ``BT2 (D, C)`` is ``-2`` times the keypoints' descriptors, transposed, and ``bb (C,)`` their squared
    norms. The rows go in chunks of ``len(rows)`` starting at ``r0``: each chunk's rows are gathered into
    ``rows``, multiplied by ``BT2`` with BLAS into ``prod`` (``np.dot``, in cache), then reduced. A last,
    shorter chunk is multiplied padded with zero rows to a multiple of ``round_to`` rows (not to
    ``len(rows)``: a few hundred queries then cost a few hundred rows). Call with ``r0`` a multiple of
    ``len(rows)`` and ``r1`` the end of all rows, so that a row's product never depends on how the rows
    are split between threads.
    """
    D, C, m = A.shape[1], BT2.shape[1], rows.shape[0]
    for s in range(r0, r1, m):
        e = min(s + m, r1)
        k = e - s
        for i in range(k):
            q = qi[s + i]
            for f in range(D):
                rows[i, f] = A[q, f]
        mm = min(m, -(-k // round_to) * round_to)
        if k < mm:
            rows[k:mm, :] = 0.0
        np.dot(rows[:mm], BT2, prod[:mm])
        for i in range(k):
            best = np.float32(np.inf)
            ex = exclude[s + i]
            for c in range(C):
                v = prod[i, c] + bb[c]
                if v < best and tj[c] != ex:
                    best = v
            aa = np.float32(0.0)
            for f in range(D):
                aa += rows[i, f] * rows[i, f]
            v = best + aa
            out[s + i] = v if v > 0.0 else np.float32(0.0)


@nb.njit(cache=True, nogil=True, parallel=True)
def padding_l2_parallel(A, qi, BT2, bb, tj, exclude, cuts, rows, prod, out, round_to):
    """:func:`padding_l2` on numba's threads: block ``h`` does the rows ``cuts[h]:cuts[h + 1]`` (whole chunks,
    so a row's product does not depend on the split) with its own ``rows[h]`` and ``prod[h]``
    (``(n_blocks, chunk, D)`` and ``(n_blocks, chunk, C)``). BLAS must be limited to one thread.

    On the threads that the scan and the index just used: on Python threads instead, the padding did not
    run faster on two cores than on one (numba's idle threads spin for a while after a parallel loop)."""
    for h in prange(cuts.shape[0] - 1):
        padding_l2(A, qi, BT2, bb, tj, exclude, cuts[h], cuts[h + 1], rows[h], prod[h], out, round_to)


@nb.njit(cache=True, nogil=True)
def gather_rows(src, rows, out):
    """``out[m] = src[rows[m]]`` (rows of any width)."""
    for m in range(rows.shape[0]):
        r = rows[m]
        for c in range(src.shape[1]):
            out[m, c] = src[r, c]


@nb.njit(cache=True, nogil=True, parallel=True)
def gather_rows_parallel(src, rows, out, blocks):
    """:func:`gather_rows` on threads."""
    for m in prange(rows.shape[0]):
        r = rows[m]
        for c in range(src.shape[1]):
            out[m, c] = src[r, c]
