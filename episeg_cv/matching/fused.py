"""A pair in one compiled call that holds no GIL: the Python entry of :mod:`._pair_kernel`.

A collection's pairs run on a pool of Python threads, one pair per thread and one kernel thread each
(``episeg colmap --workers N``). Called stage by stage (:func:`~.guided.nearest`, then
:func:`~.filtering.keep_mask` the other way), a pair's Python between the kernels holds the GIL; here
the whole pair is one ``nogil`` call on the serial kernels, with the same result (the same bits: the
pairs, their order and their ratios). :mod:`._pair_kernel` says what it chains and what it measured.
"""

from __future__ import annotations

import numpy as np

from .. import threads
from ..geometry import CHEIRALITY_EPS, TwoViewGeometry
from . import _pair_kernel
from .config import AcceptRule, SearchConfig
from .distances import PAD_CHUNK, PAD_ROUND
from .guided import padding_references

__all__ = ["match_pair", "BUCKET_SIZE"]

#: Queries per pencil bucket of the candidate index (:func:`~.guided.match`'s default).
BUCKET_SIZE = 64


def match_pair(points1: np.ndarray, rows1: np.ndarray, points2: np.ndarray, rows2: np.ndarray, norm: str,
               geometry: TwoViewGeometry, depth_range1, depth_range2, search: SearchConfig, rule: AcceptRule,
               loose: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The raw matches of a pair, their ratios and the reverse test, in one compiled call.

    The same result as :func:`~.guided.nearest` (``prefilter=True``, then the rule at ``loose``) or
    :func:`~.guided.match` (``loose=None``) from view 1 with ``depth_range1``, followed by
    :func:`~.filtering.keep_mask` from view 2 with ``depth_range2``, on checked inputs.

    Parameters
    ----------
    points1, points2 : (N1, 2), (N2, 2) float64
        Pinhole keypoints, pixels (finite).
    rows1, rows2 : (N1, D), (N2, D)
        The descriptors' scoring rows (:attr:`~.distances.Distances.a` / ``.b``).
    norm : {"l2", "l2sqr", "l1", "hamming"}
    geometry : TwoViewGeometry
        ``X2 = R X1 + t``.
    depth_range1, depth_range2 : (float, float)
        Each view's depth range, in the unit of ``t``.
    search : SearchConfig
        A numeric ``tol`` and constraint ``"segment"`` or ``"line"`` (its depth range is not used).
    rule : AcceptRule
    loose : float or None, optional
        The ratio of the raw matches (they come back with their ratios); None: the rule's, no ratios.

    Returns
    -------
    pairs : (K, 2) intp
        The raw matches.
    ratios : (K,) float64
        Their ratios (with ``loose``; otherwise empty, not used).
    keep : (K,) bool
        Which pass the reverse test.
    """
    n_pad = min(rule.pad, len(points2))
    pad_j = padding_references(0, len(points2), n_pad) if n_pad and len(points1) else np.zeros(0, dtype=np.int64)
    inverse = geometry.inverse()
    with threads.blas_limit(1):  # (the padding's products, as in Distances.nearest_excluding)
        return _pair_kernel.match_pair(
            np.ascontiguousarray(points1), np.ascontiguousarray(points2), rows1, rows2, _pair_kernel.NORM_CODES[norm],
            norm == "l2", np.ascontiguousarray(geometry.infinity_homography), geometry.epipole_homogeneous,
            np.ascontiguousarray(inverse.infinity_homography), inverse.epipole_homogeneous,
            np.array(depth_range1, dtype=np.float64), np.array(depth_range2, dtype=np.float64),
            np.array(geometry.image_size1, dtype=np.float64), np.array(geometry.image_size2, dtype=np.float64),
            CHEIRALITY_EPS, float(search.tol), search.constraint == "line", BUCKET_SIZE, pad_j,
            float(rule.ratio if loose is None else loose), bool(rule.mutual or rule.cross_check),
            bool(rule.cross_check), loose is not None, PAD_CHUNK, PAD_ROUND)
