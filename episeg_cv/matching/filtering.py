"""Outlier rejection after matching: which pairs satisfy the constraint, and why the others do not."""

from __future__ import annotations

import numpy as np

from .._validation import as_index_pairs, as_points
from ..geometry import Rejection, TwoViewGeometry, as_geometry
from . import _small_kernels as _sk
from .config import SearchConfig, resolve

__all__ = ["filter_pairs", "explain_pairs", "keep_mask", "explain"]


def keep_mask(pairs: np.ndarray, points1: np.ndarray, points2: np.ndarray, geometry: TwoViewGeometry,
              search: SearchConfig) -> np.ndarray:
    """:func:`filter_pairs` on checked inputs."""
    if search.constraint == "none":
        return np.ones(len(pairs), dtype=bool)
    if search.auto is not None or geometry.covariance is not None:
        from .auto import plan_pairs  # (auto builds on guided matching, which this module does not need)
        plan = plan_pairs(pairs, points1, points2, geometry, search)
        if plan.bands is not None:
            return plan.bands.contains(pairs[:, 0], points2[pairs[:, 1]])
        geometry, search = plan.geometry, plan.search
    tol = search.tol
    i, j = pairs[:, 0], pairs[:, 1]
    if len(pairs) < len(points1):  # the segments of the pairs' queries only, one row per pair
        depth_range = tuple(z if np.ndim(z) == 0 else z[i] for z in search.depth_range)
        seg = geometry.segments(points1[i], depth_range, margin=tol)
        i = np.arange(len(pairs))
    else:
        seg = geometry.segments(points1, search.depth_range, margin=tol)
    if search.constraint == "line":
        # 1-D gathers (one column at a time) are several times faster than gathering rows of (N, 2) arrays
        y0, y1 = np.ascontiguousarray(points2[:, 0])[j], np.ascontiguousarray(points2[:, 1])[j]
        l0, l1, l2 = (np.ascontiguousarray(seg.line[:, c])[i] for c in range(3))
        with np.errstate(invalid="ignore"):
            return np.abs(l0 * y0 + l1 * y1 + l2) <= tol  # NaN line: False
    return _sk.segment_keep(seg.line, seg.start, seg.end, seg.valid, np.ascontiguousarray(i, dtype=np.int64),
                            np.ascontiguousarray(points2), np.ascontiguousarray(j, dtype=np.int64), float(tol))


def explain(pairs: np.ndarray, points1: np.ndarray, points2: np.ndarray, geometry: TwoViewGeometry,
            search: SearchConfig) -> tuple[np.ndarray, dict]:
    """:func:`explain_pairs` on checked inputs."""
    bands = None
    if search.auto is not None or geometry.covariance is not None:
        from .auto import plan_pairs
        plan = plan_pairs(pairs, points1, points2, geometry, search.replace(constraint="segment"))
        geometry, search, bands = plan.geometry, plan.search, plan.bands
    seg = geometry.segments(points1, search.depth_range, margin=search.tol).take(pairs[:, 0])
    labels = seg.classify(points2[pairs[:, 1]], search.tol)
    if bands is not None:  # inside its band: on the segment, as far as the pose is known
        labels[bands.contains(pairs[:, 0], points2[pairs[:, 1]])] = Rejection.ON_SEGMENT
    counts = {name: int((labels == code).sum()) for code, name in enumerate(Rejection.NAMES)}
    return labels, counts


def _checked(pairs, points1, points2, geometry, search, options):
    search, _ = resolve(search, None, options, takes_rule=False)
    p1, p2 = as_points(points1, "points1"), as_points(points2, "points2")
    return as_index_pairs(pairs, len(p1), len(p2)), p1, p2, as_geometry(geometry), search


def filter_pairs(pairs, points1, points2, geometry, *, search: SearchConfig | None = None, **options) -> np.ndarray:
    """Outlier rejection after matching: which pairs satisfy the constraint.

    Parameters
    ----------
    pairs : (K, 2) array_like of int
        ``(i1, i2)`` indices into ``points1`` and ``points2``.
    points1, points2 : (N1, 2), (N2, 2) array_like
        Keypoint pixels (pixel centres at integers).
    geometry : TwoViewGeometry or FundamentalGeometry
        Known pose, ``X2 = R @ X1 + t``; with a covariance, each pair is tested
        against its query's band.
    search : SearchConfig, optional
        ``tol`` (pixel distance to the segment or line; ``"auto"``: estimated,
        with the pose, from the pairs themselves), ``depth_range`` and
        ``constraint`` (``"none"`` keeps every pair); its fields may also be given as keywords.

    Returns
    -------
    (K,) bool
        True where the pair is kept.

    Raises
    ------
    ValueError
        A pair index out of range, or other bad input.

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv import TwoViewGeometry
    >>> K = [[100, 0, 50], [0, 100, 50], [0, 0, 1]]
    >>> g = TwoViewGeometry(K, K, np.eye(3), [-1, 0, 0], image_size1=(100, 100), image_size2=(100, 100))
    >>> filter_pairs([[0, 0], [0, 1]], [[50.0, 50.0]], [[30.0, 50.0], [70.0, 50.0]], g).tolist()
    [True, False]
    """
    return keep_mask(*_checked(pairs, points1, points2, geometry, search, options))


def explain_pairs(pairs, points1, points2, geometry, *, search: SearchConfig | None = None,
                  **options) -> tuple[np.ndarray, dict]:
    """Why each pair passes or fails the segment constraint (``search.constraint`` is not used).

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
    return explain(*_checked(pairs, points1, points2, geometry, search, options))
