"""The OpenCV-compatible layer: :class:`SegmentMatcher`, a drop-in for ``cv2.BFMatcher``.

``cv2.KeyPoint`` and ``cv2.DMatch`` objects are converted here, once, to and
from the arrays of :mod:`episeg_cv.matching`.
"""

from __future__ import annotations

from collections import deque
from itertools import chain, compress, repeat
from operator import attrgetter

import cv2
import numpy as np

from ._validation import as_depth_range, as_nonnegative, as_points
from .candidates import check_constraint
from .geometry import TwoViewGeometry
from .matching import (DEFAULT_PAD, DEFAULT_RATIO, _check_k, _check_points, _exact, check_descriptors,
                       check_norm, check_ratio,
                       explain_pairs, filter_pairs, knn_descriptors, match_descriptors, radius_descriptors)

__all__ = ["SegmentMatcher", "keypoints_to_array"]


def keypoints_to_array(keypoints, name: str = "keypoints") -> np.ndarray:
    """``(N, 2)`` float64 pixel positions from a sequence of ``cv2.KeyPoint`` or an ``(N, 2)`` array."""
    if keypoints is None:
        return np.zeros((0, 2))
    if isinstance(keypoints, (list, tuple)) and len(keypoints) and isinstance(keypoints[0], cv2.KeyPoint):
        try:
            pts = cv2.KeyPoint_convert(keypoints).astype(np.float64).reshape(-1, 2)
        except cv2.error:
            raise TypeError(f"{name} must be all cv2.KeyPoint or an (N, 2) array") from None
        if not np.all(np.isfinite(pts)):
            raise ValueError(f"{name} must have finite positions, got NaN or inf")
        return pts
    return as_points(keypoints, name)


def _to_dmatches(pairs: np.ndarray, distances: np.ndarray) -> list:
    # the 3-argument constructor is 5x faster than the 4-argument one (no overload search)
    out = list(map(cv2.DMatch, pairs[:, 0].tolist(), pairs[:, 1].tolist(), distances.tolist()))
    n = len(out)
    deque(map(setattr, out, repeat("imgIdx", n), repeat(0, n)), maxlen=0)  # as cv2.BFMatcher reports for one image
    return out


def _per_query(n: int, pairs: np.ndarray, distances: np.ndarray) -> list:
    """One list of DMatch per query (pairs sorted by query), empty where it has none."""
    flat = _to_dmatches(pairs, distances)
    ends = np.searchsorted(pairs[:, 0], np.arange(1, n + 1)).tolist()
    starts = [0] + ends[:-1]
    return [flat[a:b] for a, b in zip(starts, ends)]


class SegmentMatcher:
    """A drop-in for ``cv2.BFMatcher`` that searches only the correct epipolar segment.

    Replace ``cv2.BFMatcher(cv2.NORM_L2)`` with ``SegmentMatcher(geometry, cv2.NORM_L2)``
    and add the keypoints to each call.

    Parameters
    ----------
    geometry : TwoViewGeometry
        The known pose of image 2 (train) relative to image 1 (query):
        ``X2 = R @ X1 + t``.
    normType : int, optional
        ``cv2.NORM_L2`` (SIFT), ``cv2.NORM_L1``, ``cv2.NORM_L2SQR`` or
        ``cv2.NORM_HAMMING`` (ORB, AKAZE, BRISK).
    crossCheck : bool, optional
        Keep only mutual nearest neighbours, each direction under its own
        constraint (the reverse with ``geometry.inverse()``). OpenCV cannot
        combine crossCheck with a mask; this can.
    tol : float, optional
        Pixel distance from a keypoint to the segment (not the line) within
        which it is a candidate. Default 2.
    depth_range : (zmin, zmax), optional
        Bounds on the depth in camera 1, in the unit of ``t``.
    constraint : {"segment", "line", "none"}, optional
        ``"segment"`` (ours), ``"line"`` (plain epipolar filtering, same code
        path) or ``"none"`` (exactly ``cv2.BFMatcher``).
    ratio, mutual, pad
        The acceptance rule of :meth:`match` (defaults chosen on the benchmark); see
        :func:`episeg_cv.matching.match_descriptors`. They do not apply to
        ``constraint="none"``, which returns what ``cv2.BFMatcher.match`` does.

    Notes
    -----
    :meth:`match` returns accepted matches only (the rule above), not one
    match per query as ``cv2.BFMatcher.match`` does: with the candidates
    restricted, the bare nearest neighbour of a query with a single candidate
    would always be kept. :meth:`knnMatch` and :meth:`radiusMatch` return the
    raw neighbours, like OpenCV's.

    Examples
    --------
    >>> import cv2, numpy as np
    >>> from episeg_cv import TwoViewGeometry, SegmentMatcher
    >>> K = [[100, 0, 50], [0, 100, 50], [0, 0, 1]]
    >>> g = TwoViewGeometry(K, K, np.eye(3), [-1, 0, 0], image_size1=(100, 100), image_size2=(100, 100))
    >>> kp1 = [cv2.KeyPoint(60, 20, 5), cv2.KeyPoint(60, 70, 5)]
    >>> kp2 = [cv2.KeyPoint(40, 20, 5), cv2.KeyPoint(80, 70, 5)]
    >>> des = np.eye(2, 8, dtype=np.float32)
    >>> m = SegmentMatcher(g, cv2.NORM_L2, pad=0).match(des, des, kp1, kp2)
    >>> [(d.queryIdx, d.trainIdx) for d in m]
    [(0, 0)]
    >>> len(cv2.BFMatcher(cv2.NORM_L2).match(des, des))      # BFMatcher keeps the wrong-side pair too
    2
    """

    def __init__(self, geometry, normType=cv2.NORM_L2, crossCheck=False, *, tol=2.0,
                 depth_range=(0.0, np.inf), constraint="segment", ratio=DEFAULT_RATIO, mutual=True,
                 pad=DEFAULT_PAD):
        if not isinstance(geometry, TwoViewGeometry):
            raise TypeError(f"geometry must be a TwoViewGeometry, got {type(geometry).__name__}")
        self.geometry = geometry
        self.normType = normType
        self._norm = check_norm(normType)
        self.crossCheck = bool(crossCheck)
        self.tol = as_nonnegative(tol, "tol")
        as_depth_range(depth_range, None)  # per-point arrays are checked against N at each call
        self.depth_range = depth_range
        self.constraint = check_constraint(constraint)
        self.ratio = check_ratio(ratio, "ratio")
        self.mutual = bool(mutual)
        if isinstance(pad, (bool, np.bool_)) or not isinstance(pad, (int, np.integer)) or pad < 0:
            raise ValueError(f"pad must be an integer >= 0, got {pad!r}")
        self.pad = int(pad)

    def __repr__(self) -> str:
        return (f"SegmentMatcher(normType={self.normType}, crossCheck={self.crossCheck}, tol={self.tol}, "
                f"depth_range={self.depth_range}, constraint={self.constraint!r}, ratio={self.ratio}, "
                f"mutual={self.mutual}, pad={self.pad})")

    # -- helpers ---------------------------------------------------------------------
    def _inputs(self, queryDescriptors, trainDescriptors, queryKeypoints, trainKeypoints):
        d1, d2 = check_descriptors(queryDescriptors, trainDescriptors, self._norm,
                                   names=("queryDescriptors", "trainDescriptors"))
        p1 = _check_points(keypoints_to_array(queryKeypoints, "queryKeypoints"), d1, "queryKeypoints",
                           "queryDescriptors")
        p2 = _check_points(keypoints_to_array(trainKeypoints, "trainKeypoints"), d2, "trainKeypoints",
                           "trainDescriptors")
        return d1, d2, p1, p2

    def _kw(self):
        return dict(norm=self._norm, tol=self.tol, depth_range=self.depth_range, constraint=self.constraint)

    def _bf(self):
        return cv2.BFMatcher(self.normType, self.crossCheck)

    @staticmethod
    def _cv(d):  # cv2 takes float32 or uint8 only
        return d.astype(np.float32) if d.dtype == np.float64 else d

    # -- the cv2.BFMatcher API -----------------------------------------------------------
    def match(self, queryDescriptors, trainDescriptors, queryKeypoints, trainKeypoints) -> list:
        """Accepted matches, one at most per query, as ``list[cv2.DMatch]`` (``imgIdx = 0``)."""
        d1, d2, p1, p2 = self._inputs(queryDescriptors, trainDescriptors, queryKeypoints, trainKeypoints)
        if len(d1) == 0 or len(d2) == 0:
            return []
        if self.constraint == "none":
            return list(self._bf().match(self._cv(d1), self._cv(d2)))
        pairs, dist = match_descriptors(d1, d2, p1, p2, self.geometry, ratio=self.ratio, mutual=self.mutual,
                                        pad=self.pad, cross_check=self.crossCheck, **self._kw())
        return _to_dmatches(pairs, dist)

    def knnMatch(self, queryDescriptors, trainDescriptors, queryKeypoints, trainKeypoints, k) -> list:
        """The ``k`` nearest candidates of each query: one list per query, shorter when fewer exist."""
        k = _check_k(k)
        d1, d2, p1, p2 = self._inputs(queryDescriptors, trainDescriptors, queryKeypoints, trainKeypoints)
        if self.crossCheck and k != 1:
            raise ValueError(f"k must be 1 when crossCheck is True (as in cv2.BFMatcher), got {k}")
        if len(d1) == 0:
            return []
        if len(d2) == 0:
            return [[] for _ in range(len(d1))]
        if self.constraint == "none":
            return [list(m) for m in self._bf().knnMatch(self._cv(d1), self._cv(d2), k=k)]
        if self.crossCheck:
            pairs, dist = match_descriptors(d1, d2, p1, p2, self.geometry, ratio=1.0, mutual=False, pad=0,
                                            cross_check=True, **self._kw())
            return _per_query(len(d1), pairs, dist)
        res = knn_descriptors(d1, d2, p1, p2, self.geometry, k=k, **self._kw())
        i, col = np.nonzero(res.indices >= 0)  # row-major: by query, nearest first
        j = res.indices[i, col]
        return _per_query(len(d1), np.column_stack([i, j]), _exact(d1, d2, self._norm, i, j))

    def radiusMatch(self, queryDescriptors, trainDescriptors, queryKeypoints, trainKeypoints, maxDistance) -> list:
        """All candidates within ``maxDistance`` of each query, nearest first: one list per query."""
        max_distance = as_nonnegative(maxDistance, "maxDistance")
        d1, d2, p1, p2 = self._inputs(queryDescriptors, trainDescriptors, queryKeypoints, trainKeypoints)
        if len(d1) == 0:
            return []
        if len(d2) == 0:
            return [[] for _ in range(len(d1))]
        if self.constraint == "none":
            return [list(m) for m in self._bf().radiusMatch(self._cv(d1), self._cv(d2), max_distance)]
        pairs, dist = radius_descriptors(d1, d2, p1, p2, self.geometry, max_distance=max_distance, **self._kw())
        return _per_query(len(d1), pairs, dist)

    # -- after matching ----------------------------------------------------------------
    def filter(self, matches, queryKeypoints, trainKeypoints):
        """Outlier rejection: keep only the matches that satisfy the constraint.

        Parameters
        ----------
        matches : list[cv2.DMatch] or list[list[cv2.DMatch]]
            The output of any matcher (``match``, ``knnMatch``, ``radiusMatch``).
        queryKeypoints, trainKeypoints : sequence of cv2.KeyPoint or (N, 2) array

        Returns
        -------
        The same structure, holding only the pairs that pass.
        """
        nested, flat = _flatten(matches)
        keep = filter_pairs(_pairs_of(flat), keypoints_to_array(queryKeypoints, "queryKeypoints"),
                            keypoints_to_array(trainKeypoints, "trainKeypoints"), self.geometry,
                            tol=self.tol, depth_range=self.depth_range, constraint=self.constraint)
        return _unflatten(matches, nested, keep)

    def explain(self, matches, queryKeypoints, trainKeypoints):
        """Why each match passes or fails the segment constraint.

        Returns
        -------
        labels : (K,) int8
            :class:`~episeg_cv.Rejection` labels, in the order of the flattened matches.
        counts : dict[str, int]
            Matches per reason: ``on_segment``, ``beyond_infinity``,
            ``beyond_epipole``, ``off_line``, ``empty_segment``, ``out_of_range``.
            Those on the line but not on the segment are what the segment adds.
        """
        _, flat = _flatten(matches)
        return explain_pairs(_pairs_of(flat), keypoints_to_array(queryKeypoints, "queryKeypoints"),
                             keypoints_to_array(trainKeypoints, "trainKeypoints"), self.geometry,
                             tol=self.tol, depth_range=self.depth_range)


def _flatten(matches):
    if matches is None:
        raise TypeError("matches must be a list of cv2.DMatch or a list of lists of cv2.DMatch, got None")
    matches = list(matches)
    # type() of every item in C, then the few distinct types in Python: far faster than isinstance per item
    types = set(map(type, matches))
    nested = any(issubclass(t, (list, tuple)) for t in types)
    flat = list(chain.from_iterable(matches)) if nested else matches
    if not all(issubclass(t, cv2.DMatch) for t in (set(map(type, flat)) if nested else types)):
        for m in flat:
            if not isinstance(m, cv2.DMatch):
                raise TypeError(f"matches must hold cv2.DMatch objects, got {type(m).__name__}")
    return nested, flat


_QUERY_IDX, _TRAIN_IDX = attrgetter("queryIdx"), attrgetter("trainIdx")


def _pairs_of(flat) -> np.ndarray:
    pairs = np.empty((len(flat), 2), dtype=np.intp)
    pairs[:, 0] = np.fromiter(map(_QUERY_IDX, flat), dtype=np.intp, count=len(flat))
    pairs[:, 1] = np.fromiter(map(_TRAIN_IDX, flat), dtype=np.intp, count=len(flat))
    return pairs


def _unflatten(matches, nested, keep):
    if not nested:
        return list(compress(matches, keep.tolist()))
    rows = [list(row) for row in matches]
    kept = list(compress(chain.from_iterable(rows), keep.tolist()))
    lens = np.fromiter(map(len, rows), dtype=np.intp, count=len(rows))
    ends = np.cumsum(np.bincount(np.repeat(np.arange(len(rows)), lens), weights=keep, minlength=len(rows))
                     .astype(np.intp)).tolist()
    return [kept[a:b] for a, b in zip([0] + ends[:-1], ends)]
