"""Compiled loops (numba) of :mod:`episeg_cv.geometry`: the segments and the clipped lines, one pass per point.

The same float64 operations as the array formulation in :mod:`episeg_cv.geometry` (docs/geometry.md), in
the order written, without fast-math and without fused multiply-adds, with numpy's semantics for
division by zero (inf or NaN, no exception) and NaN-propagating maximum and minimum. Each point is
independent, so the serial and the parallel variants (``name`` / ``name_parallel``, chosen by
:func:`episeg_cv.threads.run`) give the same bits.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numba import prange

__all__ = ["segments", "segments_parallel", "line_clip", "line_clip_parallel"]


@nb.njit(inline="always", error_model="numpy")
def _max(x, y):
    """numpy's maximum: NaN if either is NaN."""
    if x != x or y != y:
        return np.nan
    return x if x >= y else y


@nb.njit(inline="always", error_model="numpy")
def _min(x, y):
    if x != x or y != y:
        return np.nan
    return x if x <= y else y


@nb.njit(inline="always", error_model="numpy")
def _constraint(P, Q, lo, hi, infeasible):
    """Clip ``s`` to ``P + s Q >= 0``: a lower bound where ``Q > 0``, an upper one where ``Q < 0``."""
    r = -P / Q
    lo = _max(lo, r if Q > 0 else -np.inf)
    hi = _min(hi, r if Q < 0 else np.inf)
    return lo, hi, infeasible or (Q == 0 and P < 0)


@nb.njit(inline="always")
def _blocks(n, nblk, c):
    return c * n // nblk, (c + 1) * n // nblk


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _segments(k0, k1, x1, H, b, zmin, zmax, rect, eps, start, end, valid, line, p_inf, a):
    """Points ``k0:k1``. ``zmin`` / ``zmax`` have length 1 (one range for all) or ``N``: read with a stride
    of 0 or 1, so that there is no branch on their shape."""
    szn = 1 if zmin.shape[0] > 1 else 0
    szx = 1 if zmax.shape[0] > 1 else 0
    xmin, xmax, ymin, ymax = rect[0], rect[1], rect[2], rect[3]
    b0, b1, b2 = b[0], b[1], b[2]
    for k in range(k0, k1):
        x, y = x1[k, 0], x1[k, 1]
        a0 = x * H[0, 0] + y * H[0, 1] + H[0, 2]  # a = H [x1; 1], the homogeneous p_inf
        a1 = x * H[1, 0] + y * H[1, 1] + H[1, 2]
        a2 = x * H[2, 0] + y * H[2, 1] + H[2, 2]
        a[k, 0], a[k, 1], a[k, 2] = a0, a1, a2
        zn, zx = zmin[k * szn], zmax[k * szx]
        u1, u2, u3 = zn * a0 + b0, zn * a1 + b1, zn * a2 + b2  # U = zmin a + b
        fin = np.isfinite(zx)
        zf = zx if fin else 0.0
        v1 = zf * a0 + b0 if fin else a0  # V = zmax a + b, or a when zmax = inf
        v2 = zf * a1 + b1 if fin else a1
        v3 = zf * a2 + b2 if fin else a2
        c = eps * (np.sqrt((u1 * u1 + u2 * u2) + u3 * u3) + np.sqrt((v1 * v1 + v2 * v2) + v3 * v3))
        d1, d2, d3 = v1 - u1, v2 - u2, v3 - u3
        lo, hi, infeasible = 0.0, 1.0, False
        lo, hi, infeasible = _constraint(u1 - xmin * u3, d1 - xmin * d3, lo, hi, infeasible)
        lo, hi, infeasible = _constraint(xmax * u3 - u1, xmax * d3 - d1, lo, hi, infeasible)
        lo, hi, infeasible = _constraint(u2 - ymin * u3, d2 - ymin * d3, lo, hi, infeasible)
        lo, hi, infeasible = _constraint(ymax * u3 - u2, ymax * d3 - d2, lo, hi, infeasible)
        lo, hi, infeasible = _constraint(u3 - c, d3, lo, hi, infeasible)  # cheirality, w3 >= c
        ok = lo <= hi and not infeasible
        valid[k] = ok
        w1, w2, w3 = u1 + lo * d1, u2 + lo * d2, u3 + lo * d3
        e1, e2, e3 = u1 + hi * d1, u2 + hi * d2, u3 + hi * d3
        start[k, 0] = w1 / w3 if ok else np.nan
        start[k, 1] = w2 / w3 if ok else np.nan
        end[k, 0] = e1 / e3 if ok else np.nan
        end[k, 1] = e2 / e3 if ok else np.nan
        l0 = b1 * a2 - b2 * a1  # the line b x a, normalised
        l1 = b2 * a0 - b0 * a2
        l2 = b0 * a1 - b1 * a0
        nrm = np.sqrt(l0 * l0 + l1 * l1)  # not hypot: 1.4x faster; overflows only past 1e154
        nrm = nrm if nrm > 0 else np.nan
        line[k, 0], line[k, 1], line[k, 2] = l0 / nrm, l1 / nrm, l2 / nrm
        p_inf[k, 0], p_inf[k, 1] = a0 / a2, a1 / a2


@nb.njit(cache=True, nogil=True)
def segments(x1, H, b, zmin, zmax, rect, eps, start, end, valid, line, p_inf, a):
    """Fill ``start, end, valid, line, p_inf, a`` for the points ``x1 (N, 2)`` of image 1 (see
    :meth:`episeg_cv.TwoViewGeometry.segments`): ``H`` the infinite homography, ``b`` the homogeneous
    epipole, ``zmin`` / ``zmax`` ``(1,)`` or ``(N,)``, ``rect = (xmin, xmax, ymin, ymax)``, ``eps`` the
    relative cheirality tolerance. The caller allocates the outputs with numpy, whose large arrays get
    transparent huge pages: first-touch page faults of numba's allocations cost as much as the arithmetic."""
    _segments(np.int64(0), x1.shape[0], x1, H, b, zmin, zmax, rect, eps, start, end, valid, line, p_inf, a)


@nb.njit(cache=True, nogil=True, parallel=True)
def segments_parallel(x1, H, b, zmin, zmax, rect, eps, start, end, valid, line, p_inf, a, blocks):
    """:func:`segments` on threads."""
    n = x1.shape[0]
    nblk = blocks
    for c in prange(nblk):
        k0, k1 = _blocks(n, nblk, c)
        _segments(k0, k1, x1, H, b, zmin, zmax, rect, eps, start, end, valid, line, p_inf, a)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _line_clip(k0, k1, line, rect, start, end):
    """Lines ``k0:k1``: the whole line ``p0 + s d``, ``s`` in R, clipped to the rectangle (NaN if it misses
    or is undefined)."""
    xmin, xmax, ymin, ymax = rect[0], rect[1], rect[2], rect[3]
    for k in range(k0, k1):
        la, lb, lc = line[k, 0], line[k, 1], line[k, 2]
        p0, p1 = -lc * la, -lc * lb  # the foot of the origin's perpendicular
        d0, d1 = -lb, la
        finite = np.isfinite(la) and np.isfinite(lb) and np.isfinite(lc)
        # two points of the line, homogeneous with w = 1 (zeros where undefined, as nan_to_num)
        u1, u2 = (p0, p1) if finite else (0.0, 0.0)
        v1, v2 = (p0 + d0, p1 + d1) if finite else (0.0, 0.0)
        e1, e2 = v1 - u1, v2 - u2
        lo, hi, infeasible = -np.inf, np.inf, False
        lo, hi, infeasible = _constraint(u1 - xmin * 1.0, e1 - xmin * 0.0, lo, hi, infeasible)
        lo, hi, infeasible = _constraint(xmax * 1.0 - u1, xmax * 0.0 - e1, lo, hi, infeasible)
        lo, hi, infeasible = _constraint(u2 - ymin * 1.0, e2 - ymin * 0.0, lo, hi, infeasible)
        lo, hi, infeasible = _constraint(ymax * 1.0 - u2, ymax * 0.0 - e2, lo, hi, infeasible)
        ok = lo <= hi and not infeasible and finite
        start[k, 0] = p0 + lo * d0 if ok else np.nan
        start[k, 1] = p1 + lo * d1 if ok else np.nan
        end[k, 0] = p0 + hi * d0 if ok else np.nan
        end[k, 1] = p1 + hi * d1 if ok else np.nan


@nb.njit(cache=True, nogil=True)
def line_clip(line, rect, start, end):
    """Fill ``start, end (N, 2)`` with the unit lines ``line (N, 3)`` clipped to ``rect``."""
    _line_clip(np.int64(0), line.shape[0], line, rect, start, end)


@nb.njit(cache=True, nogil=True, parallel=True)
def line_clip_parallel(line, rect, start, end, blocks):
    """:func:`line_clip` on threads."""
    n = line.shape[0]
    nblk = blocks
    for c in prange(nblk):
        k0, k1 = _blocks(n, nblk, c)
        _line_clip(k0, k1, line, rect, start, end)
