"""Guided matching and outlier rejection on arrays: the core of :class:`SegmentMatcher`.

Points are ``(N, 2)`` float64 pixels, descriptors ``(N, D)`` float32 (SIFT,
...) or uint8 (ORB, AKAZE, BRISK: packed bits), and matches are ``(K, 2)``
intp index pairs ``(i1, i2)`` with ``(K,)`` float32 distances, in the same
units as ``cv2.BFMatcher`` reports.

Guided matching compares each query only with the keypoints of image 2 that
lie on its epipolar segment (or line), found by
:class:`~episeg_cv.candidates.CandidateIndex`, and scores the descriptors of
those pairs only, one by one in compiled code (:mod:`episeg_cv._kernels`), so
that the time follows the number of candidates.

The acceptance rule of :func:`match_descriptors`
-------------------------------------------------
A query ``i`` is matched to its nearest candidate ``j`` (distance ``d1``) when

1. ``mutual``: ``i`` is also the nearest, among the queries that have ``j``
   as a candidate, to ``j``; and
2. ``ratio``: ``d1 < ratio * d2``, where ``d2`` is the distance to the
   second-nearest *reference* descriptor: the second candidate, or the
   nearest of ``pad`` keypoints of image 2 drawn at random (the same for all
   queries, ``j`` itself excluded), whichever is nearer.

A ratio test inside a restricted candidate set alone lets every query with a
single candidate through: on a prototype, precision fell from 0.95 to 0.73.
The random padding (Theia pads guided matching the same way) gives every
query a reference that does not depend on how many candidates it has, at the
cost of one ``N1 x pad`` product instead of the ``N1 x N2`` global second
neighbour. The defaults, mutual, ``ratio = 0.68`` and ``pad = 128``, were
chosen on the precision-recall benchmark (``benchmarks/compare.py``, see
``benchmarks/results/compare.md``): of the rules tried it had the most
correct matches at 95 % precision and, after the exact global second
neighbour, at 99 %. The largest ratio that keeps precision at or above 0.95
on every scene and on Motorcycle is 0.69; the default is one step (0.01)
below it, for margin.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from . import _kernels
from ._validation import as_nonnegative, as_points
from .candidates import CandidateIndex, check_constraint
from .geometry import Rejection, TwoViewGeometry, _point_segment_distance

__all__ = ["match_descriptors", "guided_matches", "GuidedMatches", "knn_descriptors", "radius_descriptors", "filter_pairs", "explain_pairs",
           "GuidedResult", "DEFAULT_RATIO", "DEFAULT_PAD"]

#: Default ratio of the acceptance rule (chosen on the benchmark).
DEFAULT_RATIO = 0.68
#: Default number of random reference descriptors for the ratio test.
DEFAULT_PAD = 128

_NORMS = {cv2.NORM_L1: "l1", cv2.NORM_L2: "l2", cv2.NORM_L2SQR: "l2sqr", cv2.NORM_HAMMING: "hamming",
          "l1": "l1", "l2": "l2", "l2sqr": "l2sqr", "hamming": "hamming"}


def check_norm(norm) -> str:
    key = norm.lower() if isinstance(norm, str) else norm
    if isinstance(key, (bool, np.bool_)) or key not in _NORMS:
        raise ValueError("normType must be cv2.NORM_L1, cv2.NORM_L2, cv2.NORM_L2SQR or cv2.NORM_HAMMING "
                         f"(or 'l1', 'l2', 'l2sqr', 'hamming'), got {norm!r}")
    return _NORMS[key]


def check_descriptors(descriptors1, descriptors2, norm: str, names=("descriptors1", "descriptors2")):
    """Validate a pair of descriptor arrays against each other and the norm; returns them as arrays."""
    out = []
    for name, d in zip(names, (descriptors1, descriptors2)):
        if d is None:  # what cv2 detectors return for no keypoints
            other = descriptors2 if name == names[0] else descriptors1
            other = np.asarray(other) if other is not None else np.zeros((0, 0), np.float32)
            d = np.zeros((0, other.shape[1] if other.ndim == 2 else 0), dtype=other.dtype)
        d = np.asarray(d)
        if d.dtype not in (np.float32, np.float64, np.uint8):
            raise TypeError(f"{name} must be float32 or uint8 (as OpenCV's detectors give), got dtype {d.dtype}")
        if d.size == 0:
            d = d.reshape(0, d.shape[1] if d.ndim == 2 else 0)
            if norm == "hamming":
                d = d.astype(np.uint8)
        if d.ndim != 2:
            raise ValueError(f"{name} must have shape (N, D), got shape {d.shape}")
        if d.dtype != np.uint8 and d.size and not _all_finite(d):
            raise ValueError(f"{name} must be finite, got NaN or inf")
        out.append(d)
    d1, d2 = out
    if d1.shape[0] and d2.shape[0]:
        if d1.dtype != d2.dtype:
            raise TypeError(f"{names[0]} and {names[1]} must have the same dtype, got {d1.dtype} and {d2.dtype}")
        if d1.shape[1] != d2.shape[1]:
            raise ValueError(f"{names[0]} and {names[1]} must have the same width, got {d1.shape[1]} and {d2.shape[1]}")
    for name, d in zip(names, (d1, d2)):
        if d.shape[0] and norm == "hamming" and d.dtype != np.uint8:
            raise TypeError(f"{name}: NORM_HAMMING needs uint8 (binary) descriptors, got {d.dtype}")
    return d1, d2


def _all_finite(d: np.ndarray) -> bool:
    """``np.all(np.isfinite(d))`` without an ``(N, D)`` boolean array: min and max propagate NaN, and
    an infinity is one of them."""
    return bool(np.isfinite(d.min()) and np.isfinite(d.max()))


def _check_points(points, descriptors, name, dname):
    p = as_points(points, name)
    if p.shape[0] != descriptors.shape[0]:
        raise ValueError(f"{name} has {p.shape[0]} keypoints but {dname} has {descriptors.shape[0]} rows")
    return p


class _Distances:
    """Descriptor scores, computed pair by pair in compiled code (:mod:`episeg_cv._kernels`).

    Scores increase with the distance: squared distance for L2, the distance itself for L1 and
    Hamming, in float32. They rank candidates; :meth:`exact` gives the distances ``cv2`` reports.
    """

    def __init__(self, d1: np.ndarray, d2: np.ndarray, norm: str):
        self.norm = norm
        self.code = _kernels.NORM_CODES[norm]
        self.raw1, self.raw2 = d1, d2
        if norm == "hamming":
            self.a, self.b = _kernels.as_words(d1), _kernels.as_words(d2)
        else:
            self.a = np.ascontiguousarray(d1, dtype=np.float32)
            self.b = np.ascontiguousarray(d2, dtype=np.float32)

    def paired(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """``(K,)`` scores of the pairs ``(i[k], j[k])``."""
        return _kernels.paired_scores(self.a, self.b, np.asarray(i, np.int64), np.asarray(j, np.int64), self.code)

    def nearest_excluding(self, qi: np.ndarray, tj: np.ndarray, exclude: np.ndarray, chunk: int = 1024) -> np.ndarray:
        """``(len(qi),)`` smallest score of each query ``qi[r]`` over the keypoints ``tj`` (sorted), leaving out
        ``exclude[r]``; inf when nothing is left.

        Every query against the same keypoints is a dense product: for L2 it is done with BLAS, in
        row chunks with reused buffers (fresh ``len(qi) x len(tj)`` arrays cost more in page faults
        than the product on a VM), and the exclusion found by ``searchsorted``.
        """
        qi, tj, exclude = (np.asarray(v, dtype=np.int64) for v in (qi, tj, exclude))
        if self.norm not in ("l2", "l2sqr"):
            return _kernels.nearest_excluding(self.a, self.b, qi, tj, exclude, self.code)
        out = np.empty(len(qi), dtype=np.float32)
        if len(qi) == 0 or len(tj) == 0:
            out.fill(np.inf)
            return out
        pos = np.minimum(np.searchsorted(tj, exclude), len(tj) - 1)
        hit = tj[pos] == exclude
        b = self.b[tj]
        bt = np.ascontiguousarray(b.T)
        bb = np.einsum("ij,ij->i", b, b)[None, :]
        n = min(chunk, len(qi))
        rows = np.empty((n, self.a.shape[1]), dtype=np.float32)
        prod = np.empty((n, len(tj)), dtype=np.float32)
        for a in range(0, len(qi), chunk):
            z = min(a + chunk, len(qi))
            r = rows[:z - a]
            np.take(self.a, qi[a:z], axis=0, out=r, mode="clip")
            p = np.matmul(r, bt, out=prod[:z - a])
            p *= -2.0  # |a|^2 + |b|^2 - 2 a.b, clamped at 0 (rounding)
            p += np.einsum("ij,ij->i", r, r)[:, None]
            p += bb
            np.maximum(p, 0.0, out=p)
            h = np.flatnonzero(hit[a:z])
            p[h, pos[a:z][h]] = np.inf
            np.min(p, axis=1, out=out[a:z])
        return out

    def to_distance(self, scores: np.ndarray) -> np.ndarray:
        return np.sqrt(scores) if self.norm == "l2" else scores

    def exact(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Paired distances ``d(i[k], j[k])`` as float32, computed directly (as ``cv2`` reports them)."""
        return _exact(self.raw1, self.raw2, self.norm, i, j)


def _exact(raw1: np.ndarray, raw2: np.ndarray, norm: str, i: np.ndarray, j: np.ndarray,
           chunk: int = 4096) -> np.ndarray:
    """Paired distances ``d(i[k], j[k])`` as float32, computed directly (as ``cv2`` reports them).

    In chunks, with the gathered rows in buffers reused from chunk to chunk.
    """
    out = np.empty(len(i), dtype=np.float32)
    if len(i) == 0:
        return out
    n = min(chunk, len(i))
    if norm == "hamming":
        buf = np.empty((n, raw1.shape[1]), dtype=np.uint8)
        for a in range(0, len(i), chunk):
            z = min(a + chunk, len(i))
            np.bitwise_xor(raw1[i[a:z]], raw2[j[a:z]], out=buf[:z - a])
            out[a:z] = np.unpackbits(buf[:z - a], axis=1).sum(1)
        return out
    # float32 arithmetic, as cv2 does (uint8 descriptors are widened first)
    x = np.empty((n, raw1.shape[1]), dtype=np.float32)
    y = np.empty_like(x)
    for a in range(0, len(i), chunk):
        z = min(a + chunk, len(i))
        xa, ya = x[:z - a], y[:z - a]
        for raw, rows, buf in ((raw1, i[a:z], xa), (raw2, j[a:z], ya)):
            if raw.dtype == np.float32:
                np.take(raw, rows, axis=0, out=buf, mode="clip")  # (the default 'raise' buffers)
            else:
                np.copyto(buf, raw[rows], casting="unsafe")
        np.subtract(xa, ya, out=xa)
        if norm == "l1":
            np.abs(xa, out=xa)
            out[a:z] = xa.sum(1, dtype=np.float32)
        else:
            out[a:z] = np.einsum("ij,ij->i", xa, xa)
    return np.sqrt(out, out=out) if norm == "l2" else out


@dataclass(frozen=True)
class GuidedResult:
    """The nearest candidates of every query, from one scan of the candidates.

    Attributes
    ----------
    indices : (N1, k) intp
        Nearest candidates in image 2, nearest first; -1 where there are fewer.
    scores : (N1, k) float32
        Their scores (squared distance for L2), inf where missing.
    counts : (N1,) intp
        Number of candidates of each query.
    column_best : (N2,) intp
        For each keypoint of image 2, the nearest query having it as a
        candidate, or -1.
    """

    indices: np.ndarray
    scores: np.ndarray
    counts: np.ndarray
    column_best: np.ndarray


def _scan(index: CandidateIndex, dist: _Distances, k: int) -> GuidedResult:
    """One compiled pass over the candidates: the k nearest of each query, the nearest query of each
    keypoint, and the candidate counts."""
    n1, n2 = len(index.points1), len(index.points2)
    idx = np.full((n1, k), -1, dtype=np.intp)
    sc = np.full((n1, k), np.inf, dtype=np.float32)
    counts = np.zeros(n1, dtype=np.intp)
    col_s = np.full(n2, np.inf, dtype=np.float32)
    col_i = np.full(n2, -1, dtype=np.intp)
    b_sorted = np.take(dist.b, index.t_sorted, axis=0)  # each slice's descriptors in contiguous memory
    index._run(_kernels.knn_scan, dist.a, b_sorted, dist.code, idx, sc, counts, col_s, col_i)
    return GuidedResult(idx, sc, counts, col_i)


def _check_geometry(geometry):
    if not isinstance(geometry, TwoViewGeometry):
        raise TypeError(f"geometry must be a TwoViewGeometry, got {type(geometry).__name__}")


def _prepare(descriptors1, descriptors2, points1, points2, geometry, norm, tol, constraint):
    _check_geometry(geometry)
    norm = check_norm(norm)
    constraint = check_constraint(constraint)
    tol = as_nonnegative(tol, "tol")
    d1, d2 = check_descriptors(descriptors1, descriptors2, norm)
    p1 = _check_points(points1, d1, "points1", "descriptors1")
    p2 = _check_points(points2, d2, "points2", "descriptors2")
    return d1, d2, p1, p2, norm, constraint, tol


def knn_descriptors(descriptors1, descriptors2, points1, points2, geometry, *, k=2, norm="l2", tol=2.0,
                    depth_range=(0.0, np.inf), constraint="segment"):
    """The ``k`` nearest candidates of each query on its segment (or line).

    Parameters
    ----------
    descriptors1, descriptors2 : (N1, D), (N2, D) array_like
        float32 (or float64) for L1/L2, uint8 for Hamming; same dtype and width.
    points1, points2 : (N1, 2), (N2, 2) array_like
        Keypoint pixels (OpenCV convention, pixel centres at integers).
    geometry : TwoViewGeometry
        Known pose, ``X2 = R @ X1 + t``.
    k : int
        Neighbours per query (>= 1).
    norm : {"l2", "l1", "l2sqr", "hamming"} or cv2.NORM_*
    tol : float
        Pixel distance to the segment (or line) within which a keypoint is a candidate.
    depth_range : (zmin, zmax)
        Depth bounds in camera 1, see :meth:`TwoViewGeometry.segments`.
    constraint : {"segment", "line"}
        ``"line"`` is plain epipolar filtering, by the same code path.

    Returns
    -------
    GuidedResult
        ``indices``/``scores`` of shape ``(N1, k)``; convert scores to distances
        with ``np.sqrt`` for L2.

    Raises
    ------
    ValueError, TypeError
        On bad input (shapes, dtypes, norms, ``k < 1``, ``tol < 0``).
    """
    d1, d2, p1, p2, norm, constraint, tol = _prepare(descriptors1, descriptors2, points1, points2,
                                                    geometry, norm, tol, constraint)
    k = _check_k(k)
    if constraint == "none":
        raise ValueError("knn_descriptors needs constraint 'segment' or 'line'; use cv2.BFMatcher for 'none'")
    index = CandidateIndex(geometry, p1, p2, tol=tol, depth_range=depth_range, constraint=constraint)
    return _scan(index, _Distances(d1, d2, norm), k)


def _check_k(k):
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)):
        raise TypeError(f"k must be an integer >= 1, got {type(k).__name__}")
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    return int(k)


def radius_descriptors(descriptors1, descriptors2, points1, points2, geometry, *, max_distance, norm="l2",
                       tol=2.0, depth_range=(0.0, np.inf), constraint="segment"):
    """All candidates within ``max_distance`` (descriptor units): ``(pairs (K, 2), distances (K,))``,
    sorted by query, then by distance."""
    d1, d2, p1, p2, norm, constraint, tol = _prepare(descriptors1, descriptors2, points1, points2,
                                                    geometry, norm, tol, constraint)
    max_distance = as_nonnegative(max_distance, "maxDistance")
    index = CandidateIndex(geometry, p1, p2, tol=tol, depth_range=depth_range, constraint=constraint)
    dist = _Distances(d1, d2, norm)
    i, j = index._run(_kernels.candidate_pairs)
    # the scores rank, with float32 rounding: a slack keeps every pair near the boundary for the exact check
    limit = (max_distance**2 if norm == "l2" else max_distance) * (1 + 1e-4) + 1e-6
    near = dist.paired(i, j) <= limit
    i, j = i[near], j[near]
    d = dist.exact(i, j)
    keep = d <= max_distance
    i, j, d = i[keep], j[keep], d[keep]
    o = np.lexsort((j, d, i))
    return np.column_stack([i[o], j[o]]).astype(np.intp), d[o]


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
    """

    pairs: np.ndarray
    distances: np.ndarray
    ratio: np.ndarray
    mutual: np.ndarray
    candidates: np.ndarray

    def keep(self, ratio: float = DEFAULT_RATIO, mutual: bool = True) -> np.ndarray:
        """(K,) bool: which pairs the rule keeps. ``ratio = 1`` disables the ratio test."""
        return _keep(self.ratio, self.mutual, ratio, mutual)

    def accept(self, ratio: float = DEFAULT_RATIO, mutual: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """The matches kept by the rule: ``(pairs, distances)``."""
        keep = self.keep(ratio, mutual)
        return self.pairs[keep], self.distances[keep]


def guided_matches(descriptors1, descriptors2, points1, points2, geometry, *, norm="l2", tol=2.0,
                   depth_range=(0.0, np.inf), constraint="segment", pad=DEFAULT_PAD, cross_check=False, rng=0,
                   bucket_size=64) -> GuidedMatches:
    """Nearest candidate of every query on its segment (or line), with its ratio and mutual flags.

    The thresholds of :func:`match_descriptors` are then a cheap filter
    (:meth:`GuidedMatches.accept`), which is how ``benchmarks/compare.py``
    sweeps precision-recall curves. Parameters as in :func:`match_descriptors`.
    """
    i, j, ratio, mutual, counts, dist = _guided(descriptors1, descriptors2, points1, points2, geometry, norm=norm,
                                                tol=tol, depth_range=depth_range, constraint=constraint, pad=pad,
                                                cross_check=cross_check, rng=rng, bucket_size=bucket_size)
    return GuidedMatches(np.column_stack([i, j]).astype(np.intp), dist.exact(i, j), ratio, mutual, counts)


def _keep(ratio_values, mutual_values, ratio, mutual):
    keep = (ratio_values < ratio) if ratio < 1 else np.ones(len(ratio_values), dtype=bool)
    return keep & mutual_values if mutual else keep


def _guided(descriptors1, descriptors2, points1, points2, geometry, *, norm, tol, depth_range, constraint, pad,
            cross_check, rng, bucket_size, rule=None):
    """:func:`guided_matches` without the exact distances: ``(i, j, ratio, mutual, counts, distances)``, the
    last the :class:`_Distances` to compute them with (only for the pairs kept, in :func:`match_descriptors`).

    With ``rule = (ratio, mutual)``, the padding references are scored only for the pairs that pass the
    rule without them (padding can only lower ``d2``, so it can only remove pairs): the others keep
    their ratio to the second candidate, which the rule rejects anyway.
    """
    d1, d2, p1, p2, norm, constraint, tol = _prepare(descriptors1, descriptors2, points1, points2,
                                                    geometry, norm, tol, constraint)
    if isinstance(pad, (bool, np.bool_)) or not isinstance(pad, (int, np.integer)) or pad < 0:
        raise ValueError(f"pad must be an integer >= 0, got {pad!r}")
    if constraint == "none":
        raise ValueError("guided matching needs constraint 'segment' or 'line'; use cv2.BFMatcher for 'none'")
    dist = _Distances(d1, d2, norm)
    index = CandidateIndex(geometry, p1, p2, tol=tol, depth_range=depth_range, constraint=constraint,
                           bucket_size=bucket_size)
    res = _scan(index, dist, 2)
    i = np.flatnonzero(res.indices[:, 0] >= 0)
    j = res.indices[i, 0]
    s1, s2 = res.scores[i, 0], res.scores[i, 1]
    if cross_check:
        # bounds on z1 are not bounds on z2: the reverse pass uses the whole half-line (0, inf)
        back = CandidateIndex(geometry.inverse(), p2, p1, tol=tol, constraint=constraint, bucket_size=bucket_size)
        rev = _scan(back, _Distances(d2, d1, norm), 1)
        mutual = rev.indices[j, 0] == i
    else:
        mutual = res.column_best[j] == i
    n_pad = min(int(pad), len(p2))
    if n_pad and len(i):
        pad_j = np.sort(np.random.default_rng(rng).choice(len(p2), n_pad, replace=False))
        r = np.arange(len(i)) if rule is None else \
            np.flatnonzero(_keep(_ratio(dist.to_distance(s1.astype(np.float64)),
                                        dist.to_distance(s2.astype(np.float64))), mutual, *rule))
        s2 = s2.copy()
        s2[r] = np.minimum(s2[r], dist.nearest_excluding(i[r], pad_j, j[r]))
    ratio = _ratio(dist.to_distance(s1.astype(np.float64)), dist.to_distance(s2.astype(np.float64)))
    return i, j, ratio, mutual, res.counts, dist


def _ratio(d1: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """``d1 / d2``; 0 where there is no second (``d2 = inf``), inf where ``d2 = 0 < d1``, 1 for ``0 / 0``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.isfinite(d2), np.where(d2 > 0, d1 / d2, np.where(d1 > 0, np.inf, 1.0)), 0.0)


def match_descriptors(descriptors1, descriptors2, points1, points2, geometry, *, norm="l2", tol=2.0,
                      depth_range=(0.0, np.inf), constraint="segment", ratio=DEFAULT_RATIO, mutual=True,
                      pad=DEFAULT_PAD, cross_check=False, rng=0, bucket_size=64):
    """Match descriptors, comparing each query only with the keypoints on its epipolar segment.

    Parameters
    ----------
    descriptors1, descriptors2, points1, points2, geometry, norm, tol, depth_range, constraint
        As in :func:`knn_descriptors`.
    ratio : float in (0, 1], optional
        Ratio test against the second reference descriptor (see the module
        docstring). 1.0 disables it.
    mutual : bool, optional
        Keep a match only if the query is also the nearest to its keypoint
        among the queries that have that keypoint as a candidate.
    pad : int, optional
        Random keypoints of image 2 added to the ratio test's references (0 for none).
    cross_check : bool, optional
        With ``mutual``, check it in both directions, the reverse one with
        ``geometry.inverse()`` (its own segments in image 1).
    rng : int or numpy.random.Generator, optional
        Seed for the padding draw (fixed by default, so results repeat).
    bucket_size : int, optional
        Queries per pencil bucket of the candidate index (speed only; results do not change).

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
    ratio = check_ratio(ratio, "ratio")
    i, j, r, mu, _, dist = _guided(descriptors1, descriptors2, points1, points2, geometry, norm=norm, tol=tol,
                                   depth_range=depth_range, constraint=constraint, pad=pad, cross_check=cross_check,
                                   rng=rng, bucket_size=bucket_size,
                                   rule=(ratio, mutual or cross_check))
    keep = _keep(r, mu, ratio, mutual or cross_check)
    i, j = i[keep], j[keep]
    return np.column_stack([i, j]).astype(np.intp), dist.exact(i, j)


def check_ratio(value, name: str) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not 0 < value <= 1:
        raise ValueError(f"{name} must be in (0, 1], got {value!r}")
    return float(value)


def filter_pairs(pairs, points1, points2, geometry, *, tol=2.0, depth_range=(0.0, np.inf), constraint="segment"):
    """Outlier rejection after matching: which pairs satisfy the constraint.

    Parameters
    ----------
    pairs : (K, 2) array_like of int
        ``(i1, i2)`` indices into ``points1`` and ``points2``.
    points1, points2 : (N1, 2), (N2, 2) array_like
    geometry : TwoViewGeometry
    tol : float
        Pixel distance to the segment (or line).
    depth_range : (zmin, zmax)
    constraint : {"segment", "line", "none"}

    Returns
    -------
    (K,) bool
        True where the pair is kept.

    Raises
    ------
    ValueError
        A pair index out of range, or other bad input.
    """
    _check_geometry(geometry)
    constraint = check_constraint(constraint)
    tol = as_nonnegative(tol, "tol")
    pairs, p1, p2 = _check_pairs(pairs, points1, points2)
    if constraint == "none":
        return np.ones(len(pairs), dtype=bool)
    seg = geometry.segments(p1, depth_range, margin=tol)
    i, j = pairs[:, 0], pairs[:, 1]
    # 1-D gathers (one column at a time) are several times faster than gathering rows of (N, 2) arrays
    y0, y1 = np.ascontiguousarray(p2[:, 0])[j], np.ascontiguousarray(p2[:, 1])[j]
    l0, l1, l2 = (np.ascontiguousarray(seg.line[:, c])[i] for c in range(3))
    with np.errstate(invalid="ignore"):
        line_distance = np.abs(l0 * y0 + l1 * y1 + l2)
    if constraint == "line":
        return line_distance <= tol  # NaN line: False
    # A segment lies on its line, so only pairs near the line need the distance to the segment; the
    # margin covers rounding, and a NaN line (undefined: the query maps to the epipole) is kept.
    near = np.flatnonzero(~(line_distance > tol * (1 + 1e-6) + 1e-6) & seg.valid[i])
    keep = np.zeros(len(pairs), dtype=bool)
    if near.size:
        ii = i[near]
        d = _point_segment_distance(p2[j[near]], np.nan_to_num(seg.start[ii]), np.nan_to_num(seg.end[ii]))
        keep[near] = d <= tol
    return keep


def _check_pairs(pairs, points1, points2):
    p1, p2 = as_points(points1, "points1"), as_points(points2, "points2")
    arr = np.asarray(pairs)
    if arr.size == 0:
        arr = np.zeros((0, 2), dtype=np.intp)
    if arr.ndim != 2 or arr.shape[1] != 2 or not (np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"pairs must be a (K, 2) integer array, got shape {arr.shape} and dtype {arr.dtype}")
    for col, n, name in ((0, len(p1), "points1"), (1, len(p2), "points2")):
        if len(arr) and (arr[:, col].min() < 0 or arr[:, col].max() >= n):  # then find the first offender
            bad = (arr[:, col] < 0) | (arr[:, col] >= n)
            raise ValueError(f"match index {int(arr[bad, col][0])} out of range for {name} with {n} keypoints")
    return arr.astype(np.intp), p1, p2


def explain_pairs(pairs, points1, points2, geometry, *, tol=2.0, depth_range=(0.0, np.inf)):
    """Why each pair passes or fails the segment constraint.

    Returns
    -------
    labels : (K,) int8
        :class:`~episeg_cv.geometry.Rejection` labels.
    counts : dict[str, int]
        Number of pairs per label name, every label present (zero included).

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv import TwoViewGeometry
    >>> K = [[100, 0, 50], [0, 100, 50], [0, 0, 1]]
    >>> g = TwoViewGeometry(K, K, np.eye(3), [-1, 0, 0], image_size1=(100, 100), image_size2=(100, 100))
    >>> labels, counts = explain_pairs([[0, 0], [0, 1], [0, 2]], [[50.0, 50.0]],
    ...                                [[30.0, 50.0], [70.0, 50.0], [30.0, 80.0]], g)
    >>> counts["on_segment"], counts["beyond_infinity"], counts["off_line"]
    (1, 1, 1)
    """
    _check_geometry(geometry)
    tol = as_nonnegative(tol, "tol")
    pairs, p1, p2 = _check_pairs(pairs, points1, points2)
    seg = geometry.segments(p1, depth_range, margin=tol).take(pairs[:, 0])
    labels = seg.classify(p2[pairs[:, 1]], tol)
    counts = {name: int((labels == code).sum()) for code, name in enumerate(Rejection.NAMES)}
    return labels, counts
