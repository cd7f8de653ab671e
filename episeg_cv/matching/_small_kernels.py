"""Compiled kernels of :mod:`.small`: a small pair's nearest candidates in one call, and the reverse test.

:func:`nearest` is :func:`episeg_cv.matching.guided.nearest` for a calibrated geometry and the
segment constraint, from the keypoints to the ratios, without returning to Python: the segments
(:func:`episeg_cv._geometry_kernels._segments`), the per-query frames
(:func:`._index_kernels._frames`), the candidate slices, the scan (:func:`._kernels._scan_rows`),
the padding (:func:`._kernels.padding_l2` or the other norms' scores) and the ratios. Only the
slices differ from :class:`~.candidates.CandidateIndex`: the keypoints of image 2 are sorted along
three axes (``x``, ``y``, and the normal of the segments' mean direction, across nearly parallel
lines), and each query scans those inside its segment's bounding box grown by ``tol``, along the
axis where the box holds fewest. A keypoint within ``tol`` of the segment is in
that box, and the exact test of :mod:`._kernels` decides, so the candidates are the index's; the
scan's orders are total, so the results do not depend on the order of the rows.

:func:`nearest` runs on one thread and holds no GIL (``nogil``); :func:`pairs` matches many pairs
both ways (the collection's jobs, :func:`episeg_cv.colmap.job.match_pairs`), and its parallel twin
runs a pair per thread.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numba import prange

from .. import _geometry_kernels as _gk
from . import _index_kernels as _ik
from . import _kernels

__all__ = ["nearest", "nearest_ratios", "rule_passes", "reverse_keep", "segment_keep", "pairs", "pairs_parallel"]


@nb.njit(cache=True, nogil=True)
def _ratio(d1, d2):
    """``d1 / d2`` as :func:`episeg_cv.matching.guided._ratio`: 0 without a second, inf for ``d2 = 0 < d1``,
    1 for ``0 / 0``."""
    if not np.isfinite(d2):
        return 0.0
    if d2 > 0:
        return d1 / d2
    return np.inf if d1 > 0 else 1.0


@nb.njit(cache=True, nogil=True)
def _distance(s, root):
    """A score as a distance, float64 (the square root of float32 squared L2 with ``root``)."""
    return np.sqrt(np.float64(s)) if root else np.float64(s)


@nb.njit(cache=True, nogil=True)
def _bucket(k, kmin, scale, last):
    """The bucket of key ``k`` (monotone in ``k``): ``floor((k - kmin) * scale)`` clipped to ``[0, last]``."""
    return int(min(max((k - kmin) * scale, 0.0), float(last)))


@nb.njit(cache=True, nogil=True)
def _axis(x2, a0, a1, keys, order, ys, table):
    """The keypoints ``x2 (N2, 2)`` sorted along the axis ``(a0, a1)``: into ``keys (N2,)`` (their positions
    along it), ``order (N2,)`` (their rows), ``ys (N2, 2)`` (their pixels) and ``table (N2 + 1,)``, where
    ``table[c]`` is the first sorted position whose bucket (:func:`_bucket`, ``N2`` buckets over the keys'
    range) is ``c`` or more. Returns ``(kmin, scale)`` of the buckets."""
    n2 = x2.shape[0]
    v = np.empty(n2)
    for p in range(n2):
        v[p] = x2[p, 0] * a0 + x2[p, 1] * a1
    order[:] = np.argsort(v)
    for p in range(n2):
        t = order[p]
        keys[p] = v[t]
        ys[p, 0], ys[p, 1] = x2[t, 0], x2[t, 1]
    kmin = keys[0] if n2 else 0.0
    span = keys[n2 - 1] - kmin if n2 else 0.0
    scale = n2 / span if span > 0 else 0.0
    last = max(n2 - 1, 0)
    c = 0
    for p in range(n2):
        b = _bucket(keys[p], kmin, scale, last)
        while c <= b:
            table[c] = p
            c += 1
    while c <= n2:
        table[c] = n2
        c += 1
    return kmin, scale


@nb.njit(cache=True, nogil=True)
def _slices(lo, hi, keys, table, kmin, scale):
    """``[start, stop)`` of the sorted ``keys`` within ``[lo, hi]`` (as ``np.searchsorted`` with
    ``side="left"`` and ``"right"``): from the first position of each bound's bucket (``table``,
    :func:`_axis`), a few steps forward. Every key before that position lies in a lower bucket, so below
    the bound."""
    n = keys.shape[0]
    last = max(n - 1, 0)
    s = table[_bucket(lo, kmin, scale, last)]
    while s < n and keys[s] < lo:
        s += 1
    e = max(s, table[_bucket(hi, kmin, scale, last)])
    while e < n and keys[e] <= hi:
        e += 1
    return s, e


@nb.njit(cache=True, nogil=True)
def _image_axes(x2, keys, order, ys, table):
    """:func:`_axis` along ``x`` and ``y`` into row 0 and 1 of each output; ``(2, 2)`` their ``(kmin, scale)``."""
    out = np.empty((2, 2))
    out[0, 0], out[0, 1] = _axis(x2, 1.0, 0.0, keys[0], order[0], ys[0], table[0])
    out[1, 0], out[1, 1] = _axis(x2, 0.0, 1.0, keys[1], order[1], ys[1], table[1])
    return out


@nb.njit(cache=True, nogil=True, error_model="numpy")
def nearest(x1, x2, A, B, norm, root, H, b, zmin, zmax, rect, eps, tol, pad_j, ratio, mutual_rule, prefilter,
            chunk, round_to):
    """Every query's nearest candidate on its segment: ``(i, j, ratio, mutual, counts)``, as
    :func:`~episeg_cv.matching.guided.nearest` returns them.

    ``x1 (N1, 2)`` / ``x2 (N2, 2)`` float64 pixels; ``A`` / ``B`` the scoring arrays of
    :class:`~.distances.Distances` and ``norm`` its kernel code, ``root``: scores are squared L2
    distances reported as L2 (``"l2"``). ``H``, ``b``: the geometry's infinite homography and
    homogeneous epipole; ``zmin`` / ``zmax`` ``(1,)`` or ``(N1,)``; ``rect`` image 2 grown by
    ``tol``; ``eps`` the cheirality tolerance. ``pad_j``: the sorted padding references (empty:
    none). ``ratio``, ``mutual_rule``: the rule, for ``prefilter`` (pad only the pairs it keeps
    without padding). ``chunk`` / ``round_to``: the padding's BLAS blocks
    (:data:`~.distances.PAD_CHUNK`, :data:`~.distances.PAD_ROUND`).
    """
    n2 = x2.shape[0]
    keys, order = np.empty((3, n2)), np.empty((3, n2), dtype=np.int64)
    ys, table = np.empty((3, n2, 2)), np.empty((3, n2 + 1), dtype=np.int64)
    buckets = np.empty((3, 2))
    buckets[:2] = _image_axes(x2, keys, order, ys, table)
    return _nearest_sorted(x1, x2, A, B, norm, root, H, b, zmin, zmax, rect, eps, tol, pad_j, ratio, mutual_rule,
                           prefilter, chunk, round_to, keys, order, ys, table, buckets)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _nearest_sorted(x1, x2, A, B, norm, root, H, b, zmin, zmax, rect, eps, tol, pad_j, ratio, mutual_rule, prefilter,
                    chunk, round_to, keys, order, ys, table, buckets):
    """:func:`nearest` with image 2 sorted along ``x`` and ``y`` already (rows 0 and 1 of ``keys``,
    ``order``, ``ys``, ``table``, ``buckets``: :func:`_image_axes`); row 2, the segments' own axis, is
    filled here."""
    n1, n2 = x1.shape[0], x2.shape[0]
    start, end, line = np.empty((n1, 2)), np.empty((n1, 2)), np.empty((n1, 3))
    p_inf, a, valid = np.empty((n1, 2)), np.empty((n1, 3)), np.empty(n1, dtype=np.bool_)
    _gk._segments(np.int64(0), n1, x1, H, b, zmin, zmax, rect, eps, start, end, valid, line, p_inf, a)
    for q in range(n1):
        for c in range(3):
            if not np.isfinite(line[q, c]):
                line[q, c] = 0.0
    geo = np.empty((n1, 7))
    _ik._frames(np.int64(0), n1, start, end, line, False, geo)
    tol2 = tol * tol * (1 + 1e-9) + 1e-12
    # the slices: keypoints sorted along three axes (x, y, and across the segments' mean direction); each
    # query scans those inside its segment's box along the axis where the box holds fewest
    u0, u1, seen = 0.0, 0.0, False
    for q in range(n1):
        if valid[q]:
            s = 1.0 if not seen or geo[q, 3] * u0 + geo[q, 4] * u1 >= 0 else -1.0
            u0, u1, seen = u0 + s * geo[q, 3], u1 + s * geo[q, 4], True
    nu = np.hypot(u0, u1)
    a0, a1 = (-u1 / nu, u0 / nu) if nu > 0 else (1.0, 0.0)  # the normal of the mean direction
    axes = np.array([[1.0, 0.0], [0.0, 1.0], [a0, a1]])
    buckets[2, 0], buckets[2, 1] = _axis(x2, a0, a1, keys[2], order[2], ys[2], table[2])
    rows = np.empty((3, n1), dtype=np.int64)
    lo, hi = np.empty((3, n1), dtype=np.int64), np.empty((3, n1), dtype=np.int64)
    n_rows = np.zeros(3, dtype=np.int64)
    longest = 0
    for q in range(n1):
        if not valid[q]:
            continue
        P0, P1, Q0, Q1 = start[q, 0], start[q, 1], end[q, 0], end[q, 1]
        g = tol * (1 + 1e-6) + 1e-6 * (1.0 + max(abs(P0), abs(P1), abs(Q0), abs(Q1)))  # covers the test's rounding
        best, s0, s1 = -1, 0, 0
        for ax in range(3):
            kp, kq = P0 * axes[ax, 0] + P1 * axes[ax, 1], Q0 * axes[ax, 0] + Q1 * axes[ax, 1]
            c0, c1 = _slices(min(kp, kq) - g, max(kp, kq) + g, keys[ax], table[ax], buckets[ax, 0], buckets[ax, 1])
            if best < 0 or c1 - c0 < s1 - s0:
                best, s0, s1 = ax, c0, c1
        if s1 > s0:
            r = n_rows[best]
            rows[best, r], lo[best, r], hi[best, r] = q, s0, s1
            n_rows[best] = r + 1
            longest = max(longest, s1 - s0)
    idx = np.full((n1, 2), -1, dtype=np.intp)
    sc = np.full((n1, 2), np.inf, dtype=np.float32)
    counts = np.zeros(n1, dtype=np.intp)
    col_i = np.full(n2, -1, dtype=np.intp)
    col_s = np.full(n2, np.inf, dtype=np.float32)
    buf_p, buf_s = np.empty(longest, np.int64), np.empty(longest, np.float32)
    for ax in range(3):
        m = n_rows[ax]
        _kernels._scan_rows(np.int64(0), m, rows[ax, :m], lo[ax, :m], hi[ax, :m], order[ax], geo, ys[ax], False, tol,
                            tol2, A, B, norm, idx, sc, counts, col_s, col_i, buf_p, buf_s)
    i, j, ratios, mutual = nearest_ratios(idx, sc, col_i, A, B, norm, root, pad_j, ratio, mutual_rule, prefilter,
                                          chunk, round_to)
    return i, j, ratios, mutual, counts


@nb.njit(cache=True, nogil=True, error_model="numpy")
def nearest_ratios(idx, sc, best, A, B, norm, root, pad_j, ratio, mutual_rule, prefilter, chunk, round_to):
    """The end of :func:`nearest` once the candidates are scanned: ``(i, j, ratio, mutual)`` of every query
    with a candidate, from its two best ``idx (N1, 2)`` / ``sc (N1, 2)``; ``best (N2,)``: each keypoint's
    nearest query (mutual: ``best[j] == i``). The padding references ``pad_j`` are scored (for the pairs
    that ``ratio`` and ``mutual_rule`` keep without them, with ``prefilter``) as
    :meth:`~.distances.Distances.nearest_excluding` scores them on one thread."""
    n1 = idx.shape[0]
    n = 0
    for q in range(n1):
        n += idx[q, 0] >= 0
    i, j = np.empty(n, dtype=np.intp), np.empty(n, dtype=np.intp)
    s1, s2 = np.empty(n, dtype=np.float32), np.empty(n, dtype=np.float32)
    mutual = np.empty(n, dtype=np.bool_)
    n = 0
    for q in range(n1):
        if idx[q, 0] >= 0:
            i[n], j[n], s1[n], s2[n] = q, idx[q, 0], sc[q, 0], sc[q, 1]
            mutual[n] = best[idx[q, 0]] == q
            n += 1
    if pad_j.shape[0] and n:
        padded = np.empty(n, dtype=np.int64)
        m, zero = np.int64(0), np.int64(0)  # (not literals: numba compiled the callees for each literal typing)
        for r in range(n):
            keep = True
            if prefilter:
                keep = (ratio >= 1 or _ratio(_distance(s1[r], root), _distance(s2[r], root)) < ratio) and \
                       (mutual[r] or not mutual_rule)
            if keep:
                padded[m] = r
                m += 1
        qi, ex = np.empty(m, dtype=np.int64), np.empty(m, dtype=np.int64)
        for r in range(m):
            qi[r], ex[r] = i[padded[r]], j[padded[r]]
        out = np.empty(m, dtype=np.float32)
        if norm == _kernels.L2SQR:
            bt2, bb = _kernels.padding_operands(B, pad_j)
            _kernels.padding_l2(A, qi, bt2, bb, pad_j, ex, zero, m, np.empty((chunk, A.shape[1]), np.float32),
                                np.empty((chunk, pad_j.shape[0]), np.float32), out, round_to)
        else:
            _kernels._nearest_rows(zero, m, A, B, qi, pad_j, ex, norm, out)
        for r in range(m):
            s2[padded[r]] = min(s2[padded[r]], out[r])
    ratios = np.empty(n)
    for r in range(n):
        ratios[r] = _ratio(_distance(s1[r], root), _distance(s2[r], root))
    return i, j, ratios, mutual


@nb.njit(cache=True, nogil=True, error_model="numpy")
def segment_keep(line, start, end, valid, i, y, j, tol):
    """``(K,)`` bool: keypoint ``y[j[k]]`` within ``tol`` of segment ``i[k]`` (``line``, ``start``, ``end``,
    ``valid``: the arrays of :class:`~episeg_cv.EpipolarSegments`). A pair far from the line (beyond a
    rounding margin) is out without the segment distance; an undefined (NaN) line lets the segment
    distance decide. The distance is :func:`episeg_cv.geometry.point_segment_distance`'s, in the same
    order."""
    keep = np.zeros(j.shape[0], dtype=np.bool_)
    far = tol * (1 + 1e-6) + 1e-6
    for k in range(j.shape[0]):
        q = i[k]
        p0, p1 = y[j[k], 0], y[j[k], 1]
        if not valid[q] or abs(line[q, 0] * p0 + line[q, 1] * p1 + line[q, 2]) > far:
            continue
        s0, s1 = start[q, 0], start[q, 1]
        d0, d1 = end[q, 0] - s0, end[q, 1] - s1
        dd = d0 * d0 + d1 * d1
        u = 0.0
        if dd > 0:
            u = min(max(((p0 - s0) * d0 + (p1 - s1) * d1) / dd, 0.0), 1.0)
        keep[k] = np.hypot(p0 - s0 - u * d0, p1 - s1 - u * d1) <= tol
    return keep


@nb.njit(cache=True, nogil=True)
def rule_passes(ratios, mutual, ratio, mutual_rule, strict):
    """``(K,)`` bool: the matches the rule keeps, a ratio below ``ratio`` (any ratio when ``ratio >= 1``
    and not ``strict``) and, with ``mutual_rule``, mutual."""
    keep = np.empty(ratios.shape[0], dtype=np.bool_)
    for k in range(ratios.shape[0]):
        keep[k] = (ratios[k] < ratio or (ratio >= 1 and not strict)) and (mutual[k] or not mutual_rule)
    return keep


@nb.njit(cache=True, nogil=True, error_model="numpy")
def reverse_keep(x1, x2, i, j, Hi, bi, zmin, zmax, rect1, eps, tol, is_line):
    """``(K,)`` bool: the query ``x1[i[k]]`` lies within ``tol`` of the segment (or, ``is_line``, the line) in
    image 1 of the keypoint ``x2[j[k]]``, as :func:`~.filtering.keep_mask` tests the pairs ``(j, i)``
    from image 2 to image 1 (``Hi``, ``bi``: the inverse geometry; ``zmin`` / ``zmax`` ``(1,)``: image 2's
    depth range; ``rect1``: image 1 grown by ``tol``). A NaN line keeps nothing."""
    m = i.shape[0]
    y = np.empty((m, 2))
    for k in range(m):
        y[k, 0], y[k, 1] = x2[j[k], 0], x2[j[k], 1]
    start, end, line = np.empty((m, 2)), np.empty((m, 2)), np.empty((m, 3))
    p_inf, a, valid = np.empty((m, 2)), np.empty((m, 3)), np.empty(m, dtype=np.bool_)
    _gk._segments(np.int64(0), m, y, Hi, bi, zmin, zmax, rect1, eps, start, end, valid, line, p_inf, a)
    if not is_line:
        return segment_keep(line, start, end, valid, np.arange(m), x1, i, tol)
    keep = np.empty(m, dtype=np.bool_)
    for k in range(m):
        keep[k] = abs(line[k, 0] * x1[i[k], 0] + line[k, 1] * x1[i[k], 1] + line[k, 2]) <= tol
    return keep


# -- many small pairs ------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _sort_images(u0, u1, X, first, IK, IO, IY, IT, IB):
    """:func:`_image_axes` of images ``u0:u1`` (keypoints ``X[first[u]:first[u + 1]]``), once for all their
    pairs: image ``u``'s rows are columns ``first[u]:first[u + 1]`` of ``IK``, ``IO`` (local rows), ``IY``,
    and ``first[u] + u`` on of ``IT`` (one longer); ``IB[u]`` its buckets."""
    for u in range(u0, u1):
        f, g = first[u], first[u + 1]
        IB[u] = _image_axes(X[f:g], IK[:, f:g], IO[:, f:g], IY[:, f:g], IT[:, f + u:g + u + 1])


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _both_ways(x1, x2, A, B, norm, root, H, b, zr1, rect1, Hi, bi, zr2, rect2, eps, tol, pad_j, loose, mutual_rule,
               chunk, round_to, k2, o2, y2, t2, b2):
    """One pair of :func:`pairs`: ``(i, j, ratio, inlier)`` of the candidates with ratio below ``loose``;
    ``k2, o2, y2, t2, b2``: image 2 sorted along ``x`` and ``y`` (:func:`_sort_images`)."""
    n2 = x2.shape[0]
    keys, order = np.empty((3, n2)), np.empty((3, n2), dtype=np.int64)
    ys, table = np.empty((3, n2, 2)), np.empty((3, n2 + 1), dtype=np.int64)
    buckets = np.empty((3, 2))
    keys[:2], order[:2], ys[:2], table[:2], buckets[:2] = k2, o2, y2, t2, b2
    i, j, r, mu, _ = _nearest_sorted(x1, x2, A, B, norm, root, H, b, zr1[0:1], zr1[1:2], rect1, eps, tol, pad_j,
                                     loose, mutual_rule, True, chunk, round_to, keys, order, ys, table, buckets)
    ok = rule_passes(r, mu, loose, mutual_rule, True)
    ki, kj, kr = i[ok], j[ok], r[ok]
    # the reverse test: each match's keypoint of image 2 must have its query on its own segment in image 1
    inlier = reverse_keep(x1, x2, ki, kj, Hi, bi, zr2[0:1], zr2[1:2], rect2, eps, tol, False)
    return ki, kj, kr, inlier


@nb.njit(cache=True, nogil=True)
def _pair_range(p0, p1, X, A, first, img, H, b, Hi, bi, zr, rects, eps, tol, pad, pad_first, norm, root, loose,
                mutual_rule, chunk, round_to, out_first, out_i, out_j, out_r, out_in, out_n, IK, IO, IY, IT, IB):
    for p in range(p0, p1):
        u, v = img[p, 0], img[p, 1]
        f, g = first[v], first[v + 1]
        ki, kj, kr, inl = _both_ways(X[first[u]:first[u + 1]], X[f:g], A[first[u]:first[u + 1]], A[f:g], norm, root,
                                     H[p], b[p], zr[u], rects[p, 0], Hi[p], bi[p], zr[v], rects[p, 1], eps, tol[p],
                                     pad[pad_first[p]:pad_first[p + 1]], loose, mutual_rule, chunk, round_to,
                                     IK[:, f:g], IO[:, f:g], IY[:, f:g], IT[:, f + v:g + v + 1], IB[v])
        o = out_first[p]
        for k in range(ki.shape[0]):
            out_i[o + k], out_j[o + k], out_r[o + k], out_in[o + k] = ki[k], kj[k], kr[k], inl[k]
        out_n[p] = ki.shape[0]


@nb.njit(cache=True, nogil=True)
def _image_buffers(X, first):
    """Empty ``IK, IO, IY, IT, IB`` for :func:`_sort_images` of every image."""
    n, m = X.shape[0], first.shape[0] - 1
    return (np.empty((2, n)), np.empty((2, n), dtype=np.int64), np.empty((2, n, 2)),
            np.empty((2, n + m), dtype=np.int64), np.empty((m, 2, 2)))


@nb.njit(cache=True, nogil=True)
def pairs(X, A, first, img, H, b, Hi, bi, zr, rects, eps, tol, pad, pad_first, norm, root, loose, mutual_rule,
          chunk, round_to, out_first, out_i, out_j, out_r, out_in, out_n):
    """Many pairs of images, each matched both ways (:func:`nearest` forward with ratio ``loose`` and the
    rule's mutual flag, then the reverse segment test), into preallocated outputs.

    Images: their keypoints ``X[first[u]:first[u + 1]]`` (float64 pinhole pixels) and scoring rows
    ``A[...]``; ``zr (n_images, 2)`` their depth ranges. Pair ``p`` matches image ``img[p, 0]`` to
    ``img[p, 1]`` with the geometry ``H[p], b[p]`` and its inverse ``Hi[p], bi[p]``, the band ``tol[p]``,
    ``rects[p, 0]`` / ``rects[p, 1]`` the two images grown by it, padding references ``pad[pad_first[p]:pad_first[p
    + 1]]``. Its ``out_n[p]`` candidates go to rows ``out_first[p]:`` of ``out_i, out_j`` (keypoint
    rows in the two images), ``out_r`` (ratio) and ``out_in`` (the reverse test); ``out_first[p]``
    leaves room for one per query. Each image is sorted along ``x`` and ``y`` once, for all its pairs.
    """
    IK, IO, IY, IT, IB = _image_buffers(X, first)
    _sort_images(np.int64(0), first.shape[0] - 1, X, first, IK, IO, IY, IT, IB)
    _pair_range(0, img.shape[0], X, A, first, img, H, b, Hi, bi, zr, rects, eps, tol, pad, pad_first, norm, root,
                loose, mutual_rule, chunk, round_to, out_first, out_i, out_j, out_r, out_in, out_n, IK, IO, IY, IT, IB)


@nb.njit(cache=True, nogil=True, parallel=True)
def pairs_parallel(X, A, first, img, H, b, Hi, bi, zr, rects, eps, tol, pad, pad_first, norm, root, loose,
                   mutual_rule, chunk, round_to, out_first, out_i, out_j, out_r, out_in, out_n, blocks):
    """:func:`pairs` on threads, an image, then a pair, per item (each pair's outputs are its own rows)."""
    IK, IO, IY, IT, IB = _image_buffers(X, first)
    for u in prange(first.shape[0] - 1):
        _sort_images(u, u + 1, X, first, IK, IO, IY, IT, IB)
    for p in prange(img.shape[0]):
        _pair_range(p, p + 1, X, A, first, img, H, b, Hi, bi, zr, rects, eps, tol, pad, pad_first, norm, root,
                    loose, mutual_rule, chunk, round_to, out_first, out_i, out_j, out_r, out_in, out_n, IK, IO, IY,
                    IT, IB)
