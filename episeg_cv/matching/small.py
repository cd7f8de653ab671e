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

import numpy as np

from .. import threads
from .._validation import as_depth_range
from ..geometry import CHEIRALITY_EPS, TwoViewGeometry, _rect
from . import _small_kernels as _sk
from .config import AcceptRule, SearchConfig
from .distances import PAD_CHUNK, PAD_ROUND

__all__ = ["SMALL_PAIRS", "fits", "nearest"]

#: The largest ``N1 * N2`` matched in one call (about 720 x 720). The box slices scan more keypoints than
#: the index's pencil buckets, so large pairs are faster with the index: one call against the index path,
#: one thread, uniform keypoints, forward motion 1.65x at 250, 1.18x at 500, 0.84x at 1000 keypoints a
#: side; lateral 2.0x, 1.5x, 1.15x (``benchmarks/small_pairs.py``). Speed only: the results are the same.
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
        return _sk.nearest(np.ascontiguousarray(inputs.points1), np.ascontiguousarray(inputs.points2), dist.a, dist.b, dist.code, dist.norm == "l2",
                           np.ascontiguousarray(geometry.infinity_homography), geometry.epipole_homogeneous, zmin,
                           zmax, np.array(_rect(geometry.image_size2, search.tol)), CHEIRALITY_EPS, float(search.tol),
                           np.ascontiguousarray(pad_j, dtype=np.int64), float(rule.ratio),
                           bool(rule.mutual or rule.cross_check), bool(prefilter), PAD_CHUNK, PAD_ROUND)
