"""Candidate search: which keypoints of image 2 lie near each query's segment (or line).

No ``N1 x N2`` array is formed. All epipolar lines of image 2 pass through the
epipole, so they form a *pencil*; each line has a pencil angle ``phi``. The
index works in two stages:

1. **Pencil buckets.** Queries are sorted by ``phi`` and cut into buckets of
   about equal size. A keypoint ``y`` of image 2 can only be within ``tol`` of
   lines whose ``phi`` lies in a small interval (the lines through the
   epipole that touch the disk of radius ``tol`` around ``y``); it is put in
   every bucket that interval overlaps.
2. **Slices along the lines.** Inside a bucket, positions along the lines are
   measured by ``rho``, the projection on the bucket's mean line direction,
   and the bucket's keypoints are sorted by it. Projection is 1-Lipschitz, so
   a point within ``tol`` of a segment has ``rho`` within ``tol`` of the
   segment's ``rho`` interval: each query gets the contiguous slice of its
   bucket's keypoints whose ``rho`` lies in its interval.

The exact geometric test, distance to the segment (or line) at most ``tol``,
is then applied to each keypoint of the slice, in compiled code
(:mod:`._kernels`), and only the keypoints that pass it are scored.
The line and the segment use the same index; the segment's shorter ``rho``
intervals give shorter slices, so it does less work.

The pencil angle is built from an orthonormal basis of the lines through the
(unit) homogeneous epipole, so an epipole at infinity (``t_3 = 0``) or very
far needs no special case. For pure rotation (``t = 0``) there is no pencil;
every segment is a point and the index falls back to one bucket with ``rho``
along ``x``.
"""

from __future__ import annotations

import numpy as np

from .._validation import as_points
from ..geometry import EpipolarSegments, TwoViewGeometry, as_geometry
from . import _kernels
from .config import SearchConfig, resolve

__all__ = ["CandidateIndex"]


class CandidateIndex:
    """Spatial index of the keypoints of image 2 for the segments (or lines) of image-1 queries.

    Parameters
    ----------
    geometry : TwoViewGeometry or FundamentalGeometry
        Known pose; ``X2 = R @ X1 + t`` (a covariance is not used: the fixed ``tol``).
    points1 : (N1, 2) array_like
        Query pixels in image 1.
    points2 : (N2, 2) array_like
        Keypoint pixels in image 2.
    search : SearchConfig, optional
        The constraint (``"segment"`` or ``"line"``), its pixel tolerance
        ``tol`` and the depth range (ignored by ``"line"``). Its fields can
        also be given as keyword arguments (``tol=2.0``, ...).
    bucket_size : int, optional
        Queries per pencil bucket. Smaller buckets are narrower, so their
        slices hold fewer keypoints off the lines, but a keypoint near many
        lines is stored in more buckets. Speed only: the candidates do not
        change.

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

    def __init__(self, geometry: TwoViewGeometry, points1, points2, *, search: SearchConfig | None = None,
                 bucket_size: int = 64, **options):
        search, _ = resolve(search, None, options, takes_rule=False)
        if search.auto is not None:
            raise ValueError("CandidateIndex needs a numeric tol; estimate one with estimate_band (tol='auto')")
        self._setup(as_geometry(geometry), as_points(points1, "points1"), as_points(points2, "points2"), search,
                    bucket_size)

    @classmethod
    def build(cls, geometry: TwoViewGeometry, points1: np.ndarray, points2: np.ndarray, search: SearchConfig,
              bucket_size: int = 64) -> "CandidateIndex":
        """The index of inputs the caller has already checked (``(N, 2)`` float64 points, a geometry)."""
        index = cls.__new__(cls)
        index._setup(geometry, points1, points2, search, bucket_size)
        return index

    def _setup(self, geometry, points1, points2, search, bucket_size):
        if search.constraint == "none":
            raise ValueError("CandidateIndex needs constraint 'segment' or 'line'; 'none' has no index")
        self.geometry = geometry
        self.points1 = points1
        self.points2 = np.ascontiguousarray(points2)
        self.search = search
        self.tol = search.tol
        self.constraint = search.constraint
        #: The segments of the queries, clipped to image 2 grown by ``tol``.
        self.segments: EpipolarSegments = geometry.segments(self.points1, search.depth_range, margin=self.tol)
        seg = self.segments
        if self.constraint == "segment":
            self._P, self._Q, self._ok = seg.start, seg.end, seg.valid
        else:
            self._P, self._Q = seg.line_start, seg.line_end
            self._ok = np.all(np.isfinite(seg.line_start), axis=1)
        self._P, self._Q = np.ascontiguousarray(self._P), np.ascontiguousarray(self._Q)
        self._line = np.ascontiguousarray(np.where(np.isfinite(seg.line), seg.line, 0.0))
        # the kernels' per-query frame (rows of queries without a segment are never read)
        self._geo = _kernels.query_frames(self._P, self._Q, self._line, self.constraint == "line")
        self._tol2 = self.tol * self.tol * (1 + 1e-9) + 1e-12
        #: Query ``q_sorted[r]`` is compared with the keypoints ``t_sorted[q_start[r]:q_stop[r]]``.
        self.q_sorted, self.q_start, self.q_stop, self.t_sorted = self._build(max(int(bucket_size), 1))
        self._y_sorted = self.points2[self.t_sorted]

    def run(self, kernel, *args):
        """Call a kernel of :mod:`._kernels` on the slices and the exact test (kernel arguments follow)."""
        return kernel(self.q_sorted, self.q_start, self.q_stop, self.t_sorted, self._geo, self._y_sorted,
                      self.constraint == "line", self.tol, self._tol2, *args)

    def pairs(self) -> np.ndarray:
        """All candidate pairs ``(K, 2)`` of ``(query, train)`` indices, sorted by query then train."""
        i, j = self.run(_kernels.candidate_pairs)
        o = np.lexsort((j, i))
        return np.column_stack([i[o], j[o]]).astype(np.intp)

    def candidate_counts(self) -> np.ndarray:
        """(N1,) number of candidates of each query."""
        i, _ = self.run(_kernels.candidate_pairs)
        return np.bincount(i, minlength=len(self.points1)).astype(np.intp)

    # -- building ------------------------------------------------------------------
    def _pencil(self):
        """Orthonormal pencil basis in normalised image-2 coordinates, or None for ``t = 0``."""
        w, h = self.geometry.image_size2
        self._c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
        self._s = float(np.hypot(w, h))
        b = self.geometry.epipole_homogeneous
        e = np.array([(b[0] - self._c[0] * b[2]) / self._s, (b[1] - self._c[1] * b[2]) / self._s, b[2]])
        ne = float(np.sqrt(e @ e))
        if ne == 0:
            return None
        e = e / ne
        u = _cross(e, np.eye(3)[np.argmin(np.abs(e))])
        u /= np.sqrt(u @ u)
        return e, u, _cross(e, u)

    def _build(self, bucket_size: int):
        """``(q_sorted, q_start, q_stop, t_sorted)``: the slices of :attr:`t_sorted` to scan per query."""
        n2 = len(self.points2)
        q_ok = np.flatnonzero(self._ok)
        if n2 == 0 or q_ok.size == 0:
            z = np.zeros(0, dtype=np.intp)
            return z, z, z, z
        pencil = self._pencil()
        y = self.points2
        if pencil is None:  # pure rotation: every segment is a point; one bucket, rho along x
            q_sorted, qb = q_ok, np.zeros(q_ok.size, dtype=np.intp)
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
            # the queries in pencil order; the buckets are runs of about bucket_size of them
            order = np.argsort(q_phi)
            q_sorted, q_phi, line = q_ok[order], q_phi[order], line[order]
            n_b = max(1, int(np.ceil(q_ok.size / bucket_size)))
            edges = np.concatenate([[0.0], q_phi[(np.arange(1, n_b) * q_ok.size) // n_b], [np.pi]])
            qb = np.clip(np.searchsorted(edges, q_phi, side="right") - 1, 0, n_b - 1)
            # keypoints: the interval of pencil angles of lines within tol of them, and its buckets
            lo, width = _kernels.pencil_intervals(e, u, v, self._c[0], self._c[1], self._s, self.tol, y)
            t_idx, t_bucket = _kernels.spread(lo, lo + width, edges)
            # one direction per bucket: the mean direction of its lines, averaged as doubled angles
            # (the direction (-b, a) of a unit line (a, b, c), doubled, is (b^2 - a^2, -2ab))
            a, b = line[:, 0], line[:, 1]
            half = 0.5 * np.arctan2(np.bincount(qb, -2 * a * b, n_b), np.bincount(qb, b * b - a * a, n_b))
            directions = np.column_stack([np.cos(half), np.sin(half)])
        # rho: position along the bucket direction, scaled into [0, 1) so that (bucket + rho) sorts
        span = 2.0 * (self._s + 2 * self.tol + 1.0)

        def rho(points, bucket):
            return (points[:, 0] - self._c[0]) * directions[bucket, 0] + (points[:, 1] - self._c[1]) * directions[bucket, 1]

        key_t = t_bucket + (rho(y[t_idx], t_bucket) / span + 0.5)
        order_t = np.argsort(key_t)
        key_t, t_sorted = key_t[order_t], t_idx[order_t]
        start, stop = _kernels.slice_bounds(key_t, q_sorted, qb, self._P, self._Q, directions, self._c[0],
                                            self._c[1], span, self.tol)
        keep = stop > start
        return q_sorted[keep], start[keep], stop[keep], t_sorted


def _cross(a, b):
    """Cross product of two 3-vectors (``np.cross`` costs ~50 us of overhead on them)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])
