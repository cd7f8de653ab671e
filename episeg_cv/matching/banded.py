"""Guided matching where each query has its own band (a pose covariance, :mod:`episeg_cv.uncertainty`).

The band of a query is a half-width that varies along its segment (at most
the trapezoid joining its ends' half-widths) with elliptical caps
(:class:`~episeg_cv.uncertainty.EpipolarBands`), not the fixed ``tol``
stadium the compiled scan tests. So the candidates are found in two steps:

1. the queries are grouped by how far their band reaches (powers of
   ``sqrt(2)``), and one :class:`~.candidates.CandidateIndex` per group, with
   ``tol`` the group's largest reach, lists the slices of keypoints that may
   be in their bands (its public ``q_sorted``, ``q_start``, ``q_stop``,
   ``t_sorted``);
2. a compiled loop (:mod:`._band_kernels`) walks those slices, applies the
   exact band test and merges the scores into arrays shared by all groups:
   nearest and second candidate per query (ties: the smaller keypoint index),
   the nearest query of each keypoint among those having it as a candidate
   (ties: the smaller query index), and the counts.

The acceptance rule is then applied as :func:`~.guided.nearest` applies it,
with the random padding of the ratio test. With a zero covariance this gives
the pairs, ratios and mutual flags of the plain matcher (tested).
"""

from __future__ import annotations

import numpy as np

from ..uncertainty import EpipolarBands, epipolar_bands
from . import _band_kernels
from .candidates import CandidateIndex
from .config import AcceptRule, SearchConfig
from .guided import MatchInputs, Neighbors, padding_references

__all__ = ["candidate_pairs", "nearest", "match", "knn", "radius", "bands_for"]

#: Ratio between the reach of consecutive groups of queries.
GROUP_RATIO = np.sqrt(2.0)


def bands_for(geometry, points1: np.ndarray, search: SearchConfig) -> EpipolarBands:
    """The bands of the queries for the geometry's covariance, ``search.tol`` as keypoint noise."""
    return epipolar_bands(geometry, points1, tol=search.tol, depth_range=search.depth_range)


def _table(bands: EpipolarBands) -> np.ndarray:
    """``(N1, 10)`` per query: the start ``P``, the unit direction ``m``, the length ``L`` and the band's
    ``w_start, w_end, e_start, e_end`` and ``cross`` (the layout of :func:`._band_kernels.band_scan`)."""
    P = np.nan_to_num(bands.start)
    D = np.nan_to_num(bands.end) - P
    L = np.hypot(D[:, 0], D[:, 1])
    m = np.where((L > 0)[:, None], D / np.where(L > 0, L, 1.0)[:, None], np.array([1.0, 0.0]))
    return np.ascontiguousarray(np.column_stack([P, m, L, bands.w_start, bands.w_end, bands.e_start, bands.e_end,
                                                 bands.cross]))


def _indexes(geometry, bands: EpipolarBands, points1, points2, search: SearchConfig, bucket_size: int):
    """``[(queries, index)]``: one :class:`CandidateIndex` per group of queries of similar reach."""
    reach = bands.reach
    ok = np.flatnonzero(bands.valid & (reach > 0))
    if ok.size == 0 or len(points2) == 0:
        return []
    base = max(float(reach[ok].min()), 1e-6)
    group = np.floor(np.log(reach[ok] / base) / np.log(GROUP_RATIO) + 1e-9).astype(np.intp)
    out = []
    for gid in np.unique(group):
        sel = ok[group == gid]
        tol = float(reach[sel].max()) * (1 + 1e-9) + 1e-9
        index = CandidateIndex.build(geometry, points1[sel], points2, search.replace(tol=tol), bucket_size)
        out.append((sel.astype(np.int64), index))
    return out


def candidate_pairs(geometry, bands: EpipolarBands, points1: np.ndarray, points2: np.ndarray, search: SearchConfig,
                    bucket_size: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """``(i, j)``: every keypoint ``j`` of image 2 inside the band of query ``i``, sorted by ``i`` then ``j``."""
    table, y = _table(bands), np.ascontiguousarray(points2, dtype=np.float64)
    ii, jj = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
    for sel, index in _indexes(geometry, bands, points1, points2, search, bucket_size):
        i, j = _band_kernels.band_pairs(index.q_sorted, index.q_start, index.q_stop, index.t_sorted, sel, y, table)
        ii.append(i)
        jj.append(j)
    i, j = np.concatenate(ii), np.concatenate(jj)
    o = np.lexsort((j, i))
    return i[o].astype(np.intp), j[o].astype(np.intp)


def _scan(geometry, bands: EpipolarBands, points1, points2, dist, search: SearchConfig, k: int, bucket_size: int):
    """``(indices (N1, k), scores (N1, k), counts (N1,), column_best (N2,))`` in the bands."""
    n1, n2 = len(points1), len(points2)
    idx = np.full((n1, k), -1, dtype=np.intp)
    sc = np.full((n1, k), np.inf, dtype=np.float32)
    counts = np.zeros(n1, dtype=np.intp)
    col_s = np.full(n2, np.inf, dtype=np.float32)
    col_i = np.full(n2, -1, dtype=np.intp)
    table, y = _table(bands), np.ascontiguousarray(points2, dtype=np.float64)
    for sel, index in _indexes(geometry, bands, points1, points2, search, bucket_size):
        _band_kernels.band_scan(index.q_sorted, index.q_start, index.q_stop, index.t_sorted, sel, y, table,
                                dist.a, dist.b, dist.code, idx, sc, counts, col_s, col_i)
    return idx, sc, counts, col_i


def _ratio(d1, d2):
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.isfinite(d2), np.where(d2 > 0, d1 / d2, np.where(d1 > 0, np.inf, 1.0)), 0.0)


def nearest(inputs: MatchInputs, geometry, bands: EpipolarBands, search: SearchConfig, rule: AcceptRule, rng=0,
            bucket_size: int = 64):
    """As :func:`~.guided.nearest`, in the per-query bands: ``(i, j, ratio, mutual, counts)``."""
    dist, p1, p2 = inputs.distances, inputs.points1, inputs.points2
    idx, sc, counts, col = _scan(geometry, bands, p1, p2, dist, search, 2, bucket_size)
    i = np.flatnonzero(idx[:, 0] >= 0)
    j = idx[i, 0]
    s1, s2 = sc[i, 0], sc[i, 1].copy()
    if rule.cross_check:
        inv = geometry.inverse()
        back_search = search.replace(depth_range=(0.0, np.inf))
        ridx, _, _, _ = _scan(inv, bands_for(inv, p2, back_search), p2, p1, dist.reversed(), back_search, 1,
                              bucket_size)
        mutual = ridx[j, 0] == i
    else:
        mutual = col[j] == i
    n_pad = min(rule.pad, len(p2))
    if n_pad and len(i):
        pad_j = padding_references(rng, len(p2), n_pad)
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
    if k > 2:
        ci, _ = candidate_pairs(geometry, bands, p1, p2, search, bucket_size)
        k = max(1, min(k, int(np.bincount(ci, minlength=1).max(initial=0))))
    idx, _, counts, col = _scan(geometry, bands, p1, p2, dist, search, k, bucket_size)
    i, c = np.nonzero(idx >= 0)
    d = np.full(idx.shape, np.inf, dtype=np.float32)
    d[i, c] = dist.exact(i, idx[i, c])
    return Neighbors(idx, d, counts, col)


def radius(inputs: MatchInputs, geometry, bands: EpipolarBands, search: SearchConfig, max_distance: float,
           bucket_size: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """As :func:`~.guided.radius`, in the per-query bands."""
    i, j = candidate_pairs(geometry, bands, inputs.points1, inputs.points2, search, bucket_size)
    d = inputs.distances.exact(i, j)
    keep = d <= max_distance
    i, j, d = i[keep], j[keep], d[keep]
    o = np.lexsort((j, d, i))
    return np.column_stack([i[o], j[o]]).astype(np.intp), d[o]
