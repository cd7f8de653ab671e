"""Repeated structure: a match is ambiguous when one of its keypoints has a twin inside the same band.

On a repetitive texture (tiles, a checkerboard, a row of columns) the copies of
a point can lie on its segment. The ratio test sees them as candidates of the
query, across the two images; but a copy that looks *more* like the query than
the true match does (seen at the query's scale, from the query's angle) passes
it, and its neighbours are shifted the same way: a whole wall matched one
period off is locally consistent in depth (measured: a check of each match's
depth against its neighbours' removed 10-30 % of those wrong matches, and 2-5 %
of the correct matches of ordinary pairs).

What does tell the copies apart is the images themselves: a match ``(i, j)``
is *ambiguous* when keypoint ``j`` has a twin in image 2 inside the band of
query ``i``, or keypoint ``i`` a twin in image 1 inside the band of ``j``
(reverse direction), that is closer to it in descriptor space than the match
is to it, divided by the ratio: ``d(i, j) >= ratio * d(j, j')``. The viewpoint
changed the descriptor by more than the copies differ, so the descriptors
cannot say which copy is the match. Keypoints within ``tol`` of the keypoint
itself are the same point (a detector's other orientations or scales), not
twins. It is Lowe's ratio test with the second candidates taken from the
keypoint's own image, where the viewpoint does not change them.
"""

from __future__ import annotations

import numpy as np

from .candidates import CandidateIndex
from .config import SearchConfig
from .distances import Distances
from .guided import MatchInputs

__all__ = ["twin_distances", "ambiguous"]


def _nearest_twin(geometry, queries: np.ndarray, own: np.ndarray, points: np.ndarray, raw: np.ndarray, norm: str,
                  search: SearchConfig) -> np.ndarray:
    """``(K,)``: for query pixels ``queries`` (in the other image) whose own keypoints are ``own``, the
    smallest descriptor distance from ``raw[own[k]]`` to another keypoint of ``points`` in the band of
    ``queries[k]`` and farther than ``search.tol`` from ``points[own[k]]``; inf where there is none."""
    out = np.full(len(queries), np.inf)
    if len(queries) == 0:
        return out
    q, c = CandidateIndex.build(geometry, queries, points, search).candidate_lists()
    base = own[q]
    apart = np.hypot(*(points[c] - points[base]).T) > search.tol
    q, c, base = q[apart], c[apart], base[apart]
    np.minimum.at(out, q, Distances(raw, raw, norm).exact(base, c).astype(np.float64))
    return out


def twin_distances(inputs: MatchInputs, pairs: np.ndarray, geometry, search: SearchConfig) -> np.ndarray:
    """``(K,)`` the descriptor distance of each match's nearest twin (either image; module docstring), in
    the units of the matches' distances; inf where there is none (checked inputs, a numeric ``tol``)."""
    i, j = pairs[:, 0], pairs[:, 1]
    dist = inputs.distances
    twin2 = _nearest_twin(geometry, inputs.points1[i], j, inputs.points2, dist.raw2, dist.norm, search)
    back = search.replace(depth_range=(0.0, np.inf))  # depths are camera 1's: the reverse band has none
    twin1 = _nearest_twin(geometry.inverse(), inputs.points2[j], i, inputs.points1, dist.raw1, dist.norm, back)
    return np.minimum(twin1, twin2)


def ambiguous(inputs: MatchInputs, pairs: np.ndarray, geometry, search: SearchConfig, ratio: float) -> np.ndarray:
    """``(K,)`` bool: the matches ``pairs (K, 2)`` whose keypoints have a twin in the same band (module
    docstring), ``d(i, j) >= ratio * d(twin)``.

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv import TwoViewGeometry
    >>> from episeg_cv.matching import MatchInputs, SearchConfig
    >>> K = [[100, 0, 50], [0, 100, 50], [0, 0, 1]]
    >>> g = TwoViewGeometry(K, K, np.eye(3), [-1, 0, 0], image_size1=(100, 100), image_size2=(100, 100))
    >>> d1 = np.array([[0, 0], [9, 9]], np.float32)                   # query 0, and an unrelated keypoint
    >>> d2 = np.array([[1, 0], [0, 1.5], [5, 5]], np.float32)         # its match, a twin of it, another
    >>> p1 = np.array([[60.0, 50.0], [20.0, 20.0]])
    >>> p2 = np.array([[40.0, 50.0], [20.0, 50.0], [30.0, 80.0]])     # the twin is on the same row (band)
    >>> inputs = MatchInputs.check(d1, d2, p1, p2, "l2")
    >>> ambiguous(inputs, np.array([[0, 0]]), g, SearchConfig(tol=2.0), 0.8).tolist()   # 1 >= 0.8 * 1.80
    [False]
    >>> d2[1] = [1, 0.5]                                               # a closer twin: 1 >= 0.8 * 0.5
    >>> inputs = MatchInputs.check(d1, d2, p1, p2, "l2")
    >>> ambiguous(inputs, np.array([[0, 0]]), g, SearchConfig(tol=2.0), 0.8).tolist()
    [True]
    """
    if len(pairs) == 0:
        return np.zeros(0, dtype=bool)
    d = inputs.distances.exact(pairs[:, 0], pairs[:, 1]).astype(np.float64)
    return d >= ratio * twin_distances(inputs, pairs, geometry, search)
