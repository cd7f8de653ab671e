"""Small pairs in one compiled call: :func:`~.guided.nearest` without the pencil index.

A collection's images often hold a few hundred keypoints each (dinoSparseRing: 150-370 with
COLMAP's SIFT). On such a pair the arithmetic takes tens of microseconds, and the
:class:`~.candidates.CandidateIndex` build and the Python between the stages took most of the
0.6 ms that :func:`~.guided.nearest` cost. Here it is one ``nogil`` numba call
(:func:`._small_kernels.nearest`): the same segments, the same exact test and scores, the same
padding and ratios, with simpler candidate slices (each query's segment box along ``x``, ``y`` or
across the segments' mean direction). The results equal the index path's
(``tests/core/test_small.py`` compares them), so
which path runs is a question of speed only: :func:`fits` takes the pairs of at most
:data:`SMALL_PAIRS` keypoint pairs, with the segment constraint and a calibrated pose (the
oriented half-lines of a :class:`~episeg_cv.FundamentalGeometry` and pose covariances keep the
general path). :func:`episeg_cv.colmap.match_model` matches many such pairs in one call
(:func:`~episeg_cv.colmap.job.match_pairs`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import threads
from .._validation import as_depth_range
from ..geometry import CHEIRALITY_EPS, TwoViewGeometry, _rect
from . import _small_kernels as _sk
from ._kernels import NORM_CODES
from .config import AcceptRule, SearchConfig
from .distances import PAD_CHUNK, PAD_ROUND

__all__ = ["SMALL_PAIRS", "SmallPair", "fits", "nearest", "many"]

#: The largest ``N1 * N2`` matched in one call (about 720 x 720). The box slices scan more keypoints than
#: the index's pencil buckets, so large pairs are faster with the index: one call against the index path,
#: one thread, uniform keypoints, forward motion 2.1x at 250, 1.34x at 500, 1.06x at 1000 keypoints a
#: side, 0.77x at 2000; lateral 2.5x, 1.65x, 1.41x, 1.17x (``benchmarks/small_pairs.py``). Beyond about
#: 720 a side forward motion gains nothing. Speed only: the results are the same.
SMALL_PAIRS = 1 << 19


def fits(n1: int, n2: int, search: SearchConfig, rule: AcceptRule, geometry=None) -> bool:
    """Whether :func:`nearest` serves a call of ``n1`` queries and ``n2`` keypoints (otherwise the index
    path does); ``geometry`` None: a :class:`~episeg_cv.TwoViewGeometry` without covariance."""
    return (n1 * n2 <= SMALL_PAIRS and search.constraint == "segment" and search.auto is None
            and not rule.cross_check
            and (geometry is None or (type(geometry) is TwoViewGeometry and geometry.covariance is None)))


def nearest(inputs, geometry: TwoViewGeometry, search: SearchConfig, rule: AcceptRule, pad_j: np.ndarray,
            prefilter: bool):
    """:func:`~.guided.nearest` of a pair that :func:`fits`: ``(i, j, ratio, mutual, counts)``.

    ``pad_j``: the sorted padding references (:func:`~.guided.padding_references`; empty for none).
    """
    dist = inputs.distances
    zmin, zmax = as_depth_range(search.depth_range, len(inputs.points1))
    zmin = np.ascontiguousarray(np.atleast_1d(zmin), dtype=np.float64)
    zmax = np.ascontiguousarray(np.atleast_1d(zmax), dtype=np.float64)
    with threads.blas_limit(1):  # (the padding's products: one thread, as in Distances.nearest_excluding)
        return _sk.nearest(np.ascontiguousarray(inputs.points1), np.ascontiguousarray(inputs.points2), dist.a, dist.b,
                           dist.code, dist.norm == "l2", np.ascontiguousarray(geometry.infinity_homography),
                           geometry.epipole_homogeneous, zmin, zmax, _rect(geometry.image_size2, search.tol),
                           CHEIRALITY_EPS, float(search.tol), np.ascontiguousarray(pad_j, dtype=np.int64),
                           float(rule.ratio), bool(rule.mutual or rule.cross_check), bool(prefilter), PAD_CHUNK,
                           PAD_ROUND)


@dataclass(frozen=True)
class SmallPair:
    """One pair for :func:`many`: checked queries of image 1 against the keypoints of image 2.

    ``points1 (N1, 2)`` / ``points2 (N2, 2)`` float64 pixels and ``rows1`` / ``rows2`` their scoring rows
    (:attr:`~.distances.Distances.a`, one norm for all pairs); arrays shared between pairs (the same
    object) are passed once. ``geometry`` a :class:`~episeg_cv.TwoViewGeometry` without covariance,
    ``tol`` its band (pixels), ``depth1`` / ``depth2`` the two views' depth ranges (scalars).
    """

    points1: np.ndarray
    rows1: np.ndarray
    points2: np.ndarray
    rows2: np.ndarray
    geometry: TwoViewGeometry
    tol: float
    depth1: tuple
    depth2: tuple


def many(items: list, rule: AcceptRule, ratio: float, norm: str, pad_refs) -> list:
    """Every pair of ``items`` matched both ways in one compiled call: per pair ``(i, j, ratio, inlier)``.

    ``i, j`` (int64) are the nearest candidates with a ratio below ``ratio`` (and mutual when ``rule``
    asks), as :func:`~.guided.nearest` with ``prefilter`` finds them under ``rule.replace(ratio=ratio)``;
    ``inlier`` (bool): the query lies on its keypoint's segment in image 1 too (``depth2``), as
    :func:`~.filtering.keep_mask` tests it. ``pad_refs(n2, n_pad)``: the padding references of a pair
    (:func:`~.guided.padding_references` with the caller's seed). On the kernels' threads, a pair per
    thread (:func:`episeg_cv.threads.run`); the pairs must :func:`fits`.
    """
    if not items:
        return []
    arrays, where = [], {}

    def slot(points, rows, depth):  # an image's arrays once, with its depth range
        key = (id(points), id(rows), tuple(float(z) for z in depth))
        if key not in where:
            where[key] = len(arrays)
            arrays.append((points, rows, key[2]))
        return where[key]

    img = np.array([[slot(it.points1, it.rows1, it.depth1), slot(it.points2, it.rows2, it.depth2)] for it in items],
                   dtype=np.int64)
    X = np.ascontiguousarray(np.concatenate([p for p, _, _ in arrays]), dtype=np.float64)
    A = np.ascontiguousarray(np.concatenate([r for _, r, _ in arrays]))
    first = np.concatenate([[0], np.cumsum([len(p) for p, _, _ in arrays])]).astype(np.int64)
    zr = np.array([z for _, _, z in arrays], dtype=np.float64).reshape(-1, 2)
    inverses = [it.geometry.inverse() for it in items]
    H = np.array([it.geometry.infinity_homography for it in items]).reshape(-1, 3, 3)
    b = np.array([it.geometry.epipole_homogeneous for it in items]).reshape(-1, 3)
    Hi = np.array([g.infinity_homography for g in inverses]).reshape(-1, 3, 3)
    bi = np.array([g.epipole_homogeneous for g in inverses]).reshape(-1, 3)
    tol = np.array([float(it.tol) for it in items])
    rects = np.array([[_rect(it.geometry.image_size2, it.tol), _rect(it.geometry.image_size1, it.tol)]
                      for it in items]).reshape(-1, 2, 4)
    n1, n2 = first[img[:, 0] + 1] - first[img[:, 0]], first[img[:, 1] + 1] - first[img[:, 1]]
    pads = [np.asarray(pad_refs(int(m2), min(rule.pad, int(m2))), dtype=np.int64) if min(rule.pad, m2) and m1
            else np.zeros(0, dtype=np.int64) for m1, m2 in zip(n1, n2)]
    pad = np.concatenate(pads + [np.zeros(0, dtype=np.int64)])
    pad_first = np.concatenate([[0], np.cumsum([len(p) for p in pads])]).astype(np.int64)
    out_first = np.concatenate([[0], np.cumsum(n1)]).astype(np.int64)
    total = int(out_first[-1])
    out_i, out_j = np.empty(total, dtype=np.int64), np.empty(total, dtype=np.int64)
    out_r, out_in = np.empty(total), np.empty(total, dtype=np.bool_)
    out_n = np.zeros(len(items), dtype=np.int64)
    with threads.blas_limit(1):
        threads.run(_sk.pairs, _sk.pairs_parallel, total if len(items) > 1 else 0, X, A, first, img, H, b, Hi, bi,
                    zr, rects, CHEIRALITY_EPS, tol, pad, pad_first, NORM_CODES[norm], norm == "l2", float(ratio),
                    bool(rule.mutual or rule.cross_check), PAD_CHUNK, PAD_ROUND, out_first, out_i, out_j, out_r,
                    out_in, out_n)
    return [(out_i[o:o + n], out_j[o:o + n], out_r[o:o + n], out_in[o:o + n]) for o, n in zip(out_first, out_n)]
