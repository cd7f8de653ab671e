"""The OpenCV-compatible layer: :class:`SegmentMatcher`, a drop-in for ``cv2.BFMatcher``.

``cv2.KeyPoint`` and ``cv2.DMatch`` objects are converted here, once, to and
from the arrays of :mod:`episeg_cv.matching`.
"""

from __future__ import annotations

import contextlib
import gc
from collections import deque
from itertools import chain, compress, repeat
from operator import attrgetter

import cv2
import numpy as np

from ._validation import as_index_pairs, as_nonnegative, as_norm, as_points, as_positive_int
from .geometry import as_geometry
from .matching import auto, guided
from .matching.candidates import CandidateIndex
from .matching.config import AcceptRule, SearchConfig, resolve
from .matching.filtering import explain, keep_mask

__all__ = ["SegmentMatcher", "keypoints_to_array", "pairs_of"]

#: Norm names -> the ``cv2.NORM_*`` constants that ``cv2.BFMatcher`` takes.
_CV2_NORMS = {"l1": cv2.NORM_L1, "l2": cv2.NORM_L2, "l2sqr": cv2.NORM_L2SQR, "hamming": cv2.NORM_HAMMING}


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
    with _collector_paused():
        return [flat[a:b] for a, b in zip(starts, ends)]


@contextlib.contextmanager
def _collector_paused():
    """Python's cyclic garbage collector off while a burst of lists is made (it ran every 700 new lists,
    and each run walked the young ones: 12 % of knnMatch's per-query lists at 10k queries); a collector
    the program turned off stays off."""
    if not gc.isenabled():
        yield
        return
    gc.disable()
    try:
        yield
    finally:
        gc.enable()


class SegmentMatcher:
    """A drop-in for ``cv2.BFMatcher`` that searches only the correct epipolar segment.

    Replace ``cv2.BFMatcher(cv2.NORM_L2)`` with ``SegmentMatcher(geometry, cv2.NORM_L2)``
    and add the keypoints to each call.

    Parameters
    ----------
    geometry : TwoViewGeometry or FundamentalGeometry
        The known pose of image 2 (train) relative to image 1 (query):
        ``X2 = R @ X1 + t``; with a covariance
        (:meth:`~episeg_cv.TwoViewGeometry.with_covariance`) each query is
        searched in its own band. Or an oriented fundamental matrix
        (:func:`~episeg_cv.estimate_geometry`): the half-line from the epipole.
    normType : int, optional
        ``cv2.NORM_L2`` (SIFT), ``cv2.NORM_L1``, ``cv2.NORM_L2SQR`` or
        ``cv2.NORM_HAMMING`` (ORB, AKAZE, BRISK).
    crossCheck : bool, optional
        Keep only mutual nearest neighbours, each direction under its own
        constraint (the reverse with ``geometry.inverse()``). OpenCV cannot
        combine crossCheck with a mask; this can.
    search : SearchConfig, optional
        Where the candidates are: ``constraint`` (``"segment"``, ours;
        ``"line"``, plain epipolar filtering by the same code path; ``"none"``,
        exactly ``cv2.BFMatcher``), ``tol`` (pixels to the segment, default 2;
        ``"auto"`` estimates it, and corrects the pose when that matters, from
        each call's keypoints: :func:`~episeg_cv.estimate_band`) and
        ``depth_range`` (bounds on the depth in camera 1, unit of ``t``).
    rule : AcceptRule, optional
        The acceptance rule of :meth:`match`: ``ratio``, ``mutual``, ``pad``
        (defaults chosen on the benchmark). It does not apply to
        ``constraint="none"``, which returns what ``cv2.BFMatcher.match`` does.
    **options
        Fields of either object as keywords (``tol=4``, ``ratio=0.8``, ...).

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

    def __init__(self, geometry, normType=cv2.NORM_L2, crossCheck=False, *, search: SearchConfig | None = None,
                 rule: AcceptRule | None = None, **options):
        self.geometry = as_geometry(geometry)
        self.normType = normType
        self._norm = as_norm(normType)
        if crossCheck:
            options = {"cross_check": True, **options}
        #: The :class:`~episeg_cv.SearchConfig` and :class:`~episeg_cv.AcceptRule` of every call.
        self.search, self.rule = resolve(search, rule, options)

    # the settings, as attributes (read-only: make a new matcher to change them)
    crossCheck = property(lambda self: self.rule.cross_check, doc="Mutual nearest neighbours in both directions.")
    tol = property(lambda self: self.search.tol, doc="Pixel tolerance of the constraint (a float or an AutoTol).")
    depth_range = property(lambda self: self.search.depth_range, doc="Depth bounds in camera 1.")
    constraint = property(lambda self: self.search.constraint, doc="'segment', 'line' or 'none'.")
    ratio = property(lambda self: self.rule.ratio, doc="Ratio of the acceptance rule.")
    mutual = property(lambda self: self.rule.mutual, doc="Mutual check of the acceptance rule.")
    pad = property(lambda self: self.rule.pad, doc="Random reference keypoints of the ratio test.")

    def __repr__(self) -> str:
        return f"SegmentMatcher(normType={self.normType}, search={self.search!r}, rule={self.rule!r})"

    # -- helpers ---------------------------------------------------------------------
    def _inputs(self, queryDescriptors, trainDescriptors, queryKeypoints, trainKeypoints) -> guided.MatchInputs:
        return guided.MatchInputs.check(queryDescriptors, trainDescriptors,
                                        keypoints_to_array(queryKeypoints, "queryKeypoints"),
                                        keypoints_to_array(trainKeypoints, "trainKeypoints"), self._norm,
                                        names=("queryDescriptors", "trainDescriptors", "queryKeypoints",
                                               "trainKeypoints"))

    def _bf(self):
        return cv2.BFMatcher(_CV2_NORMS[self._norm], self.crossCheck)

    @staticmethod
    def _cv(d):  # cv2 takes float32 or uint8 only
        return d.astype(np.float32) if d.dtype == np.float64 else d

    def _index(self, index, inp):
        if self.constraint == "none":
            if index is not None:
                raise ValueError("constraint 'none' has no candidate index; index must be None")
            return None
        return guided.check_index(index, inp, self.geometry, self.search)

    def index(self, queryKeypoints, trainKeypoints) -> CandidateIndex:
        """The candidate index of a pair of keypoint sets, to pass as ``index=`` to several calls on that pair.

        The segments and the index depend on the keypoints and the geometry, not on the
        descriptors; building them once saves that part (about a third of :meth:`match` at 10k
        keypoints) when, for example, :meth:`knnMatch` and :meth:`match` run on the same pair.
        Each call checks that the index fits its keypoints.

        Examples
        --------
        >>> import cv2, numpy as np
        >>> from episeg_cv import TwoViewGeometry, SegmentMatcher
        >>> K = [[100, 0, 50], [0, 100, 50], [0, 0, 1]]
        >>> g = TwoViewGeometry(K, K, np.eye(3), [-1, 0, 0], image_size1=(100, 100), image_size2=(100, 100))
        >>> kp1, kp2 = [cv2.KeyPoint(60, 20, 5)], [cv2.KeyPoint(40, 20, 5), cv2.KeyPoint(30, 20, 5)]
        >>> des1, des2 = np.eye(1, 8, dtype=np.float32), np.eye(2, 8, dtype=np.float32)
        >>> m = SegmentMatcher(g, cv2.NORM_L2, pad=0)
        >>> idx = m.index(kp1, kp2)
        >>> [[d.trainIdx for d in row] for row in m.knnMatch(des1, des2, kp1, kp2, k=2, index=idx)]
        [[0, 1]]
        >>> [d.trainIdx for d in m.match(des1, des2, kp1, kp2, index=idx)]
        [0]
        """
        if self.constraint == "none":
            raise ValueError("constraint 'none' has no candidate index")
        return CandidateIndex(self.geometry, keypoints_to_array(queryKeypoints, "queryKeypoints"),
                              keypoints_to_array(trainKeypoints, "trainKeypoints"), search=self.search)

    # -- the cv2.BFMatcher API -----------------------------------------------------------
    def match(self, queryDescriptors, trainDescriptors, queryKeypoints, trainKeypoints, *, index=None) -> list:
        """Accepted matches, one at most per query, as ``list[cv2.DMatch]`` (``imgIdx = 0``).

        ``index``: a :meth:`index` of these keypoints to reuse, or None."""
        inp = self._inputs(queryDescriptors, trainDescriptors, queryKeypoints, trainKeypoints)
        index = self._index(index, inp)
        d1, d2 = inp.distances.raw1, inp.distances.raw2
        if len(d1) == 0 or len(d2) == 0:
            return []
        if self.constraint == "none":
            return list(self._bf().match(self._cv(d1), self._cv(d2)))
        return _to_dmatches(*auto.match(inp, self.geometry, self.search, self.rule, index=index))

    def knnMatch(self, queryDescriptors, trainDescriptors, queryKeypoints, trainKeypoints, k, *, index=None) -> list:
        """The ``k`` nearest candidates of each query: one list per query, shorter when fewer exist.

        ``index``: a :meth:`index` of these keypoints to reuse, or None."""
        k = as_positive_int(k, "k")
        inp = self._inputs(queryDescriptors, trainDescriptors, queryKeypoints, trainKeypoints)
        index = self._index(index, inp)
        d1, d2 = inp.distances.raw1, inp.distances.raw2
        if self.crossCheck and k != 1:
            raise ValueError(f"k must be 1 when crossCheck is True (as in cv2.BFMatcher), got {k}")
        if len(d1) == 0:
            return []
        if len(d2) == 0:
            return [[] for _ in range(len(d1))]
        if self.constraint == "none":
            return [list(m) for m in self._bf().knnMatch(self._cv(d1), self._cv(d2), k=k)]
        if self.crossCheck:
            rule = AcceptRule(ratio=1.0, mutual=False, pad=0, cross_check=True)
            return _per_query(len(d1), *auto.match(inp, self.geometry, self.search, rule, index=index))
        return _per_query(len(d1), *auto.knn(inp, self.geometry, self.search, k, self.rule, index=index).pairs())

    def radiusMatch(self, queryDescriptors, trainDescriptors, queryKeypoints, trainKeypoints, maxDistance, *,
                    index=None) -> list:
        """All candidates within ``maxDistance`` of each query, nearest first: one list per query.

        ``index``: a :meth:`index` of these keypoints to reuse, or None."""
        max_distance = as_nonnegative(maxDistance, "maxDistance")
        inp = self._inputs(queryDescriptors, trainDescriptors, queryKeypoints, trainKeypoints)
        index = self._index(index, inp)
        d1, d2 = inp.distances.raw1, inp.distances.raw2
        if len(d1) == 0:
            return []
        if len(d2) == 0:
            return [[] for _ in range(len(d1))]
        if self.constraint == "none":
            return [list(m) for m in self._bf().radiusMatch(self._cv(d1), self._cv(d2), max_distance)]
        return _per_query(len(d1), *auto.radius(inp, self.geometry, self.search, max_distance, self.rule,
                                                index=index))

    # -- after matching ----------------------------------------------------------------
    def _pairs_and_points(self, matches, queryKeypoints, trainKeypoints):
        nested, flat = _flatten(matches)
        p1 = keypoints_to_array(queryKeypoints, "queryKeypoints")
        p2 = keypoints_to_array(trainKeypoints, "trainKeypoints")
        return nested, as_index_pairs(pairs_of(flat), len(p1), len(p2), ("queryKeypoints", "trainKeypoints")), p1, p2

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
        nested, pairs, p1, p2 = self._pairs_and_points(matches, queryKeypoints, trainKeypoints)
        return _unflatten(matches, nested, keep_mask(pairs, p1, p2, self.geometry, self.search))

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
        _, pairs, p1, p2 = self._pairs_and_points(matches, queryKeypoints, trainKeypoints)
        return explain(pairs, p1, p2, self.geometry, self.search)


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


def pairs_of(flat) -> np.ndarray:
    """``(K, 2)`` intp ``(queryIdx, trainIdx)`` of a flat list of ``cv2.DMatch``."""
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
