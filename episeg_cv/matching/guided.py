"""Guided matching on arrays: each query is compared only with the keypoints on its segment.

Points are ``(N, 2)`` float64 pixels, descriptors ``(N, D)`` float32 (SIFT,
...) or uint8 (ORB, AKAZE, BRISK: packed bits), and matches are ``(K, 2)``
intp index pairs ``(i1, i2)`` with ``(K,)`` float32 distances, in the same
units as ``cv2.BFMatcher`` reports.

The candidates of each query are found by
:class:`~episeg_cv.matching.candidates.CandidateIndex`, and only those pairs
are scored, one by one in compiled code (:mod:`._kernels`), so that the time
follows the number of candidates. The acceptance rule of
:func:`match_descriptors` is :class:`~episeg_cv.AcceptRule`.

Each public function here is a door: it checks its arguments once and calls
the function of the same job that takes a :class:`MatchInputs` (checked
arrays) and trusts them. :class:`~episeg_cv.SegmentMatcher` calls those
directly, after checking its own arguments under OpenCV's names.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from .._validation import as_descriptor_pair, as_nonnegative, as_norm, as_points_of, as_positive_int
from ..geometry import TwoViewGeometry, as_geometry
from . import small
from .candidates import CandidateIndex
from .config import AcceptRule, SearchConfig, resolve
from .distances import Distances

__all__ = ["MatchInputs", "Neighbors", "GuidedMatches", "knn_descriptors", "radius_descriptors", "guided_matches",
           "match_descriptors", "knn", "radius", "nearest", "match", "check_index"]

NAMES = ("descriptors1", "descriptors2", "points1", "points2")


@dataclass(frozen=True)
class MatchInputs:
    """Checked descriptors and keypoints of one matching call (made by :meth:`check`).

    Attributes
    ----------
    distances : Distances
        The two descriptor arrays and their norm.
    points1, points2 : (N1, 2), (N2, 2) float64
        Keypoint pixels, one per descriptor row.
    """

    distances: Distances
    points1: np.ndarray
    points2: np.ndarray

    @classmethod
    def check(cls, descriptors1, descriptors2, points1, points2, norm, names=NAMES) -> "MatchInputs":
        """Check the arrays against each other and the norm; ``names`` are the arguments' names for errors."""
        norm = as_norm(norm)
        d1, d2 = as_descriptor_pair(descriptors1, descriptors2, norm, names[:2])
        p1 = as_points_of(points1, d1, names[2], names[0])
        p2 = as_points_of(points2, d2, names[3], names[1])
        return cls(Distances(d1, d2, norm), p1, p2)

    def reversed(self) -> "MatchInputs":
        """Image 2 as the queries, image 1 as the keypoints."""
        return MatchInputs(self.distances.reversed(), self.points2, self.points1)


@dataclass(frozen=True)
class Neighbors:
    """The ``k`` nearest candidates of every query (:func:`knn_descriptors`).

    Attributes
    ----------
    indices : (N1, k) intp
        Nearest candidates in image 2, nearest first (ties: smaller index); -1 where there are fewer.
    distances : (N1, k) float32
        Their descriptor distances, as ``cv2.BFMatcher`` reports them; inf where missing.
    counts : (N1,) intp
        Number of candidates of each query.
    column_best : (N2,) intp
        For each keypoint of image 2, the nearest query having it as a candidate, or -1.
    """

    indices: np.ndarray
    distances: np.ndarray
    counts: np.ndarray
    column_best: np.ndarray

    def pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """The neighbours as ``(pairs (K, 2), distances (K,))``, by query, nearest first."""
        i, col = np.nonzero(self.indices >= 0)  # row-major: by query, nearest first
        return np.column_stack([i, self.indices[i, col]]).astype(np.intp), self.distances[i, col]


@dataclass(frozen=True)
class _Scan:
    """One compiled pass over the candidates (scores: squared distance for L2)."""

    indices: np.ndarray
    scores: np.ndarray
    counts: np.ndarray
    column_best: np.ndarray
    column_scores: np.ndarray

    @classmethod
    def empty(cls, n1: int, n2: int, k: int) -> "_Scan":
        """Accumulators for :meth:`CandidateIndex.scan`: nothing found yet."""
        return cls(np.full((n1, k), -1, dtype=np.intp), np.full((n1, k), np.inf, dtype=np.float32),
                   np.zeros(n1, dtype=np.intp), np.full(n2, -1, dtype=np.intp), np.full(n2, np.inf, dtype=np.float32))

    def add(self, index: CandidateIndex, dist: Distances) -> "_Scan":
        """Merge the candidates of ``index`` (its queries and keypoints are rows of ``dist``) into this scan."""
        index.scan(dist.a, dist.b, dist.code, self.indices, self.scores, self.counts, self.column_scores,
                   self.column_best)
        return self


def _scan(index: CandidateIndex, dist: Distances, k: int) -> _Scan:
    """The k nearest candidates of each query, the nearest query of each keypoint, and the counts."""
    return _Scan.empty(len(index.points1), len(index.points2), k).add(index, dist)


def _guided_search(search: SearchConfig) -> SearchConfig:
    if search.constraint == "none":
        raise ValueError("guided matching needs constraint 'segment' or 'line'; use cv2.BFMatcher for 'none'")
    return search


def _index(inputs: MatchInputs, geometry: TwoViewGeometry, search: SearchConfig, bucket_size: int = 64,
           index: CandidateIndex | None = None) -> CandidateIndex:
    """The caller's index (checked by :func:`check_index`), or a new one."""
    if index is not None:
        return index
    return CandidateIndex.build(geometry, inputs.points1, inputs.points2, _guided_search(search), bucket_size)


def check_index(index, inputs: MatchInputs, geometry: TwoViewGeometry, search: SearchConfig):
    """``index`` itself when it was built for these points, geometry and search (or is None); else an error.

    Reusing an index skips the segments and the index build, the part of a call that does not
    depend on the descriptors (about a third of ``match`` at 10k keypoints): for example
    ``knnMatch`` and ``match`` on the same pair. It is checked against the call's inputs, so that a
    stale index cannot give wrong candidates.
    """
    if index is None:
        return None
    if not isinstance(index, CandidateIndex):
        raise TypeError(f"index must be a CandidateIndex or None, got {type(index).__name__}")
    g = index.geometry
    same_geometry = g is geometry or (
        type(g) is type(geometry) and g.image_size1 == geometry.image_size1 and g.image_size2 == geometry.image_size2
        and all(np.array_equal(getattr(g, a), getattr(geometry, a))
                for a in ("infinity_homography", "epipole_homogeneous")))
    if not same_geometry:
        raise ValueError("index was built for another geometry")
    if index.search != _guided_search(search):
        raise ValueError(f"index was built for {index.search!r}, this call searches {search!r}")
    for name, a, b in (("points1", index.points1, inputs.points1), ("points2", index.points2, inputs.points2)):
        if a.shape != b.shape or not np.array_equal(a, b):
            raise ValueError(f"index was built for other {name} (queries: image 1, train: image 2)")
    return index


# -- on checked inputs ---------------------------------------------------------------------------
def knn(inputs: MatchInputs, geometry: TwoViewGeometry, search: SearchConfig, k: int,
        index: CandidateIndex | None = None) -> Neighbors:
    """:func:`knn_descriptors` on checked inputs (``index``: a checked index to reuse, or None)."""
    index = _index(inputs, geometry, search, index=index)
    if k > 2:  # no query has more neighbours than candidates: the (N1, k) arrays need no more columns
        k = max(1, min(k, int(index.candidate_counts().max(initial=0))))
    res = _scan(index, inputs.distances, k)
    found = res.indices >= 0
    dist = np.full(res.indices.shape, np.inf, dtype=np.float32)
    dist[found] = inputs.distances.to_distance(res.scores[found])  # the scores the neighbours were ranked by
    return Neighbors(res.indices, dist, res.counts, res.column_best)


def radius(inputs: MatchInputs, geometry: TwoViewGeometry, search: SearchConfig,
           max_distance: float, index: CandidateIndex | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`radius_descriptors` on checked inputs (``index``: a checked index to reuse, or None)."""
    index = _index(inputs, geometry, search, index=index)
    dist = inputs.distances
    i, j = index.candidate_lists()
    # the scores rank, with float32 rounding: a slack keeps every pair near the boundary for the exact check
    limit = (max_distance**2 if dist.norm == "l2" else max_distance) * (1 + 1e-4) + 1e-6
    near = dist.paired(i, j) <= limit
    i, j = i[near], j[near]
    d = dist.exact(i, j)
    keep = d <= max_distance
    i, j, d = i[keep], j[keep], d[keep]
    o = np.lexsort((j, d, i))
    return np.column_stack([i[o], j[o]]).astype(np.intp), d[o]


def padding_references(rng, n2: int, n_pad: int) -> np.ndarray:
    """The ``n_pad`` padding references among ``n2`` keypoints, sorted: drawn by ``np.random.default_rng(rng)``,
    the same for the same seed (an int seed's draw is kept: a collection draws the same few many times, and
    a draw cost about 60 us, 6 % of matching a pair of 250 keypoints)."""
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool):
        return _seeded_references(int(rng), n2, n_pad).copy()
    return np.sort(np.random.default_rng(rng).choice(n2, n_pad, replace=False))


@functools.lru_cache(maxsize=256)
def _seeded_references(seed: int, n2: int, n_pad: int) -> np.ndarray:
    return np.sort(np.random.default_rng(seed).choice(n2, n_pad, replace=False))


def _ratio(d1: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """``d1 / d2``; 0 where there is no second (``d2 = inf``), inf where ``d2 = 0 < d1``, 1 for ``0 / 0``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.isfinite(d2), np.where(d2 > 0, d1 / d2, np.where(d1 > 0, np.inf, 1.0)), 0.0)


def _keep(ratio_values, mutual_values, ratio, mutual):
    keep = (ratio_values < ratio) if ratio < 1 else np.ones(len(ratio_values), dtype=bool)
    return keep & mutual_values if mutual else keep


def nearest(inputs: MatchInputs, geometry: TwoViewGeometry, search: SearchConfig, rule: AcceptRule, rng=0,
            bucket_size: int = 64, prefilter: bool = False, index: CandidateIndex | None = None):
    """Every query's nearest candidate with its ratio and mutual flag: ``(i, j, ratio, mutual, counts)``.

    With ``prefilter``, the padding references are scored only for the pairs that pass ``rule`` without
    them (padding can only lower ``d2``, so it can only remove pairs): the others keep their ratio to
    the second candidate, which the rule rejects anyway.
    """
    dist = inputs.distances
    p1, p2 = inputs.points1, inputs.points2
    n_pad = min(rule.pad, len(p2))
    if index is None and small.fits(len(p1), len(p2), search, rule, geometry):  # one compiled call, same results
        pad_j = padding_references(rng, len(p2), n_pad) if n_pad and len(p1) else np.zeros(0, dtype=np.int64)
        return small.nearest(inputs, geometry, search, rule, pad_j, prefilter)
    index = _index(inputs, geometry, search, bucket_size, index)
    res = _scan(index, dist, 2)
    i = np.flatnonzero(res.indices[:, 0] >= 0)
    j = res.indices[i, 0]
    s1, s2 = res.scores[i, 0], res.scores[i, 1]
    if rule.cross_check:
        # bounds on z1 are not bounds on z2: the reverse pass uses the whole half-line (0, inf)
        back = CandidateIndex.build(geometry.inverse(), p2, p1, search.replace(depth_range=(0.0, np.inf)), bucket_size)
        rev = _scan(back, dist.reversed(), 1)
        mutual = rev.indices[j, 0] == i
    else:
        mutual = res.column_best[j] == i
    if n_pad and len(i):
        pad_j = padding_references(rng, len(p2), n_pad)
        r = np.arange(len(i)) if not prefilter else \
            np.flatnonzero(_keep(_ratio(dist.to_distance(s1.astype(np.float64)),
                                        dist.to_distance(s2.astype(np.float64))), mutual,
                                 rule.ratio, rule.mutual or rule.cross_check))
        s2 = s2.copy()
        s2[r] = np.minimum(s2[r], dist.nearest_excluding(i[r], pad_j, j[r]))
    ratio = _ratio(dist.to_distance(s1.astype(np.float64)), dist.to_distance(s2.astype(np.float64)))
    return i, j, ratio, mutual, res.counts


def match(inputs: MatchInputs, geometry: TwoViewGeometry, search: SearchConfig, rule: AcceptRule, rng=0,
          bucket_size: int = 64, index: CandidateIndex | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`match_descriptors` on checked inputs (``index``: a checked index to reuse, or None)."""
    i, j, r, mu, _ = nearest(inputs, geometry, search, rule, rng, bucket_size, prefilter=True, index=index)
    keep = _keep(r, mu, rule.ratio, rule.mutual or rule.cross_check)
    i, j = i[keep], j[keep]
    return np.column_stack([i, j]).astype(np.intp), inputs.distances.exact(i, j)


# -- the doors ---------------------------------------------------------------------------------
def knn_descriptors(descriptors1, descriptors2, points1, points2, geometry, *, k=2, norm="l2",
                    search: SearchConfig | None = None, index: CandidateIndex | None = None, **options) -> Neighbors:
    """The ``k`` nearest candidates of each query on its segment (or line).

    Parameters
    ----------
    descriptors1, descriptors2 : (N1, D), (N2, D) array_like
        float32 (or float64) for L1/L2, uint8 for Hamming; same dtype and width.
    points1, points2 : (N1, 2), (N2, 2) array_like
        Keypoint pixels (OpenCV convention, pixel centres at integers).
    geometry : TwoViewGeometry or FundamentalGeometry
        Known pose, ``X2 = R @ X1 + t`` (or an oriented fundamental matrix).
    k : int
        Neighbours per query (>= 1).
    norm : {"l2", "l1", "l2sqr", "hamming"} or cv2.NORM_*
    search : SearchConfig, optional
        The constraint (``"segment"`` or ``"line"``), ``tol`` (pixels, or
        ``"auto"``: :func:`~episeg_cv.estimate_band`) and ``depth_range``; its
        fields may also be given as keywords. A geometry with a covariance
        (:meth:`~episeg_cv.TwoViewGeometry.with_covariance`) is searched in
        per-query bands, ``tol`` then being the keypoint noise.
    index : CandidateIndex, optional
        An index already built for these points, this geometry and this
        search (``CandidateIndex(geometry, points1, points2, search=search)``),
        to reuse across calls on the same pair (``knn_descriptors`` then
        ``match_descriptors``, ...): it skips the segments and the index
        build. Checked against the call; ``ValueError`` if it does not fit.
        Only with a numeric ``tol`` and a geometry without covariance.

    Returns
    -------
    Neighbors
        ``indices`` and ``distances`` of shape ``(N1, k')``, nearest first, with ``k'`` the
        smaller of ``k`` and the largest number of candidates of any query (so that a huge
        ``k`` costs no memory).

    Raises
    ------
    ValueError, TypeError
        On bad input (shapes, dtypes, norms, ``k < 1``, ``tol < 0``, an unknown option).

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv import TwoViewGeometry
    >>> K = [[100, 0, 50], [0, 100, 50], [0, 0, 1]]
    >>> g = TwoViewGeometry(K, K, np.eye(3), [-1, 0, 0], image_size1=(100, 100), image_size2=(100, 100))
    >>> d1 = np.array([[1, 0, 0, 0]], np.float32)
    >>> d2 = np.array([[0, 1, 0, 0], [1, 1, 0, 0], [1, 0, 0, 0]], np.float32)
    >>> nb = knn_descriptors(d1, d2, [[60.0, 20.0]], [[40.0, 20.0], [30.0, 20.0], [80.0, 20.0]], g, k=2)
    >>> nb.indices.tolist(), nb.distances.astype(float).round(3).tolist()   # keypoint 2: wrong side
    ([[1, 0]], [[1.0, 1.414]])
    """
    from . import auto  # (auto builds on this module: tol="auto" and covariance bands resolved there)
    search, _ = resolve(search, None, options, takes_rule=False)
    inputs = MatchInputs.check(descriptors1, descriptors2, points1, points2, norm)
    k = as_positive_int(k, "k")
    geometry = as_geometry(geometry)
    return auto.knn(inputs, geometry, search, k, index=check_index(index, inputs, geometry, search))


def radius_descriptors(descriptors1, descriptors2, points1, points2, geometry, *, max_distance, norm="l2",
                       search: SearchConfig | None = None, index: CandidateIndex | None = None,
                       **options) -> tuple[np.ndarray, np.ndarray]:
    """All candidates within ``max_distance`` (descriptor units): ``(pairs (K, 2), distances (K,))``,
    sorted by query, then by distance. Other parameters as in :func:`knn_descriptors`."""
    from . import auto
    search, _ = resolve(search, None, options, takes_rule=False)
    inputs = MatchInputs.check(descriptors1, descriptors2, points1, points2, norm)
    geometry = as_geometry(geometry)
    return auto.radius(inputs, geometry, search, as_nonnegative(max_distance, "maxDistance"),
                       index=check_index(index, inputs, geometry, search))


@dataclass(frozen=True)
class GuidedMatches:
    """Every query's nearest candidate, with what the acceptance rule thresholds on.

    Attributes
    ----------
    pairs : (K, 2) intp
        ``(i1, i2)``: each query with at least one candidate and its nearest one, sorted by ``i1``.
    distances : (K,) float32
        Their descriptor distances, as ``cv2`` reports them.
    ratio : (K,) float64
        ``d1 / d2``, with ``d2`` the distance to the second reference
        descriptor (second candidate, or nearest random pad keypoint); 0 when
        there is none.
    mutual : (K,) bool
        The query is also the nearest to its keypoint (within the candidate
        relation, or both directions with ``cross_check``).
    candidates : (N1,) intp
        Number of candidates of every query.
    rule : AcceptRule
        The rule the ratios and mutual flags were computed under; the default of :meth:`keep`.
    estimate : BandEstimate or None
        With ``tol="auto"``: the band and the geometry used (:func:`~episeg_cv.estimate_band`).
    """

    pairs: np.ndarray
    distances: np.ndarray
    ratio: np.ndarray
    mutual: np.ndarray
    candidates: np.ndarray
    rule: AcceptRule = AcceptRule()
    estimate: object = None

    def keep(self, ratio: float | None = None, mutual: bool | None = None) -> np.ndarray:
        """(K,) bool: which pairs the rule keeps. ``ratio = 1`` disables the ratio test.

        ``ratio`` and ``mutual`` default to :attr:`rule`'s (with ``cross_check``, mutual is implied).
        """
        ratio = self.rule.ratio if ratio is None else ratio
        mutual = (self.rule.mutual or self.rule.cross_check) if mutual is None else mutual
        return _keep(self.ratio, self.mutual, ratio, mutual)

    def accept(self, ratio: float | None = None, mutual: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The matches kept by the rule: ``(pairs, distances)``."""
        keep = self.keep(ratio, mutual)
        return self.pairs[keep], self.distances[keep]


def guided_matches(descriptors1, descriptors2, points1, points2, geometry, *, norm="l2",
                   search: SearchConfig | None = None, rule: AcceptRule | None = None, rng=0, bucket_size=64,
                   index: CandidateIndex | None = None, **options) -> GuidedMatches:
    """Nearest candidate of every query on its segment (or line), with its ratio and mutual flags.

    The thresholds of :func:`match_descriptors` are then a cheap filter
    (:meth:`GuidedMatches.accept`), which is how ``benchmarks/compare.py``
    sweeps precision-recall curves. Parameters as in :func:`match_descriptors`.
    """
    from . import auto
    search, rule = resolve(search, rule, options)
    inputs = MatchInputs.check(descriptors1, descriptors2, points1, points2, norm)
    geometry = as_geometry(geometry)
    (i, j, ratio, mutual, counts), plan = auto.nearest(inputs, geometry, search, rule, rng,
                                                       as_positive_int(bucket_size, "bucket_size"),
                                                       index=check_index(index, inputs, geometry, search))
    return GuidedMatches(np.column_stack([i, j]).astype(np.intp), inputs.distances.exact(i, j), ratio, mutual, counts,
                         rule, plan.estimate)


def match_descriptors(descriptors1, descriptors2, points1, points2, geometry, *, norm="l2",
                      search: SearchConfig | None = None, rule: AcceptRule | None = None, rng=0, bucket_size=64,
                      index: CandidateIndex | None = None, **options) -> tuple[np.ndarray, np.ndarray]:
    """Match descriptors, comparing each query only with the keypoints on its epipolar segment.

    Parameters
    ----------
    descriptors1, descriptors2, points1, points2, geometry, norm, search
        As in :func:`knn_descriptors`.
    rule : AcceptRule, optional
        ``ratio``, ``mutual``, ``pad`` and ``cross_check`` (see
        :class:`~episeg_cv.AcceptRule`); its fields may also be given as keywords.
    rng : int or numpy.random.Generator, optional
        Seed for the padding draw (fixed by default, so results repeat).
    bucket_size : int, optional
        Queries per pencil bucket of the candidate index (speed only; results do not change).
    index : CandidateIndex, optional
        An index to reuse, as in :func:`knn_descriptors` (then ``bucket_size`` is the index's).
    **options
        Fields of :class:`~episeg_cv.SearchConfig` or :class:`~episeg_cv.AcceptRule`
        (``tol=4``, ``ratio=0.8``, ...); they override ``search`` and ``rule``.

    Returns
    -------
    pairs : (K, 2) intp
        ``(i1, i2)`` indices, sorted by ``i1``.
    distances : (K,) float32
        Descriptor distances, as ``cv2.BFMatcher`` reports them.

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv import TwoViewGeometry
    >>> K = [[100, 0, 50], [0, 100, 50], [0, 0, 1]]
    >>> g = TwoViewGeometry(K, K, np.eye(3), [-1, 0, 0], image_size1=(100, 100), image_size2=(100, 100))
    >>> p1 = np.array([[60.0, 20.0], [60.0, 70.0]])
    >>> p2 = np.array([[40.0, 20.0], [80.0, 70.0]])        # the second is on the wrong side of the row
    >>> d = np.eye(2, 8, dtype=np.float32)
    >>> pairs, dist = match_descriptors(d, d, p1, p2, g, pad=0)
    >>> pairs.tolist(), dist.tolist()
    ([[0, 0]], [0.0])
    """
    from . import auto
    search, rule = resolve(search, rule, options)
    inputs = MatchInputs.check(descriptors1, descriptors2, points1, points2, norm)
    geometry = as_geometry(geometry)
    return auto.match(inputs, geometry, search, rule, rng, as_positive_int(bucket_size, "bucket_size"),
                      index=check_index(index, inputs, geometry, search))
