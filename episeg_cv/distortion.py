"""Lens distortion: OpenCV's coefficients, and moving keypoints into the pinhole image.

The epipolar segment is a pinhole construction. Keypoints of a distorted
image are first moved to where an ideal pinhole camera with the same ``K``
would see them (:func:`undistort_points`); the constraint acts there.
"""

from __future__ import annotations

import cv2
import numpy as np

from ._validation import as_camera_matrix, as_points

__all__ = ["DIST_LENGTHS", "as_distortion", "undistort_points", "UNDISTORT_CRITERIA", "ROUND_TRIP_PX"]

#: Valid numbers of distortion coefficients (OpenCV's model).
DIST_LENGTHS = (4, 5, 8, 12, 14)


def as_distortion(d, name: str, source: str):
    """OpenCV distortion coefficients as a ``(k,)`` float64 array, ``k`` in 4, 5, 8, 12, 14; None when
    ``d`` is None, empty or all zero. Errors are prefixed with ``source`` (a file name)."""
    if d is None:
        return None
    try:
        arr = np.asarray(d, dtype=np.float64).ravel()
    except (ValueError, TypeError):
        raise ValueError(f"{source}: key '{name}' must be a list of 4, 5, 8, 12 or 14 numbers, got {d!r}") from None
    if arr.size == 0:
        return None
    if arr.size not in DIST_LENGTHS or not np.all(np.isfinite(arr)):
        raise ValueError(f"{source}: key '{name}' must hold 4, 5, 8, 12 or 14 finite distortion coefficients, "
                         f"got {arr.size}")
    return None if not np.any(arr) else arr


#: Termination of the iterative undistortion (OpenCV's default is 5 iterations).
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-9)


def undistort_points(points, K, dist) -> np.ndarray:
    """Move pixels of a distorted image into the pinhole image with the same ``K``.

    ``cv2.undistortPoints(points, K, dist, P=K)``: the output is where each
    point would be seen by an ideal pinhole camera ``K`` (same image size), so
    the epipolar segment of :class:`~episeg_cv.TwoViewGeometry` applies to it.
    Use it on the keypoints of both images before matching.

    Parameters
    ----------
    points : (N, 2) array_like
        Pixels of the distorted (as-captured) image.
    K : (3, 3) array_like
        The camera matrix.
    dist : (k,) array_like or None
        OpenCV distortion coefficients, ``k`` in 4, 5, 8, 12, 14. None or all
        zero returns a copy of ``points``.

    Returns
    -------
    (N, 2) float64
        Undistorted pixels; NaN where the distortion has no inverse there: where
        distorting the result again does not come back to the point (within
        :data:`ROUND_TRIP_PX`), or where the distortion folds (its Jacobian
        determinant is not positive), as ``k1 = -5`` does beyond a radius.
        ``cv2.undistortPoints`` returns some position for such points, from which
        a match would be searched on the wrong epipolar segment.

    Examples
    --------
    >>> K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    >>> undistort_points([[319.5, 239.5], [600.0, 400.0]], K, [0.1, 0, 0, 0]).round(2).tolist()
    [[319.5, 239.5], [589.54, 394.02]]
    >>> undistort_points([[319.5, 239.5], [600.0, 400.0]], K, [-5.0, 0, 0, 0]).round(2).tolist()  # folds
    [[319.5, 239.5], [nan, nan]]
    """
    p = as_points(points, "points")
    K = as_camera_matrix(K, "K")
    d = as_distortion(dist, "dist", "undistort_points")
    if d is None or len(p) == 0:
        return p.copy()
    out = cv2.undistortPoints(p.reshape(-1, 1, 2), K, d, None, None, K, UNDISTORT_CRITERIA).reshape(-1, 2)
    out = out.astype(np.float64)
    out[~_maps_back(out, p, K, d)] = np.nan
    return out


#: Largest pixel error of the round trip (undistort, then distort again) for a point to keep its position.
ROUND_TRIP_PX = 0.05


def _maps_back(undistorted: np.ndarray, points: np.ndarray, K: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(N,) bool: distorting ``undistorted`` gives ``points`` again, where the distortion is one-to-one."""
    n = np.column_stack([np.linalg.solve(K, np.column_stack([undistorted, np.ones(len(undistorted))]).T).T[:, :2],
                         np.ones(len(undistorted))])

    def distort(offset):
        x = n + np.array([offset[0], offset[1], 0.0])
        return cv2.projectPoints(x.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, d)[0].reshape(-1, 2)

    eps = 1e-6
    with np.errstate(invalid="ignore"):
        back = distort((0.0, 0.0))
        jx = (distort((eps, 0.0)) - distort((-eps, 0.0))) / (2 * eps)
        jy = (distort((0.0, eps)) - distort((0.0, -eps))) / (2 * eps)
        det = jx[:, 0] * jy[:, 1] - jx[:, 1] * jy[:, 0]
        return np.all(np.isfinite(undistorted), axis=1) & (np.hypot(*(back - points).T) <= ROUND_TRIP_PX) & (det > 0)

