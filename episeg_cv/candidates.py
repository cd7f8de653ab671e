"""Candidate search: which keypoints of image 2 lie near each query's segment (or line).

No ``N1 x N2`` array is formed. All epipolar lines of image 2 pass through the
epipole, so they form a *pencil*; each line has a pencil angle ``phi``. The
index works in two stages:

1. **Pencil buckets.** Queries are sorted by ``phi`` and cut into buckets of
   about equal size. A keypoint ``y`` of image 2 can only be within ``tol`` of
   lines whose ``phi`` lies in a small interval (the lines through the
   epipole that touch the disk of radius ``tol`` around ``y``); it is put in
   every bucket that interval overlaps.
2. **Blocks along the lines.** Inside a bucket, positions along the lines are
   measured by ``rho``, the projection on the bucket's mean line direction.
   Projection is 1-Lipschitz, so a point within ``tol`` of a segment has
   ``rho`` within ``tol`` of the segment's ``rho`` interval. Queries are
   grouped by their interval, and each group gets one contiguous slice of the
   bucket's keypoints sorted by ``rho``.

Each block, ``(queries, keypoints)``, is small and dense, which suits BLAS for
the descriptor distances. The exact geometric test, distance to the segment
(or line) at most ``tol``, is then applied inside the block by :meth:`mask`.
The line and the segment use the same index; the segment's shorter ``rho``
intervals give smaller blocks. The pencil angle is built from an orthonormal
basis of the lines through the (unit) homogeneous epipole, so an epipole at
infinity (``t_3 = 0``) or very far needs no special case. For pure rotation
(``t = 0``) there is no pencil; every segment is a point and the index falls
back to one bucket with ``rho`` along ``x``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._validation import as_nonnegative, as_points
from .geometry import EpipolarSegments, TwoViewGeometry

__all__ = ["CandidateIndex", "CONSTRAINTS"]

#: The known constraints. ``"none"`` is handled by the matcher, not here.
CONSTRAINTS = ("segment", "line", "none")


def check_constraint(constraint) -> str:
    if not isinstance(constraint, str) or constraint not in CONSTRAINTS:
        raise ValueError(f"constraint must be one of {CONSTRAINTS}, got {constraint!r}")
    return constraint


@dataclass(frozen=True)
class Block:
    """A group of queries and the keypoints of image 2 they must be compared with."""

    queries: np.ndarray  # (g,) intp indices into points1
    train: np.ndarray  # (m,) intp indices into points2


class CandidateIndex:
    """Spatial index of the keypoints of image 2 for the segments (or lines) of image-1 queries.

    Parameters
    ----------
    geometry : TwoViewGeometry
        Known pose; ``X2 = R @ X1 + t``.
    points1 : (N1, 2) array_like
        Query pixels in image 1.
    points2 : (N2, 2) array_like
        Keypoint pixels in image 2.
    tol : float, optional
        Pixel tolerance: a candidate is within ``tol`` of the segment (or line).
    depth_range : (zmin, zmax), optional
        Passed to :meth:`TwoViewGeometry.segments` (ignored by ``"line"``).
    constraint : {"segment", "line"}
        Which region the candidates must lie in.
    group_size : int, optional
        Queries per block. Larger blocks mean fewer Python steps but more
        wasted pairs.
    bucket_size : int, optional
        Queries per pencil bucket (each bucket is cut into blocks).

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv import TwoViewGeometry
    >>> K = [[100, 0, 50], [0, 100, 50], [0, 0, 1]]
    >>> g = TwoViewGeometry(K, K, np.eye(3), [-1, 0, 0], image_size1=(100, 100), image_size2=(100, 100))
    >>> p1 = [[50.0, 50.0]]                           # segment: the row y = 50, left of x = 50
    >>> p2 = [[30.0, 50.5], [70.0, 50.0], [30.0, 60.0]]
    >>> CandidateIndex(g, p1, p2, tol=2.0).pairs().tolist()
    [[0, 0]]
    >>> CandidateIndex(g, p1, p2, tol=2.0, constraint="line").pairs().tolist()
    [[0, 0], [0, 1]]
    """

    def __init__(self, geometry: TwoViewGeometry, points1, points2, *, tol: float = 2.0,
                 depth_range=(0.0, np.inf), constraint: str = "segment", group_size: int = 32,
                 bucket_size: int = 64):
        if not isinstance(geometry, TwoViewGeometry):
            raise TypeError(f"geometry must be a TwoViewGeometry, got {type(geometry).__name__}")
        constraint = check_constraint(constraint)
        if constraint == "none":
            raise ValueError("CandidateIndex needs constraint 'segment' or 'line'; 'none' has no index")
        self.geometry = geometry
        self.points1 = as_points(points1, "points1")
        self.points2 = as_points(points2, "points2")
        self.tol = as_nonnegative(tol, "tol")
        self.constraint = constraint
        #: The segments of the queries, clipped to image 2 grown by ``tol``.
        self.segments: EpipolarSegments = geometry.segments(self.points1, depth_range, margin=self.tol)
        seg = self.segments
        if constraint == "segment":
            self._P, self._Q, self._ok = seg.start, seg.end, seg.valid.copy()
        else:
            self._P, self._Q = seg.line_start, seg.line_end
            self._ok = np.all(np.isfinite(seg.line_start), axis=1)
        self._P = np.where(self._ok[:, None], self._P, 0.0)
        self._Q = np.where(self._ok[:, None], self._Q, 0.0)
        self._line = np.where(np.isfinite(seg.line), seg.line, 0.0)
        # a local frame per query: unit normal n and direction d of its segment (or line), so that a
        # point y is at offset n.y - off_n across and s = d.y - off_d along, with 0 <= s <= length
        D = self._Q - self._P
        length = np.hypot(D[:, 0], D[:, 1])
        d = np.where(length[:, None] > 0, D / np.where(length > 0, length, 1.0)[:, None], [1.0, 0.0])
        n = np.column_stack([-d[:, 1], d[:, 0]])
        if constraint == "line":
            n, off_n = self._line[:, :2], -self._line[:, 2]
        else:
            off_n = (n * self._P).sum(1)
        # per query (one extra last row, selected by the padding index -1, that is never a candidate):
        # across = n.y - off_n, and along = |d.y - mid| - half, with mid the segment's middle and half its
        # half-length, so the distance to the segment is hypot(across, max(along, 0))
        far = 1e12
        self._n0, self._n1 = np.r_[n[:, 0], 0.0], np.r_[n[:, 1], 0.0]
        self._off_n = np.r_[off_n, far]
        self._d0, self._d1 = np.r_[d[:, 0], 0.0], np.r_[d[:, 1], 0.0]
        self._half = np.r_[0.5 * length, 0.0]
        self._mid = np.r_[(d * self._P).sum(1) + 0.5 * length, 0.0]
        self._y0 = np.r_[self.points2[:, 0], far]
        self._y1 = np.r_[self.points2[:, 1], far]
        self._tol2 = self.tol * self.tol * (1 + 1e-9) + 1e-12
        self._groups = self._build(max(int(group_size), 1), max(int(bucket_size), 1))

    @property
    def blocks(self) -> list[Block]:
        """The blocks, ``(queries, keypoints)`` to compare, as a list."""
        gr = self._groups
        return [Block(gr.q_sorted[a:b], gr.t_sorted[c:d])
                for a, b, c, d in zip(gr.q_start, gr.q_stop, gr.t_start, gr.t_stop)]

    # -- the exact test ------------------------------------------------------------
    def mask(self, queries: np.ndarray, train: np.ndarray) -> np.ndarray:
        """``(len(queries), len(train))`` bool: is ``points2[train[j]]`` a candidate of ``queries[i]``.

        Segment: distance to the segment (a capsule) at most ``tol``. Line:
        distance to the line at most ``tol``. Queries must have a valid
        segment (those in :attr:`blocks` do).
        """
        return self.mask_batch(np.asarray(queries)[None], np.asarray(train)[None])[0]

    def pairs(self) -> np.ndarray:
        """All candidate pairs ``(K, 2)`` of ``(query, train)`` indices, sorted by query then train."""
        out = [np.zeros((0, 2), dtype=np.intp)]
        for blk in self.blocks:
            i, j = np.nonzero(self.mask(blk.queries, blk.train))
            out.append(np.column_stack([blk.queries[i], blk.train[j]]))
        pairs = np.concatenate(out)
        return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]

    def candidate_counts(self) -> np.ndarray:
        """(N1,) number of candidates of each query."""
        counts = np.zeros(len(self.points1), dtype=np.intp)
        for blk in self.blocks:
            counts[blk.queries] = self.mask(blk.queries, blk.train).sum(1)
        return counts

    # -- building ------------------------------------------------------------------
    def _pencil(self):
        """Orthonormal pencil basis in normalised image-2 coordinates, or None for ``t = 0``."""
        w, h = self.geometry.image_size2
        self._c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
        self._s = float(np.hypot(w, h))
        b = self.geometry.epipole_homogeneous
        e = np.array([(b[0] - self._c[0] * b[2]) / self._s, (b[1] - self._c[1] * b[2]) / self._s, b[2]])
        ne = np.linalg.norm(e)
        if ne == 0:
            return None
        e = e / ne
        u = np.cross(e, np.eye(3)[np.argmin(np.abs(e))])
        u /= np.linalg.norm(u)
        return e, u, np.cross(e, u)

    def _phi_of_points(self, e, u, v, y):
        """Pencil angle in ``[0, pi)`` of the line through the epipole and each pixel ``y``, and that line.

        The line is ``l = e x (yn, 1)`` in normalised coordinates ``yn = (y - c) / s``.
        """
        y0 = (y[:, 0] - self._c[0]) / self._s
        y1 = (y[:, 1] - self._c[1]) / self._s
        l0 = e[1] - e[2] * y1
        l1 = e[2] * y0 - e[0]
        l2 = e[0] * y1 - e[1] * y0
        a = l0 * u[0] + l1 * u[1] + l2 * u[2]
        b = l0 * v[0] + l1 * v[1] + l2 * v[2]
        return np.mod(np.arctan2(b, a), np.pi), (l0, l1)

    def _build(self, group_size: int, bucket_size: int) -> "_Groups":
        n2 = len(self.points2)
        q_ok = np.flatnonzero(self._ok)
        if n2 == 0 or q_ok.size == 0:
            return _Groups.empty()
        pencil = self._pencil()
        y = self.points2
        if pencil is None:  # pure rotation: every segment is a point; one bucket, rho along x
            q_phi = np.zeros(q_ok.size)
            edges = np.array([0.0, np.pi])
            t_idx, t_bucket = np.arange(n2), np.zeros(n2, dtype=np.intp)
            directions = np.array([[1.0, 0.0]])
        else:
            e, u, v = pencil
            # queries: the pencil angle of their epipolar line, taken in normalised coordinates
            line = self._line[q_ok]
            ln = np.column_stack([line[:, 0] * self._s, line[:, 1] * self._s,
                                  line[:, 0] * self._c[0] + line[:, 1] * self._c[1] + line[:, 2]])
            q_phi = np.mod(np.arctan2(ln @ v, ln @ u), np.pi)
            q_phi[~np.any(line != 0, axis=1)] = 0.0  # undefined line: the point is the epipole itself
            n_buckets = max(1, int(np.ceil(q_ok.size / bucket_size)))
            cuts = np.sort(q_phi)[(np.arange(1, n_buckets) * q_ok.size) // n_buckets]
            edges = np.concatenate([[0.0], cuts, [np.pi]])
            # keypoints: the interval of pencil angles of lines within tol of them
            phi_y, (l0, l1) = self._phi_of_points(e, u, v, y)
            normal = np.column_stack([l0, l1]) / np.maximum(np.hypot(l0, l1), 1e-300)[:, None]
            with np.errstate(divide="ignore", invalid="ignore"):
                # tol / r, with r the pixel distance from y to the epipole (0 at infinity)
                ratio = (self.tol / self._s) * abs(e[2]) / np.hypot(e[0] - (y[:, 0] - self._c[0]) / self._s * e[2],
                                                                    e[1] - (y[:, 1] - self._c[1]) / self._s * e[2])
            ratio = np.where(np.isfinite(ratio), ratio, np.inf)
            everywhere = ratio >= 1 - 1e-9
            tau = self.tol / np.sqrt(np.maximum(1.0 - ratio**2, 1e-18)) * (1 + 1e-9) + 1e-9
            tau = np.where(everywhere, 0.0, tau)
            lo, _ = self._phi_of_points(e, u, v, y - tau[:, None] * normal)
            hi, _ = self._phi_of_points(e, u, v, y + tau[:, None] * normal)
            # the arc from lo to hi (mod pi) must contain phi_y; otherwise it is the other one
            width = np.mod(hi - lo, np.pi)
            swap = np.mod(phi_y - lo, np.pi) > width
            lo, width = np.where(swap, hi, lo), np.where(swap, np.pi - width, width)
            lo = np.where(everywhere, 0.0, lo)
            width = np.where(everywhere, np.pi, width)
            t_idx, t_bucket = _spread(lo, lo + width, edges)
            # one direction per bucket: the mean direction of its lines (doubled-angle average)
            n_b = len(edges) - 1
            q_bucket = np.clip(np.searchsorted(edges, q_phi, side="right") - 1, 0, n_b - 1)
            ang2 = 2 * np.arctan2(line[:, 0], -line[:, 1])  # direction (-b, a) of each line
            half = 0.5 * np.arctan2(np.bincount(q_bucket, np.sin(ang2), n_b), np.bincount(q_bucket, np.cos(ang2), n_b))
            directions = np.column_stack([np.cos(half), np.sin(half)])
        n_b = len(edges) - 1
        if pencil is None:
            q_bucket = np.zeros(q_ok.size, dtype=np.intp)
        # rho: position along the bucket direction, scaled into [0, 1) so that (bucket + rho) sorts
        span = 2.0 * (self._s + 2 * self.tol + 1.0)

        def rho(points, bucket):
            return (points[:, 0] - self._c[0]) * directions[bucket, 0] + (points[:, 1] - self._c[1]) * directions[bucket, 1]

        key_t = t_bucket + (rho(y[t_idx], t_bucket) / span + 0.5)
        order_t = np.argsort(key_t)
        key_t, t_sorted = key_t[order_t], t_idx[order_t]

        r1, r2 = rho(self._P[q_ok], q_bucket), rho(self._Q[q_ok], q_bucket)
        q_lo, q_hi = np.minimum(r1, r2) - self.tol, np.maximum(r1, r2) + self.tol
        order_q = np.argsort(q_bucket + ((q_lo + q_hi) / (4 * span) + 0.5))  # by bucket, then by mid-interval
        q_sorted, qb, q_lo, q_hi = q_ok[order_q], q_bucket[order_q], q_lo[order_q], q_hi[order_q]
        # groups: consecutive queries of one bucket, at most group_size long
        pos = np.arange(len(qb))
        bucket_start = np.maximum.accumulate(np.where(np.r_[True, qb[1:] != qb[:-1]], pos, 0))
        first = np.flatnonzero((pos - bucket_start) % group_size == 0)
        g_lo = np.minimum.reduceat(q_lo, first)
        g_hi = np.maximum.reduceat(q_hi, first)
        g_b = qb[first]
        a = np.searchsorted(key_t, g_b + (g_lo / span + 0.5), side="left")
        z = np.searchsorted(key_t, g_b + (g_hi / span + 0.5), side="right")
        keep = z > a
        bounds = np.r_[first, len(qb)]
        return _Groups(q_sorted, bounds[:-1][keep], bounds[1:][keep], t_sorted, a[keep], z[keep])

    # -- batched access for the matcher -------------------------------------------------
    def batches(self, max_elements: int = 1 << 17):
        """Yield ``(Q, T)`` padded index arrays, ``(G, g)`` and ``(G, m)``, covering every block.

        Blocks of similar width are batched together so that ``G * g * m``
        stays near ``max_elements``; padding entries are ``-1``.
        """
        gr = self._groups
        n = len(gr.q_start)
        if n == 0:
            return
        g_len = gr.q_stop - gr.q_start
        t_len = gr.t_stop - gr.t_start
        order = np.argsort(t_len, kind="stable")
        g = int(g_len.max())
        k = 0
        while k < n:
            # widths grow along `order`, so the cost of taking blocks k..stop-1 grows with stop
            cost = np.arange(1, n - k + 1) * g * np.maximum(t_len[order[k:]], 1)
            over = cost > max_elements
            stop = k + max(1, int(np.argmax(over)) if over.any() else n - k)
            sel = order[k:stop]
            m = int(t_len[sel].max())
            g = int(g_len[sel].max())
            cols = np.arange(m)
            T = gr.t_sorted[np.minimum(gr.t_start[sel, None] + cols, len(gr.t_sorted) - 1)]
            T[cols[None, :] >= t_len[sel, None]] = -1
            rows = np.arange(g)
            Q = gr.q_sorted[np.minimum(gr.q_start[sel, None] + rows, len(gr.q_sorted) - 1)]
            Q[rows[None, :] >= g_len[sel, None]] = -1
            yield Q, T
            k = stop

    def mask_batch(self, Q: np.ndarray, T: np.ndarray) -> np.ndarray:
        """``(G, g, m)`` bool candidate test for padded index arrays from :meth:`batches` (-1 is never a candidate)."""
        y0, y1 = self._y0[T][:, None, :], self._y1[T][:, None, :]  # (G, 1, m)
        across = self._n0[Q][:, :, None] * y0  # (G, g, m)
        across += self._n1[Q][:, :, None] * y1
        across -= self._off_n[Q][:, :, None]
        if self.constraint == "line":
            return np.abs(across, out=across) <= self.tol
        along = self._d0[Q][:, :, None] * y0
        along += self._d1[Q][:, :, None] * y1
        along -= self._mid[Q][:, :, None]
        np.abs(along, out=along)
        along -= self._half[Q][:, :, None]  # > 0 beyond an end of the segment
        np.maximum(along, 0.0, out=along)
        np.square(along, out=along)
        np.square(across, out=across)
        across += along
        return across <= self._tol2


@dataclass(frozen=True)
class _Groups:
    """Blocks as slices: queries ``q_sorted[q_start:q_stop]`` against keypoints ``t_sorted[t_start:t_stop]``."""

    q_sorted: np.ndarray
    q_start: np.ndarray
    q_stop: np.ndarray
    t_sorted: np.ndarray
    t_start: np.ndarray
    t_stop: np.ndarray

    @staticmethod
    def empty() -> "_Groups":
        z = np.zeros(0, dtype=np.intp)
        return _Groups(z, z, z, z, z, z)


def _spread(lo: np.ndarray, hi: np.ndarray, edges: np.ndarray):
    """Assign each interval ``[lo, hi]`` (angles, ``hi`` may exceed pi) to every bucket it overlaps.

    Returns ``(item, bucket)`` index arrays, each pair once. Intervals that
    wrap past pi are split in two.
    """
    n_b = len(edges) - 1
    hi = np.minimum(hi, lo + np.pi)
    k0 = np.clip(np.searchsorted(edges, lo, side="right") - 1, 0, n_b - 1)
    k1 = np.clip(np.searchsorted(edges, np.minimum(hi, np.pi), side="right") - 1, 0, n_b - 1)
    items, first, last = [np.arange(len(lo))], [k0], [k1]
    wrap = np.flatnonzero(hi > np.pi)
    if wrap.size:  # the piece past pi continues at 0, up to (not into) the buckets already covered
        w1 = np.clip(np.searchsorted(edges, hi[wrap] - np.pi, side="right") - 1, 0, n_b - 1)
        items.append(wrap)
        first.append(np.zeros(wrap.size, dtype=k0.dtype))
        last.append(np.minimum(w1, k0[wrap] - 1))
    item, k0, k1 = np.concatenate(items), np.concatenate(first), np.concatenate(last)
    count = np.maximum(k1 - k0 + 1, 0)
    offsets = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    return np.repeat(item, count), np.repeat(k0, count) + offsets
