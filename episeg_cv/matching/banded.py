"""Guided matching where each query has its own band (a pose covariance, :mod:`episeg_cv.uncertainty`).

The band of a query is a trapezoid around its segment with elliptical caps
(:class:`~episeg_cv.uncertainty.EpipolarBands`), not the fixed ``tol``
stadium the compiled scan tests. So the candidates are found in two steps:

1. the queries are grouped by how far their band reaches (powers of
   ``sqrt(2)`` times ``tol``), and one :class:`~.candidates.CandidateIndex` per
   group, with ``tol`` the group's largest reach, lists a superset of their
   candidates (:meth:`~.candidates.CandidateIndex.pairs`);
2. the exact band test keeps those inside (:meth:`EpipolarBands.contains`).

The acceptance rule is then applied to those pairs exactly as the scan
applies it (:func:`~.guided.nearest`): nearest and second candidate per
query (ties: the smaller keypoint index), the nearest query of each keypoint
among those having it as a candidate (ties: the smaller query index), and
the random padding of the ratio test. With a zero covariance this gives the
pairs, ratios and mutual flags of the plain matcher (tested).
"""

from __future__ import annotations

import numpy as np

from ..uncertainty import EpipolarBands, epipolar_bands
from .candidates import CandidateIndex
from .config import AcceptRule, SearchConfig
from .guided import MatchInputs, Neighbors

__all__ = ["candidate_pairs", "nearest", "match", "knn", "radius", "bands_for"]

#: Ratio between the reach of consecutive groups of queries.
GROUP_RATIO = np.sqrt(2.0)


def bands_for(geometry, points1: np.ndarray, search: SearchConfig) -> EpipolarBands:
    """The bands of the queries for the geometry's covariance, ``search.tol`` as keypoint noise."""
    return epipolar_bands(geometry, points1, tol=search.tol, depth_range=search.depth_range)


def candidate_pairs(geometry, bands: EpipolarBands, points1: np.ndarray, points2: np.ndarray, search: SearchConfig,
                    bucket_size: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """``(i, j)``: every keypoint ``j`` of image 2 inside the band of query ``i``, sorted by ``i`` then ``j``."""
    reach = bands.reach
    ok = np.flatnonzero(bands.valid & (reach > 0))
    if ok.size == 0 or len(points2) == 0:
        z = np.zeros(0, dtype=np.intp)
        return z, z
    base = max(float(reach[ok].min()), 1e-6)
    group = np.floor(np.log(reach[ok] / base) / np.log(GROUP_RATIO) + 1e-9).astype(np.intp)
    ii, jj = [], []
    for gid in np.unique(group):
        sel = ok[group == gid]
        tol = float(reach[sel].max()) * (1 + 1e-9) + 1e-9
        index = CandidateIndex.build(geometry, points1[sel], points2, search.replace(tol=tol), bucket_size)
        pairs = index.pairs()
        ii.append(sel[pairs[:, 0]])
        jj.append(pairs[:, 1])
    i, j = np.concatenate(ii), np.concatenate(jj)
    inside = bands.contains(i, points2[j])
    i, j = i[inside], j[inside]
    o = np.lexsort((j, i))
    return i[o].astype(np.intp), j[o].astype(np.intp)


def _ranked(dist, i, j):
    """Scores of the pairs, and the pairs sorted by query, then score, then keypoint."""
    s = dist.paired(i, j)
    o = np.lexsort((j, s, i))
    return i[o], j[o], s[o]


def _column_best(i, j, s, n2):
    col = np.full(n2, -1, dtype=np.intp)
    if len(i):
        o = np.lexsort((i, s, j))
        jj, ii = j[o], i[o]
        first = np.ones(len(jj), dtype=bool)
        first[1:] = jj[1:] != jj[:-1]
        col[jj[first]] = ii[first]
    return col


def _top(i, j, s, n1, k):
    """``(indices (n1, k), scores (n1, k), counts (n1,))`` from pairs sorted by query, then score."""
    idx = np.full((n1, k), -1, dtype=np.intp)
    sc = np.full((n1, k), np.inf, dtype=np.float32)
    counts = np.bincount(i, minlength=n1).astype(np.intp)
    if len(i):
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        rank = np.arange(len(i)) - starts[i]
        keep = rank < k
        idx[i[keep], rank[keep]] = j[keep]
        sc[i[keep], rank[keep]] = s[keep]
    return idx, sc, counts


def _ratio(d1, d2):
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.isfinite(d2), np.where(d2 > 0, d1 / d2, np.where(d1 > 0, np.inf, 1.0)), 0.0)


def nearest(inputs: MatchInputs, geometry, bands: EpipolarBands, search: SearchConfig, rule: AcceptRule, rng=0,
            bucket_size: int = 64):
    """As :func:`~.guided.nearest`, in the per-query bands: ``(i, j, ratio, mutual, counts)``."""
    dist, p1, p2 = inputs.distances, inputs.points1, inputs.points2
    n1, n2 = len(p1), len(p2)
    ci, cj = candidate_pairs(geometry, bands, p1, p2, search, bucket_size)
    ci, cj, cs = _ranked(dist, ci, cj)
    idx, sc, counts = _top(ci, cj, cs, n1, 2)
    i = np.flatnonzero(idx[:, 0] >= 0)
    j = idx[i, 0]
    s1, s2 = sc[i, 0], sc[i, 1].copy()
    if rule.cross_check:
        inv = geometry.inverse()
        back_search = search.replace(depth_range=(0.0, np.inf))
        ri, rj = candidate_pairs(inv, bands_for(inv, p2, back_search), p2, p1, back_search, bucket_size)
        ri, rj, rs = _ranked(dist.reversed(), ri, rj)
        ridx, _, _ = _top(ri, rj, rs, n2, 1)
        mutual = ridx[j, 0] == i
    else:
        mutual = _column_best(ci, cj, cs, n2)[j] == i
    n_pad = min(rule.pad, n2)
    if n_pad and len(i):
        pad_j = np.sort(np.random.default_rng(rng).choice(n2, n_pad, replace=False))
        s2 = np.minimum(s2, dist.nearest_excluding(i, pad_j, j))
    ratio = _ratio(dist.to_distance(s1.astype(np.float64)), dist.to_distance(s2.astype(np.float64)))
    return i, j, ratio, mutual, counts


def match(inputs: MatchInputs, geometry, bands: EpipolarBands, search: SearchConfig, rule: AcceptRule, rng=0,
          bucket_size: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """As :func:`~.guided.match`, in the per-query bands."""
    i, j, r, mu, _ = nearest(inputs, geometry, bands, search, rule, rng, bucket_size)
    keep = (r < rule.ratio) if rule.ratio < 1 else np.ones(len(r), dtype=bool)
    if rule.mutual or rule.cross_check:
        keep &= mu
    i, j = i[keep], j[keep]
    return np.column_stack([i, j]).astype(np.intp), inputs.distances.exact(i, j)


def knn(inputs: MatchInputs, geometry, bands: EpipolarBands, search: SearchConfig, k: int,
        bucket_size: int = 64) -> Neighbors:
    """As :func:`~.guided.knn`, in the per-query bands."""
    dist, p1, p2 = inputs.distances, inputs.points1, inputs.points2
    ci, cj = candidate_pairs(geometry, bands, p1, p2, search, bucket_size)
    ci, cj, cs = _ranked(dist, ci, cj)
    counts = np.bincount(ci, minlength=len(p1))
    if k > 2:
        k = max(1, min(k, int(counts.max(initial=0))))
    idx, _, counts = _top(ci, cj, cs, len(p1), k)
    i, col = np.nonzero(idx >= 0)
    d = np.full(idx.shape, np.inf, dtype=np.float32)
    d[i, col] = dist.exact(i, idx[i, col])
    return Neighbors(idx, d, counts, _column_best(ci, cj, cs, len(p2)))


def radius(inputs: MatchInputs, geometry, bands: EpipolarBands, search: SearchConfig, max_distance: float,
           bucket_size: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """As :func:`~.guided.radius`, in the per-query bands."""
    i, j = candidate_pairs(geometry, bands, inputs.points1, inputs.points2, search, bucket_size)
    d = inputs.distances.exact(i, j)
    keep = d <= max_distance
    i, j, d = i[keep], j[keep], d[keep]
    o = np.lexsort((j, d, i))
    return np.column_stack([i[o], j[o]]).astype(np.intp), d[o]
