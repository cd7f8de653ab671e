"""``tol="auto"`` for a collection: one band for every pair, from the confident matches of a few pairs.

The two-view estimate (:mod:`episeg_cv.matching.auto`) finds a pair's band
from its confident matches and may correct the pair's pose. A collection's
poses are global, and the triangulation uses them as they are, so here no
pose is corrected (``AutoTol.refine`` does not apply) and the band is one
number for the collection, from steps 1 and 4 of that estimate:

1. **Confident matches** of the pairs :func:`band_pairs` picks from the pair
   list: those whose cameras most likely see the same part of the scene,
   until every image is in one of them (at most :data:`SAMPLE_PAIRS`). Guided
   matching around the given poses in the wide band (``AutoTol.band``; 64 px
   at 640 x 480), with the strict rule (mutual, ratio below
   ``AutoTol.strict_ratio``), each view's depth range applied; per pair at most :data:`MAX_QUERIES` keypoints of the first image,
   spread over it, against every keypoint of the second (the wide band on 8k
   keypoints cost more than the matching of the whole collection). A uniform
   sample instead was measured and rejected: the spread one gives an image's
   sparse parts (dinoSparseRing's silhouettes) more than their share, and
   their matches are noisier, so its sigma is higher than that of every
   keypoint (0.74 against 0.64 px on dinoSparseRing's neighbour pairs). But
   the track consensus's tolerance from the uniform sample's 0.61 px (1.83
   instead of 2.13 px) kept 489 accurate points instead of 515 there, 26
   fewer to drop 4 inaccurate ones (95.0 % accurate instead of 94.5 %; on
   COLMAP's features 314 instead of 325), the rooms unchanged
   (``benchmarks/colmap.py``): the consensus's tolerance, not the band,
   decides that trade (:mod:`.consensus`).
2. **The band**: ``k`` robust standard deviations
   (:func:`episeg_cv.refinement.robust_sigma`) of all their signed distances
   to their segments, pooled, clamped to ``[tol_min, tol_max]``; with fewer
   than ``min_matches`` confident matches in all, ``2 tol_min``.
3. **The track consensus's tolerance** (:mod:`.consensus`): ``k sigma`` too,
   but at least :data:`TAU_MIN` (1 px) instead of ``tol_min``. The band's
   floor of 2 px is for single pairs, whose matches nothing checks again; the
   consensus checks where each triangulated point reprojects in every image of
   its track, an error of the keypoints' and poses' noise. On the synthetic
   rooms (sigma 0.1 px) this tolerance of 1 px instead of 2 px kept 0.5 % fewer
   accurate 3D points and dropped 30 % of the inaccurate ones; on the real
   dinoSparseRing (sigma 0.7 px) it is the band itself. With the fallback, the band.

What the band buys is measured in ``benchmarks/colmap.py``: poses that are
exact (the synthetic rooms) give the fixed default's 2 px; a real calibration
gives what its keypoints and poses need.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..matching import fused, guided, small
from ..matching.auto import clip_tol, strict_rule
from ..matching.config import AcceptRule, AutoTol, SearchConfig
from ..matching.distances import Distances
from ..refinement import robust_sigma, segment_residuals, spread_subset
from .job import image_rows, pair_inputs
from .store import FeatureStore

__all__ = ["CollectionBand", "collection_band", "band_pairs", "SAMPLE_PAIRS", "TAU_MIN", "MAX_QUERIES"]

#: Most pairs whose confident matches give a collection's band (:func:`band_pairs`).
SAMPLE_PAIRS = 16
#: Smallest reprojection tolerance of the track consensus that the band sets, pixels.
TAU_MIN = 1.0
#: Queries of the first image per sampled pair (a few hundred confident matches in all are enough: on
#: the 12-view room, 256 queries a pair gave 600 of them and the sigma of 1024, 0.25 s sooner).
MAX_QUERIES = 256


@dataclass(frozen=True)
class CollectionBand:
    """The band ``tol="auto"`` found for a collection (:func:`collection_band`).

    Attributes
    ----------
    tol : float
        The band, pixels (in the pinhole images).
    sigma : float
        Robust standard deviation of the confident matches' distances to their segments, pixels
        (NaN for the fallback).
    matches, pairs : int
        Confident matches pooled, and the pairs they came from (of those sampled).
    fallback : bool
        Too few confident matches: ``2 tol_min``.
    tau : float
        Reprojection tolerance for the track consensus, pixels (step 3).
    """

    tol: float
    sigma: float
    matches: int
    pairs: int
    fallback: bool
    tau: float

    def as_dict(self) -> dict:
        return {"tol": self.tol, "sigma": self.sigma, "matches": self.matches, "pairs": self.pairs,
                "fallback": self.fallback, "tau": self.tau}


def sample_pairs(pair_list, n: int = SAMPLE_PAIRS) -> list:
    """Up to ``n`` pairs of ``pair_list``, evenly spread over it (its first and last included)."""
    if len(pair_list) <= n:
        return list(pair_list)
    return [pair_list[k] for k in np.unique(np.linspace(0, len(pair_list) - 1, n).round().astype(int))]


def band_pairs(views, pair_list, n: int = SAMPLE_PAIRS) -> list:
    """The pairs of ``pair_list`` whose confident matches give the band: at most ``n``, those whose cameras
    most likely see the same part of the scene, until every image of the list is in one of them.

    A pair's score is the angle between the two cameras' optical axes, in units of the narrower one's
    (diagonal) field of view, plus the distance between their centres, in units of the median over the
    list (no scene scale needed); the lowest first. The pairs are taken in that order, each one only if
    it brings an image that no pair taken so far holds (a greedy edge cover: between ``m / 2`` and
    ``m - 1`` pairs for ``m`` images). On a ring such as dinoSparseRing these are neighbours. The 16
    pairs spread evenly over the list that the band took before were mostly views that share nothing,
    and their wide pass cost as much: there, 9 of them gave 127 confident matches, 83 % of them from 2
    pairs, where the 10 pairs of this rule give 515, from every image, in less time (11 against 14 ms).

    Parameters
    ----------
    views : sequence of View
        World-to-camera poses ``X_cam = R X_world + t``.
    pair_list : sequence of (int, int)
        Indices into ``views``.
    n : int, optional
        Most pairs.

    Returns
    -------
    list of (int, int)
        In the order of ``pair_list``.

    Examples
    --------
    Six cameras on a ring, all looking at its centre: neighbours, until each image is in one.

    >>> from episeg_cv.colmap import View, exhaustive_pairs
    >>> def ring(k, n=6):
    ...     a = 2 * np.pi * k / n
    ...     z = -np.array([np.cos(a), 0.0, np.sin(a)])  # the optical axis, towards the centre
    ...     x = np.cross([0.0, 1.0, 0.0], z)
    ...     R = np.stack([x, np.cross(z, x), z])
    ...     return View(f"{k}.png", k + 1, 1, np.diag([500.0, 500.0, 1.0]), R, R @ (3 * z), (640, 480))
    >>> views = [ring(k) for k in range(6)]
    >>> got = band_pairs(views, exhaustive_pairs(6))
    >>> all((j - i) % 6 in (1, 5) for i, j in got), sorted({v for p in got for v in p})
    (True, [0, 1, 2, 3, 4, 5])
    """
    pair_list = [tuple(p) for p in pair_list]
    if not pair_list or n <= 0:
        return []
    i, j = np.array(pair_list).T
    axes = np.array([v.R[2] for v in views])  # each optical axis in the world: R^T e3
    centers = np.array([v.center for v in views])
    fov = np.array([2 * np.arctan(np.hypot(*v.image_size) / (v.K[0, 0] + v.K[1, 1])) for v in views])
    angle = np.arccos(np.clip(np.einsum("ij,ij->i", axes[i], axes[j]), -1.0, 1.0)) / np.minimum(fov[i], fov[j])
    baseline = np.linalg.norm(centers[i] - centers[j], axis=1)
    scale = np.median(baseline)
    score = angle + (baseline / scale if scale > 0 else 0.0)
    covered = np.zeros(len(views), dtype=bool)
    left = len(np.unique(np.concatenate([i, j])))  # images not in the sample yet
    chosen = []
    for k in np.argsort(score, kind="stable"):
        if not (covered[i[k]] and covered[j[k]]):
            chosen.append(k)
            left -= int(not covered[i[k]]) + int(not covered[j[k]])
            covered[i[k]] = covered[j[k]] = True
            if left == 0 or len(chosen) == n:
                break
    return [pair_list[k] for k in sorted(chosen)]


def collection_band(views, store: FeatureStore, pair_list, search: SearchConfig, rule: AcceptRule,
                    options: AutoTol, sample: int = SAMPLE_PAIRS, imap=map, per_task=None) -> CollectionBand:
    """The collection's band (module docstring) on checked inputs.

    Parameters
    ----------
    views : list of View
        With their depth ranges.
    store : FeatureStore
        Holding every image's features (:meth:`FeatureStore.ensure` done).
    pair_list : list of (int, int)
        Indices into ``views``.
    search : SearchConfig
        The constraint (its ``tol`` is the one being estimated).
    rule : AcceptRule
        The padding of the strict rule is at least this rule's.
    options : AutoTol
    imap : callable, optional
        ``imap(fn, items)`` runs the larger sampled pairs (the general path), for example
        :meth:`.runner.Runner.imap`; the small ones are matched here, in one compiled call.
    per_task : callable, optional
        ``per_task(n)``: how many of ``n`` larger pairs go in one task (:meth:`.runner.Runner.spread`);
        default all of them.
    """
    strict = strict_rule(options, rule)
    largest = max((v.image_size for v in views), key=lambda s: s[0] * s[1])
    small_ones, large_ones = [], []  # (sample number, queries, keypoints, geometry, wide search, view 2's range)
    rows, queries = {}, {}  # per image: (points, scoring rows) of its keypoints with a pinhole position, its queries
    for k, (i, j) in enumerate(band_pairs(views, pair_list, sample)):
        wide = search.replace(tol=options.first_band(views[j].image_size), depth_range=views[i].depth_range)
        for v in (i, j):
            if v not in rows:
                rows[v] = image_rows(views[v], store)[:2]
        # (a View's geometry has no covariance)
        if small.fits(min(len(rows[i][0]), MAX_QUERIES), len(rows[j][0]), wide, strict):
            if i not in queries:  # (shared by its pairs: many() passes an image's arrays once)
                q = spread_subset(rows[i][0], MAX_QUERIES)
                queries[i] = rows[i] if len(q) == len(rows[i][0]) else (rows[i][0][q], rows[i][1][q])
            small_ones.append((k, queries[i], rows[j], views[i].geometry_to(views[j]), wide, views[j].depth_range))
        else:  # its inputs are made in its task, on the runner's threads
            large_ones.append((k, views[i], views[j], store, wide, strict))
    size = per_task(len(large_ones)) if per_task is not None and large_ones else max(1, len(large_ones))
    tasks = [large_ones[k:k + size] for k in range(0, len(large_ones), size)]
    found = {k: r for task in imap(_confident, tasks) for k, r in task}
    # the small pairs in one call on every core, the same matches as guided.match (the reverse test unused)
    pairs = small.many([small.SmallPair(*x1, *x2, g, s.tol, s.depth_range, d2) for _, x1, x2, g, s, d2 in small_ones],
                       strict, strict.ratio, store.norm, lambda n2, n_pad: guided.padding_references(0, n2, n_pad))
    for (k, x1, x2, g, _, _), (qi, kj, _, _) in zip(small_ones, pairs):
        found[k] = _residuals(g, x1[0][qi], x2[0][kj])
    residuals = [found[k] for k in sorted(found) if len(found[k])]
    used = len(residuals)
    r = np.concatenate(residuals) if residuals else np.zeros(0)
    fallback = len(r) < options.min_matches
    sigma = float("nan") if fallback else robust_sigma(r)
    tol = clip_tol(sigma, options, largest)
    tau = tol if fallback else float(min(max(options.k * sigma, TAU_MIN), tol))
    return CollectionBand(tol, sigma, int(len(r)), used, fallback, tau)


def _confident(task) -> list:
    """``[(sample number, signed distances to their segments)]`` of the confident matches of sampled pairs
    on the general path (a task for the runner's workers, one kernel thread each).

    Each pair is one compiled call (:func:`~episeg_cv.matching.fused.match_pair`, as a collection's
    large pairs): the matches of :func:`~episeg_cv.matching.guided.match`, the same bits, its reverse
    test unused. Stage by stage, the band compiled ``knn_scan``, ``bucket_frames`` and ``padding_l2``
    once more for the feature store's read-only arrays, about 3 s of a first run.
    """
    out = []
    for k, view1, view2, store, wide, strict in task:
        inputs, g, _, _ = pair_inputs(view1, view2, store)
        inputs = _queries(inputs, spread_subset(inputs.points1, MAX_QUERIES))
        d = inputs.distances
        conf = fused.match_pair(inputs.points1, d.a, inputs.points2, d.b, d.norm, g, view1.depth_range,
                                view2.depth_range, wide, strict)[0]
        out.append((k, _residuals(g, inputs.points1[conf[:, 0]], inputs.points2[conf[:, 1]])))
    return out


def _residuals(g, points1: np.ndarray, points2: np.ndarray) -> np.ndarray:
    return segment_residuals(g, points1, points2) if len(points1) else np.zeros(0)


def _queries(inputs: guided.MatchInputs, rows: np.ndarray) -> guided.MatchInputs:
    """The same inputs with only the queries ``rows`` of image 1, read-only as the store's arrays (a
    writable copy would compile the pair kernel once more: numba types an array's flags)."""
    if len(rows) == len(inputs.points1):
        return inputs
    d = inputs.distances
    raw1, points1 = d.raw1[rows], inputs.points1[rows]
    raw1.flags.writeable = points1.flags.writeable = False
    return guided.MatchInputs(Distances(raw1, d.raw2, d.norm), points1, inputs.points2)
