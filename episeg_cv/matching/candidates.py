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

The pencil angle (compared as a cheaper pseudo-angle with the same order, see
:mod:`._index_kernels`) is built from an orthonormal basis of the lines through the
(unit) homogeneous epipole, so an epipole at infinity (``t_3 = 0``) or very
far needs no special case. For pure rotation (``t = 0``) there is no pencil;
every segment is a point and the index falls back to one bucket with ``rho``
along ``x``.
"""

from __future__ import annotations

import numpy as np

from .. import threads
from .._validation import as_points, as_positive_int
from ..geometry import EpipolarSegments, TwoViewGeometry, as_geometry
from . import _index_kernels as _ik
from . import _kernels
from .config import SearchConfig, resolve

__all__ = ["CandidateIndex"]

#: Per-thread column arrays of the parallel scan, reused across scans.
_SCRATCH = threads.Scratch()
#: Blocks of rows per thread in the parallel scan (evens out uneven slices).
BLOCKS_PER_THREAD = 4


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
                    as_positive_int(bucket_size, "bucket_size"))

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
        self._geo = threads.run(_ik.query_frames, _ik.query_frames_parallel, len(self._P), self._P, self._Q,
                                self._line, self.constraint == "line")
        self._tol2 = self.tol * self.tol * (1 + 1e-9) + 1e-12
        #: Query ``q_sorted[r]`` is compared with the keypoints ``t_sorted[q_start[r]:q_stop[r]]``.
        self.q_sorted, self.q_start, self.q_stop, self.t_sorted = self._build(max(int(bucket_size), 1))
        self._y_sorted = np.empty((len(self.t_sorted), 2))
        _gather(self.points2, self.t_sorted, self._y_sorted)

    def run(self, kernel, *args):
        """Call a serial kernel of :mod:`._kernels` on the slices and the exact test (kernel arguments follow)."""
        return kernel(self.q_sorted, self.q_start, self.q_stop, self.t_sorted, self._geo, self._y_sorted,
                      self.constraint == "line", self.tol, self._tol2, *args)

    def scan(self, a: np.ndarray, b: np.ndarray, norm: int, idx: np.ndarray, sc: np.ndarray, counts: np.ndarray,
             col_s: np.ndarray, col_i: np.ndarray) -> None:
        """Score every candidate pair; *accumulate* the results into the arrays given.

        ``a (N1, D)`` / ``b (N2, D)`` are the scoring arrays of :class:`~.distances.Distances` and
        ``norm`` its kernel code. Merged into (never reset): ``idx (N1, k)`` intp / ``sc (N1, k)``
        float32, each query's ``k`` best candidates (ties by the smaller keypoint index; -1 / inf
        where none), ``counts (N1,)`` intp (candidates added), ``col_s (N2,)`` float32 / ``col_i
        (N2,)`` intp, each keypoint's best query (ties by the smaller query index). So several
        indexes over disjoint groups of queries can be scanned into the same arrays. The result is
        the same for every thread count (:func:`episeg_cv.set_num_threads`).
        """
        rows = len(self.q_sorted)
        if rows == 0:
            return
        if not threads.use_parallel(rows):
            self.run(_kernels.knn_scan, a, b, norm, idx, sc, counts, col_s, col_i)
            return
        n = threads.get_num_threads()
        bounds = _kernels.work_bounds(self.q_start, self.q_stop, BLOCKS_PER_THREAD * n)
        tcol_s = _SCRATCH.get("tcol_s", (n, len(col_s)), np.float32)
        tcol_i = _SCRATCH.get("tcol_i", (n, len(col_i)), col_i.dtype)
        threads.call_parallel(self.run, _kernels.knn_scan_parallel, a, b, norm, idx, sc, counts, col_s,
                              col_i, bounds, tcol_s, tcol_i)

    def candidate_lists(self) -> tuple[np.ndarray, np.ndarray]:
        """Every candidate pair as ``(i, j)`` int64 arrays, in scan order (unsorted)."""
        if threads.use_parallel(len(self.q_sorted)):
            return threads.call_parallel(self.run, _kernels.candidate_pairs_parallel, threads.blocks())
        return self.run(_kernels.candidate_pairs)

    def pairs(self) -> np.ndarray:
        """All candidate pairs ``(K, 2)`` of ``(query, train)`` indices, sorted by query then train."""
        i, j = self.candidate_lists()
        o = np.lexsort((j, i))
        return np.column_stack([i[o], j[o]]).astype(np.intp)

    def candidate_counts(self) -> np.ndarray:
        """(N1,) number of candidates of each query."""
        i, _ = self.candidate_lists()
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
        c0, c1 = float(self._c[0]), float(self._c[1])
        if pencil is None:  # pure rotation: every segment is a point; one bucket, rho along x
            q_sorted, qb = q_ok, np.zeros(q_ok.size, dtype=np.intp)
            edges = np.array([0.0, _ik.PERIOD])
            lo, width = np.zeros(n2), np.full(n2, _ik.PERIOD)
        else:
            e, u, v = pencil
            # queries: the pencil angle of their epipolar line, taken in normalised coordinates; in pencil
            # order, the buckets are runs of about bucket_size of them
            q_phi = threads.run(_ik.query_phi, _ik.query_phi_parallel, q_ok.size, self._line, q_ok, self._s, c0, c1,
                                u, v)
            order = np.argsort(q_phi)
            q_sorted, q_phi = q_ok[order], q_phi[order]
            n_b = max(1, int(np.ceil(q_ok.size / bucket_size)))
            edges = np.concatenate([[0.0], q_phi[(np.arange(1, n_b) * q_ok.size) // n_b], [_ik.PERIOD]])
            qb = np.clip(np.searchsorted(edges, q_phi, side="right") - 1, 0, n_b - 1)
            # keypoints: the interval of pencil angles of lines within tol of them
            lo, width = threads.run(_ik.pencil_intervals, _ik.pencil_intervals_parallel, n2, e, u, v, c0, c1,
                                    self._s, self.tol, y)
        n_b = len(edges) - 1
        bstart = np.searchsorted(qb, np.arange(n_b + 1), side="left")
        # per bucket: a direction (the mean of its lines'), rho along it, each query's rho interval and their hull
        span = 2.0 * (self._s + 2 * self.tol + 1.0)
        directions, klo, khi, hull = threads.run(_ik.bucket_frames, _ik.bucket_frames_parallel, q_sorted.size,
                                                 q_sorted, bstart, self._line, self._P, self._Q, pencil is not None,
                                                 c0, c1, span, self.tol)
        # each keypoint in the buckets its interval overlaps (within the hull), sorted by bucket then rho
        t_sorted, key_t, tstart = threads.run(_ik.spread_keys, _ik.spread_keys_parallel, n2, lo, width, edges, y,
                                              directions, c0, c1, span, hull)
        start, stop = threads.run(_ik.slice_bounds, _ik.slice_bounds_parallel, q_sorted.size, key_t, tstart, qb,
                                  klo, khi)
        keep = stop > start
        return q_sorted[keep], start[keep], stop[keep], t_sorted


def _gather(src: np.ndarray, rows: np.ndarray, out: np.ndarray) -> None:
    """``out[m] = src[rows[m]]``, on threads for many rows."""
    threads.run(_kernels.gather_rows, _kernels.gather_rows_parallel, len(rows), src, rows, out)


def _cross(a, b):
    """Cross product of two 3-vectors (``np.cross`` costs ~50 us of overhead on them)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])
