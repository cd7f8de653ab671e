"""Compiled loops that build :class:`~episeg_cv.matching.candidates.CandidateIndex` (numba).

Each kernel that runs on several threads has a serial twin (``name`` and ``name_parallel``), chosen by
:func:`episeg_cv.threads.run`. Every item (query, keypoint, bucket) is computed by the same code from
the same inputs whatever the thread, and the order of the outputs does not depend on the threads, so
the index is the same for every thread count. Arithmetic is float64, without fast-math.

Conventions: ``P, Q (N1, 2)`` are the ends of each query's segment (or clipped line), ``line (N1, 3)``
its unit epipolar line (zero where undefined), ``y (N2, 2)`` the keypoints of image 2. Pencil angles
``phi`` are taken in normalised coordinates ``(x - c) / s`` of image 2, in the basis ``(u, v)`` of the
lines through the unit homogeneous epipole ``e``, as *pseudo-angles* in ``[0, PERIOD)``: a strictly
increasing function of the angle mod pi (:func:`_pseudo_angle`, one division instead of an arctangent).
The index only sorts and compares them, circularly, so any such function gives the same buckets.
``edges (n_b + 1,)`` bound the pencil buckets; ``span`` scales the position ``rho`` along a bucket's
direction into a key ``bucket + rho / span + 1/2`` that sorts by bucket, then by ``rho``.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numba import prange

__all__ = ["query_frames", "query_frames_parallel", "query_phi", "query_phi_parallel", "bucket_frames",
           "bucket_frames_parallel", "pencil_intervals", "pencil_intervals_parallel", "spread_keys",
           "spread_keys_parallel", "slice_bounds", "slice_bounds_parallel"]


#: The period of the pseudo-angles (the angle's is pi).
PERIOD = 2.0


@nb.njit(inline="always")
def _pseudo_angle(b, a):
    """A strictly increasing function of the angle of ``(a, b)`` taken mod pi, in ``[0, PERIOD)``: 0 along
    ``+a``, 1 along ``+b``, 0 for ``(0, 0)``; NaN stays NaN.
    Replaces ``arctan2(b, a) % pi``, which cost several times as much."""
    if b < 0.0 or (b == 0.0 and a < 0.0):  # the same line: the direction in the upper half-plane
        a, b = -a, -b
    s = abs(a) + b
    if s == 0.0:  # no direction: 0, as arctan2(0, 0)
        return 0.0
    p = 1.0 - a / s
    return 0.0 if p >= PERIOD else p  # (rounding next to the direction -a)


@nb.njit(inline="always")
def _wrap(x):
    """``x % PERIOD`` for ``x`` in ``(-PERIOD, PERIOD)`` (the same value: ``fmod`` of such ``x`` is ``x``),
    without the division of a general modulo."""
    return x + PERIOD if x < 0.0 else x


@nb.njit(inline="always")
def _blocks(n, nblk, c):
    """Items ``[lo, hi)`` of block ``c`` of ``nblk``."""
    return c * n // nblk, (c + 1) * n // nblk


# -- per query -------------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _frames(q0, q1, P, Q, line, is_line, geo):
    for q in range(q0, q1):
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


@nb.njit(cache=True, nogil=True)
def query_frames(P, Q, line, is_line):
    """``geo (N, 7)`` per query (see :mod:`._kernels`): the unit normal ``(n0, n1)`` and offset of the
    segment's line (the epipolar line's with ``is_line``), the unit direction, the middle's position
    along it and the half-length. A zero-length segment (a point) gets the direction ``(1, 0)``."""
    geo = np.empty((P.shape[0], 7))
    _frames(0, P.shape[0], P, Q, line, is_line, geo)
    return geo


@nb.njit(cache=True, nogil=True, parallel=True)
def query_frames_parallel(P, Q, line, is_line, blocks):
    """:func:`query_frames` on threads."""
    n = P.shape[0]
    geo = np.empty((n, 7))
    nblk = blocks
    for c in prange(nblk):
        q0, q1 = _blocks(n, nblk, c)
        _frames(q0, q1, P, Q, line, is_line, geo)
    return geo


@nb.njit(cache=True, nogil=True)
def _phi(r0, r1, line, q_ok, s, c0, c1, u, v, out):
    for r in range(r0, r1):
        q = q_ok[r]
        a, b, c = line[q, 0], line[q, 1], line[q, 2]
        if a == 0.0 and b == 0.0:  # undefined line: the point is the epipole itself
            out[r] = 0.0
            continue
        l0, l1, l2 = a * s, b * s, a * c0 + b * c1 + c
        out[r] = _pseudo_angle(l0 * v[0] + l1 * v[1] + l2 * v[2], l0 * u[0] + l1 * u[1] + l2 * u[2])


@nb.njit(cache=True, nogil=True)
def query_phi(line, q_ok, s, c0, c1, u, v):
    """``(len(q_ok),)`` pencil angle of the epipolar line of each query ``q_ok[r]`` (0 where undefined)."""
    out = np.empty(q_ok.shape[0])
    _phi(np.int64(0), q_ok.shape[0], line, q_ok, s, c0, c1, u, v, out)
    return out


@nb.njit(cache=True, nogil=True, parallel=True)
def query_phi_parallel(line, q_ok, s, c0, c1, u, v, blocks):
    """:func:`query_phi` on threads."""
    n = q_ok.shape[0]
    out = np.empty(n)
    nblk = blocks
    for c in prange(nblk):
        r0, r1 = _blocks(n, nblk, c)
        _phi(r0, r1, line, q_ok, s, c0, c1, u, v, out)
    return out


# -- per bucket of queries -------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _bucket(b, q_sorted, bstart, line, P, Q, pencil, c0, c1, span, tol, directions, klo, khi, hull):
    if pencil:  # the mean direction of the bucket's lines, averaged as doubled angles
        sy = 0.0  # (the direction (-b, a) of a unit line (a, b, c), doubled, is (b^2 - a^2, -2ab))
        sx = 0.0
        for r in range(bstart[b], bstart[b + 1]):
            q = q_sorted[r]
            a, bb = line[q, 0], line[q, 1]
            sy += -2 * a * bb
            sx += bb * bb - a * a
        half = 0.5 * np.arctan2(sy, sx)
        dx, dy = np.cos(half), np.sin(half)
    else:  # pure rotation: one bucket, rho along x
        dx, dy = 1.0, 0.0
    directions[b, 0], directions[b, 1] = dx, dy
    lo_b, hi_b = np.inf, -np.inf
    for r in range(bstart[b], bstart[b + 1]):
        q = q_sorted[r]
        r1 = (P[q, 0] - c0) * dx + (P[q, 1] - c1) * dy
        r2 = (Q[q, 0] - c0) * dx + (Q[q, 1] - c1) * dy
        klo[r] = b + ((min(r1, r2) - tol) / span + 0.5)
        khi[r] = b + ((max(r1, r2) + tol) / span + 0.5)
        lo_b = min(lo_b, klo[r])
        hi_b = max(hi_b, khi[r])
    hull[b, 0], hull[b, 1] = lo_b, hi_b


@nb.njit(cache=True, nogil=True)
def bucket_frames(q_sorted, bstart, line, P, Q, pencil, c0, c1, span, tol):
    """Per bucket (queries ``q_sorted[bstart[b]:bstart[b + 1]]``): its direction ``(n_b, 2)``; per query
    row, the key interval ``[klo, khi]`` of its slice (its segment's ``rho`` interval grown by ``tol``);
    per bucket, the ``hull (n_b, 2)`` of those intervals (no slice of the bucket reaches past it)."""
    n_b = bstart.shape[0] - 1
    directions, hull = np.empty((n_b, 2)), np.empty((n_b, 2))
    klo, khi = np.empty(q_sorted.shape[0]), np.empty(q_sorted.shape[0])
    for b in range(n_b):
        _bucket(np.int64(b), q_sorted, bstart, line, P, Q, pencil, c0, c1, span, tol, directions, klo, khi, hull)
    return directions, klo, khi, hull


@nb.njit(cache=True, nogil=True, parallel=True)
def bucket_frames_parallel(q_sorted, bstart, line, P, Q, pencil, c0, c1, span, tol, blocks):
    """:func:`bucket_frames` on threads."""
    n_b = bstart.shape[0] - 1
    directions, hull = np.empty((n_b, 2)), np.empty((n_b, 2))
    klo, khi = np.empty(q_sorted.shape[0]), np.empty(q_sorted.shape[0])
    for b in prange(n_b):
        _bucket(np.int64(b), q_sorted, bstart, line, P, Q, pencil, c0, c1, span, tol, directions, klo, khi, hull)
    return directions, klo, khi, hull


# -- per keypoint -------------------------------------------------------------------------------------
@nb.njit(inline="always")
def _pencil_angle(e, u, v, c0, c1, s, x0, x1):
    """Pseudo-angle of the line through the epipole ``e`` and pixel ``(x0, x1)``, in the pencil basis
    ``(u, v)``, and the first two coefficients of that line (normalised coordinates)."""
    y0 = (x0 - c0) / s
    y1 = (x1 - c1) / s
    l0 = e[1] - e[2] * y1
    l1 = e[2] * y0 - e[0]
    l2 = e[0] * y1 - e[1] * y0
    a = l0 * u[0] + l1 * u[1] + l2 * u[2]
    b = l0 * v[0] + l1 * v[1] + l2 * v[2]
    return _pseudo_angle(b, a), l0, l1


@nb.njit(cache=True, nogil=True)
def _intervals(k0, k1, e, u, v, c0, c1, s, tol, y, lo, width):
    for k in range(k0, k1):
        phi, l0, l1 = _pencil_angle(e, u, v, c0, c1, s, y[k, 0], y[k, 1])
        h = max(np.hypot(l0, l1), 1e-300)
        # tol / r (r infinite for an epipole at infinity)
        r = np.hypot(e[0] - (y[k, 0] - c0) / s * e[2], e[1] - (y[k, 1] - c1) / s * e[2])
        ratio = (tol / s) * abs(e[2]) / r if r > 0 else np.inf
        if ratio >= 1 - 1e-9:  # y is within tol of the epipole: every line
            lo[k] = 0.0
            width[k] = PERIOD
            continue
        tau = tol / np.sqrt(max(1.0 - ratio * ratio, 1e-18)) * (1 + 1e-9) + 1e-9
        a, _, _ = _pencil_angle(e, u, v, c0, c1, s, y[k, 0] - tau * l0 / h, y[k, 1] - tau * l1 / h)
        b, _, _ = _pencil_angle(e, u, v, c0, c1, s, y[k, 0] + tau * l0 / h, y[k, 1] + tau * l1 / h)
        w = _wrap(b - a)  # (pseudo-angles are in [0, PERIOD))
        if _wrap(phi - a) > w:  # the arc from a to b must contain phi; otherwise it is the other one
            lo[k] = b
            width[k] = PERIOD - w
        else:
            lo[k] = a
            width[k] = w


@nb.njit(cache=True, nogil=True)
def pencil_intervals(e, u, v, c0, c1, s, tol, y):
    """For each pixel ``y (N, 2)``: the interval ``[lo, lo + width]`` (mod ``PERIOD``) of pencil
    pseudo-angles of the lines through the epipole that pass within ``tol`` of it (``width = PERIOD``:
    all of them).

    The lines through the epipole at distance ``tol`` from ``y`` touch the circle of radius ``tol``
    around it; they are found as the lines through the points ``y +- tau n``, with ``n`` the normal
    of the line through ``y`` and ``tau = tol / sqrt(1 - (tol / r)^2)``, ``r`` the distance from ``y``
    to the epipole. Both are grown slightly, for rounding.
    """
    lo, width = np.empty(y.shape[0]), np.empty(y.shape[0])
    _intervals(np.int64(0), y.shape[0], e, u, v, c0, c1, s, tol, y, lo, width)
    return lo, width


@nb.njit(cache=True, nogil=True, parallel=True)
def pencil_intervals_parallel(e, u, v, c0, c1, s, tol, y, blocks):
    """:func:`pencil_intervals` on threads."""
    n = y.shape[0]
    lo, width = np.empty(n), np.empty(n)
    nblk = blocks
    for c in prange(nblk):
        k0, k1 = _blocks(n, nblk, c)
        _intervals(k0, k1, e, u, v, c0, c1, s, tol, y, lo, width)
    return lo, width


#: Cells of the lookup grid over ``[0, PERIOD]`` per pencil bucket (:func:`_grid`).
GRID_PER_BUCKET = 4


@nb.njit(cache=True, nogil=True)
def _grid(edges):
    """``grid[c]``: the number of ``edges`` at or below ``c PERIOD / G`` (``G = GRID_PER_BUCKET n_b``), so that
    :func:`_ranges` searches a few edges instead of all of them."""
    g = GRID_PER_BUCKET * (edges.shape[0] - 1)
    return np.searchsorted(edges, np.arange(g + 1) * (PERIOD / g), side="right")


@nb.njit(cache=True, nogil=True)
def _bisect(a, lo, hi, x, right):
    """``lo +`` ``np.searchsorted(a[lo:hi], x, side)`` for sorted ``a``: the first index in ``[lo, hi)``
    whose value is above ``x`` (``right``) or at or above it (else); ``hi`` when there is none."""
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < x or (right and a[mid] == x):
            lo = mid + 1
        else:
            hi = mid
    return lo


@nb.njit(cache=True, nogil=True)
def _ranges(k0, k1, lo, width, edges, grid, ranges):
    """Keypoints ``k0:k1``: the buckets ``ranges[k, 0]..ranges[k, 1]`` that the angle interval
    ``[lo, lo + width]`` overlaps and, where it passes ``PERIOD``, ``0..ranges[k, 2]`` (up to, not into,
    those already covered; -1 without).

    Each bucket is ``np.searchsorted(edges, x, side="right") - 1``, as a binary search between the grid
    cells one either side of ``x``'s (so that rounding in the cell's number cannot miss)."""
    n_b = edges.shape[0] - 1
    g = grid.shape[0] - 1
    scale = g / PERIOD
    for k in range(k0, k1):
        h = min(lo[k] + width[k], lo[k] + PERIOD)
        for j in range(3):
            if j == 0:
                x = lo[k]
            elif j == 1:
                x = min(h, PERIOD)
            elif h > PERIOD:
                x = h - PERIOD
            else:
                ranges[k, 2] = -1
                break
            f = x * scale
            if f >= 0.0:
                c = int(f) if f < g else g - 1
                a, z = grid[max(c - 1, 0)], grid[min(c + 2, g)]
            else:  # NaN
                a, z = 0, edges.shape[0]
            ranges[k, j] = min(max(_bisect(edges, a, z, x, True) - 1, 0), n_b - 1)
        if h > PERIOD:
            ranges[k, 2] = min(ranges[k, 2], ranges[k, 0] - 1)


@nb.njit(cache=True, nogil=True)
def _spread(k0, k1, ranges, y, directions, c0, c1, span, hull, first, bucket, key, count):
    """Keypoints ``k0:k1``: with ``count``, the number of their (bucket, key) entries into ``first[k]``;
    else those entries from position ``first[k]``. An entry (keypoint ``k`` in a bucket ``b`` of its
    ``ranges[k]``) is kept only if its key lies in the bucket's hull.

    (The entry is computed here, not in a helper taking the arrays: such a call cost about 30 ns per
    entry, eight times the arithmetic.)"""
    for k in range(k0, k1):
        b0, b1, w1 = ranges[k, 0], ranges[k, 1], ranges[k, 2]
        m = 0 if count else first[k]
        x0, x1 = y[k, 0] - c0, y[k, 1] - c1
        n0 = b1 - b0 + 1
        for r in range(n0 + w1 + 1):  # buckets b0..b1, then 0..w1
            b = b0 + r if r < n0 else r - n0
            kb = b + ((x0 * directions[b, 0] + x1 * directions[b, 1]) / span + 0.5)
            if kb >= hull[b, 0] and kb <= hull[b, 1]:
                if not count:
                    bucket[m], key[m] = b, kb
                m += 1
        if count:
            first[k] = m


@nb.njit(cache=True, nogil=True)
def _prefix(first):
    """In place: counts ``first[0:n]`` -> starts ``first[0:n + 1]`` (``first[n]``: the total)."""
    acc = 0
    for k in range(first.shape[0]):
        c = first[k]
        first[k] = acc
        acc += c
    return acc


#: Sort cells per bucket, per entry of the bucket on average (:func:`_by_cell`).
CELLS_PER_ENTRY = 1
#: Largest cell sorted by insertion (:func:`_sort_cells`); larger ones (keys bunched in one place) by merge sort.
INSERTION_MAX = 32


@nb.njit(cache=True, nogil=True)
def _by_cell(first, bucket, key, n_b):
    """Counting sort of the entries (keypoint-major) by bucket, then by the cell of their key in the bucket,
    stable: ``(t_c, key_c, cstart, per)``, cell ``c`` (of bucket ``c // per``) being ``cstart[c]:cstart[c + 1]``.

    A key ``b + f`` of bucket ``b`` goes to cell ``b per + floor(f per)`` (clamped to the bucket's cells): a
    non-decreasing function of the key within the bucket, so sorting each cell by key (stably,
    :func:`_sort_cells`) sorts the bucket as a stable sort by key would. ``per`` gives about
    ``CELLS_PER_ENTRY`` cells per entry of a bucket."""
    total = bucket.shape[0]
    per = max(1, (CELLS_PER_ENTRY * total) // max(n_b, 1))
    cstart = np.zeros(n_b * per + 1, dtype=np.int64)
    cell = np.empty(total, dtype=np.int64)
    for m in range(total):
        b = bucket[m]
        f = (key[m] - b) * per
        c = b * per + (0 if f < 0 else (per - 1 if f >= per - 1 else int(f)))
        cell[m] = c
        cstart[c + 1] += 1
    for c in range(n_b * per):
        cstart[c + 1] += cstart[c]
    pos = cstart[:-1].copy()
    t_c = np.empty(total, dtype=np.int64)
    key_c = np.empty(total)
    n = first.shape[0] - 1
    for k in range(n):
        for m in range(first[k], first[k + 1]):
            p = pos[cell[m]]
            t_c[p], key_c[p] = k, key[m]
            pos[cell[m]] = p + 1
    return t_c, key_c, cstart, per


@nb.njit(cache=True, nogil=True)
def _sort_cells(c0, c1, cstart, t_c, key_c):
    """In place: cells ``c0:c1`` each sorted by key, stably (equal keys keep their keypoint order)."""
    for c in range(c0, c1):
        a, z = cstart[c], cstart[c + 1]
        if z - a <= INSERTION_MAX:
            for m in range(a + 1, z):
                kk, tt = key_c[m], t_c[m]
                r = m
                while r > a and key_c[r - 1] > kk:
                    key_c[r], t_c[r] = key_c[r - 1], t_c[r - 1]
                    r -= 1
                key_c[r], t_c[r] = kk, tt
        else:
            o = np.argsort(key_c[a:z], kind="mergesort")
            ks, ts = key_c[a:z][o], t_c[a:z][o]
            key_c[a:z], t_c[a:z] = ks, ts


@nb.njit(cache=True, nogil=True)
def spread_keys(lo, width, edges, y, directions, c0, c1, span, hull):
    """Each keypoint into every bucket its angle interval ``[lo, lo + width]`` overlaps (``lo + width``
    may pass ``PERIOD``: the rest continues at 0), with its key in that bucket; sorted by key:
    ``(t_sorted, key_sorted, bstart)``, bucket ``b`` being ``bstart[b]:bstart[b + 1]``."""
    n = lo.shape[0]
    first = np.empty(n + 1, dtype=np.int64)
    ranges = np.empty((n, 3), dtype=np.int64)
    _ranges(np.int64(0), n, lo, width, edges, _grid(edges), ranges)
    no_i, no_f = np.empty(0, np.int64), np.empty(0)
    _spread(np.int64(0), n, ranges, y, directions, c0, c1, span, hull, first, no_i, no_f, True)
    total = _prefix(first[:n])
    first[n] = total
    bucket, key = np.empty(total, np.int64), np.empty(total)
    _spread(np.int64(0), n, ranges, y, directions, c0, c1, span, hull, first, bucket, key, False)
    t_sorted, key_sorted, cstart, per = _by_cell(first, bucket, key, edges.shape[0] - 1)
    _sort_cells(np.int64(0), cstart.shape[0] - 1, cstart, t_sorted, key_sorted)
    return t_sorted, key_sorted, cstart[::per].copy()


@nb.njit(cache=True, nogil=True, parallel=True)
def spread_keys_parallel(lo, width, edges, y, directions, c0, c1, span, hull, blocks):
    """:func:`spread_keys` on threads (the counting sort between the passes is serial)."""
    n = lo.shape[0]
    nblk = blocks
    first = np.empty(n + 1, dtype=np.int64)
    grid, ranges = _grid(edges), np.empty((n, 3), dtype=np.int64)
    no_i, no_f = np.empty(0, np.int64), np.empty(0)
    for c in prange(nblk):
        k0, k1 = _blocks(n, nblk, c)
        _ranges(k0, k1, lo, width, edges, grid, ranges)
        _spread(k0, k1, ranges, y, directions, c0, c1, span, hull, first, no_i, no_f, True)
    total = _prefix(first[:n])
    first[n] = total
    bucket, key = np.empty(total, np.int64), np.empty(total)
    for c in prange(nblk):
        k0, k1 = _blocks(n, nblk, c)
        _spread(k0, k1, ranges, y, directions, c0, c1, span, hull, first, bucket, key, False)
    t_sorted, key_sorted, cstart, per = _by_cell(first, bucket, key, edges.shape[0] - 1)
    cells = cstart.shape[0] - 1
    for c in prange(nblk):
        a, z = _blocks(cells, nblk, c)
        _sort_cells(a, z, cstart, t_sorted, key_sorted)
    return t_sorted, key_sorted, cstart[::per].copy()


# -- per query row -----------------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _slices(r0, r1, key_t, bstart, qb, klo, khi, start, stop):
    """``start[r]``: the first key of bucket ``qb[r]`` at or above ``klo[r]`` (``np.searchsorted`` left);
    ``stop[r]``: the first above ``khi[r]`` (right). (:func:`_bisect`: ``np.searchsorted`` on a slice cost a
    fifth more at 10k queries.)"""
    for r in range(r0, r1):
        a, z = bstart[qb[r]], bstart[qb[r] + 1]
        start[r] = _bisect(key_t, a, z, klo[r], False)
        stop[r] = _bisect(key_t, start[r], z, khi[r], True)  # (khi >= klo: not before start)


@nb.njit(cache=True, nogil=True)
def slice_bounds(key_t, bstart, qb, klo, khi):
    """``(start, stop)`` per query row ``r``: the keys of its bucket ``qb[r]`` in ``[klo[r], khi[r]]``."""
    n = qb.shape[0]
    start, stop = np.empty(n, np.int64), np.empty(n, np.int64)
    _slices(np.int64(0), n, key_t, bstart, qb, klo, khi, start, stop)
    return start, stop


@nb.njit(cache=True, nogil=True, parallel=True)
def slice_bounds_parallel(key_t, bstart, qb, klo, khi, blocks):
    """:func:`slice_bounds` on threads."""
    n = qb.shape[0]
    start, stop = np.empty(n, np.int64), np.empty(n, np.int64)
    nblk = blocks
    for c in prange(nblk):
        r0, r1 = _blocks(n, nblk, c)
        _slices(r0, r1, key_t, bstart, qb, klo, khi, start, stop)
    return start, stop
