"""Pose noise in pixels, for ``benchmarks/noisy_poses.py``: per-image errors that mean the same on every lens.

Each view gets a rotation error of angle ``theta`` about a random axis and a
camera-centre error of length ``d`` in a random direction, with

- ``f * theta = p`` pixels (a rotation by ``theta`` moves the image of every
  point by about ``f * theta`` near the image centre), and
- ``f * d / z = p`` pixels, ``z`` the view's typical scene depth (a sideways
  move by ``d`` shifts the image of a point at depth ``z`` by ``f * d / z``;
  the part of ``d`` along the viewing direction moves it less),

``f = K[0, 0]``. The rotation error is applied in the camera frame
(``R' = dR @ R``) and the centre moves in the world frame (``C' = C + d u``,
``t' = -R' C'``). Also here: the typical depth of a view of dinoSparseRing
(distance from the camera centre to the centre of the object's bounding box)
and of a rendered room (median finite rendered depth), the relative
rotation errors of a set of poses against the true ones, and the similarity
that best takes a model onto another one triangulated from the same matches
(to judge a model up to its frame, which no method can recover from noisy
poses).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from episeg_cv.colmap.adjust import similarity
from episeg_cv.refinement import rotation_angle_deg


def _unit(rng) -> np.ndarray:
    u = rng.normal(size=3)
    return u / np.linalg.norm(u)


def perturb_views(views, pixels: float, depths, seed) -> list:
    """Views with per-image pose errors of ``pixels`` px in rotation and in camera centre.

    Parameters
    ----------
    views : sequence of episeg_cv.colmap.View
        True poses (world-to-camera, ``X_cam = R @ X_world + t``).
    pixels : float
        ``p >= 0``: rotation angle ``p / f`` radians about a random axis, centre
        moved by ``p * z / f`` (world units) in a random direction; ``f = K[0, 0]``.
    depths : sequence of float
        ``z`` per view, world units (its typical scene depth), same order as ``views``.
    seed : int or sequence of int
        Seed of ``numpy.random.default_rng``; the same seed gives the same errors.

    Returns
    -------
    list of View
        Copies of ``views`` with ``R`` and ``t`` replaced (``pixels == 0``: the same poses).

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv.colmap import View
    >>> v = View("a.png", 1, 1, np.diag([500.0, 500.0, 1.0]), np.eye(3), np.zeros(3), (640, 480))
    >>> w = perturb_views([v], 2.0, [5.0], seed=0)[0]
    >>> round(float(np.radians(rotation_angle_deg(w.R @ v.R.T))) * 500, 6)  # f * theta, px
    2.0
    >>> round(float(np.linalg.norm(w.center - v.center)) * 500 / 5.0, 6)  # f * d / z, px
    2.0
    """
    if not np.isfinite(pixels) or pixels < 0:
        raise ValueError(f"pixels must be a finite number >= 0, got {pixels!r}")
    depths = np.asarray(depths, dtype=float)
    if depths.shape != (len(views),) or not np.all(np.isfinite(depths) & (depths > 0)):
        raise ValueError(f"depths must hold one positive depth per view ({len(views)}), got shape {depths.shape}")
    rng = np.random.default_rng(seed)
    out = []
    for v, z in zip(views, depths):
        f = float(v.K[0, 0])
        dR = cv2.Rodrigues(_unit(rng) * (pixels / f))[0]
        R = dR @ v.R
        c = v.center + _unit(rng) * (pixels * z / f)
        out.append(dataclasses.replace(v, R=R, t=-R @ c))
    return out


def relative_rotation_errors(views, true_views) -> np.ndarray:
    """Per pair ``a < b``, the angle between the relative rotations of ``views`` and of ``true_views``, degrees.

    The relative rotation of a pair is ``R_b @ R_a.T``; the error does not
    depend on the world frame, so poses aligned to another frame by a
    similarity compare as they are. Views are matched by name.

    Returns
    -------
    (n * (n - 1) / 2,) float64

    >>> import numpy as np
    >>> from episeg_cv.colmap import View
    >>> K = np.diag([500.0, 500.0, 1.0])
    >>> a = [View(n, i, 1, K, np.eye(3), np.zeros(3), (640, 480)) for i, n in enumerate("xyz")]
    >>> b = [dataclasses.replace(v, R=cv2.Rodrigues(np.array([0.01, 0, 0]))[0]) for v in a]  # one common turn
    >>> relative_rotation_errors(b, a).round(9).tolist()
    [0.0, 0.0, 0.0]
    """
    by_name = {v.name: v for v in views}
    T = list(true_views)
    errors = []
    for i in range(len(T)):
        for j in range(i + 1, len(T)):
            ta, tb, ea, eb = T[i], T[j], by_name[T[i].name], by_name[T[j].name]
            errors.append(rotation_angle_deg((tb.R @ ta.R.T).T @ (eb.R @ ea.R.T)))
    return np.array(errors, dtype=float)


def trimmed_similarity(source, target, keep: float = 0.5, rounds: int = 5) -> tuple:
    """:func:`episeg_cv.colmap.adjust.similarity` on the pairs it fits best (trimmed least squares): first on
    the share ``keep`` of the pairs
    nearest to the medians of both sets, then ``rounds`` times on the share ``keep`` with the smallest residuals
    of the previous fit. Wrong matches, triangulated far off and differently by two sets of poses, would
    otherwise pull the similarity.

    >>> rng = np.random.default_rng(0)
    >>> X = rng.normal(size=(40, 3))
    >>> Y = 2 * X + [1, 2, 3]
    >>> Y[:12] += rng.normal(scale=50.0, size=(12, 3))  # 30 % wild pairs
    >>> s, Q, c = trimmed_similarity(X, Y)
    >>> round(s, 9), bool(np.allclose(Q, np.eye(3))), np.round(c, 9).tolist()
    (2.0, True, [1.0, 2.0, 3.0])
    """
    source, target = np.asarray(source, dtype=float), np.asarray(target, dtype=float)
    if not 0 < keep <= 1:
        raise ValueError(f"keep must be in (0, 1], got {keep!r}")
    n = max(3, int(np.ceil(keep * len(source))))
    # start from the pairs nearest to the medians of both sets (a far-off point would ruin a first fit on all)
    ranks = [np.argsort(np.argsort(np.linalg.norm(x - np.median(x, axis=0), axis=1), kind="stable"), kind="stable")
             for x in (source, target)]
    best = np.argsort(np.maximum(*ranks), kind="stable")[:n]
    for _ in range(rounds):
        s, Q, c = similarity(source[best], target[best])
        residual = np.linalg.norm(s * source @ Q.T + c - target, axis=1)
        best = np.argsort(residual, kind="stable")[:n]
    return similarity(source[best], target[best])


def tracks(rec) -> list:
    """``[(xyz, [(image_id, point2D_idx), ...]), ...]``: the 3D points of a pycolmap Reconstruction and their tracks."""
    return [(np.array(p.xyz, dtype=float), [(int(e.image_id), int(e.point2D_idx)) for e in p.track.elements])
            for p in rec.points3D.values()]


def corresponding_points(tracks_a, tracks_b) -> tuple:
    """The points of two triangulations of one database that share an observation (a keypoint of an image).

    ``tracks_a``, ``tracks_b``: as :func:`tracks` gives them. A point of ``a``
    pairs with the point of ``b`` that holds most of its observations (the
    first such on a tie); points of ``a`` with none in ``b`` are left out.

    Returns
    -------
    A, B : (K, 3) float64
        ``A[k]`` of ``a`` and ``B[k]`` of ``b`` hold the same keypoints.

    >>> a = [(np.zeros(3), [(1, 5), (2, 7)]), (np.ones(3), [(1, 6), (3, 0)])]
    >>> b = [(np.full(3, 9.0), [(2, 7), (3, 1)]), (np.full(3, 8.0), [(4, 4)])]
    >>> A, B = corresponding_points(a, b)
    >>> A.tolist(), B.tolist()
    ([[0.0, 0.0, 0.0]], [[9.0, 9.0, 9.0]])
    """
    owner = {obs: k for k, (_, track) in enumerate(tracks_b) for obs in track}
    A, B = [], []
    for xyz, track in tracks_a:
        hits = [owner[o] for o in track if o in owner]
        if hits:
            A.append(xyz)
            B.append(tracks_b[max(dict.fromkeys(hits), key=hits.count)][0])
    return np.array(A, dtype=float).reshape(-1, 3), np.array(B, dtype=float).reshape(-1, 3)


def box_depths(views, box) -> np.ndarray:
    """Distance from each camera centre to the centre of the box ``(low, high)`` (world units), ``(n,)``."""
    centre = (np.asarray(box[0], float) + np.asarray(box[1], float)) / 2.0
    return np.array([np.linalg.norm(v.center - centre) for v in views])


def median_depths(depth_maps) -> np.ndarray:
    """Median of the finite depths of each rendered depth map, ``(n,)``."""
    return np.array([float(np.median(d[np.isfinite(d)])) for d in depth_maps])
