"""Posed views: one image with its pinhole camera, COLMAP camera model, world pose and depth range.

Conventions
-----------
- Poses are world-to-camera, ``X_cam = R @ X_world + t`` (as
  :meth:`TwoViewGeometry.from_world_poses` and COLMAP's ``cam_from_world``);
  the pair ``(i, j)`` has ``X_j = R X_i + t``.
- Keypoints are in episeg_cv's pixel convention (the centre of the top-left
  pixel is ``(0, 0)``), in the *raw* (distorted) image. COLMAP's convention,
  ``(0.5, 0.5)``, is applied only where the database is written.
- The epipolar constraint needs a pinhole camera. Every keypoint of a camera
  with distortion is mapped through COLMAP's own camera model
  (``pycolmap.Camera.cam_from_img``, the exact inverse COLMAP uses) to a
  normalised ray, then to the pinhole image of the camera's calibration
  matrix ``K``. The constraint, and its pixel tolerance, act there; the
  database gets the raw keypoints.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from .._validation import as_camera_matrix, as_depth_range, as_image_size, as_rotation, as_vector3
from ..geometry import TwoViewGeometry

__all__ = ["View", "PINHOLE_MODELS", "depth_range_from_depths", "is_bounded", "require_pycolmap", "rig_pose",
           "camera_pose", "poses_agree"]

#: COLMAP camera models without distortion: pinhole keypoints are the raw ones.
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")


def require_pycolmap():
    """The pycolmap module, or an ImportError that says how to install it."""
    try:
        import pycolmap
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError('episeg_cv.colmap needs pycolmap: pip install "episeg_cv[colmap]"') from e
    return pycolmap


@dataclass(frozen=True, eq=False)
class View:
    """One posed image.

    Attributes
    ----------
    name : str
        Image path relative to the image folder (as in a COLMAP model).
    image_id, camera_id : int
        COLMAP ids (kept from the model, so the database agrees with it).
    K : (3, 3) float64
        Pinhole intrinsics, pixel centres at integer coordinates.
    R : (3, 3) float64
    t : (3,) float64
        World-to-camera pose, ``X_cam = R @ X_world + t``.
    image_size : (int, int)
        ``(width, height)``.
    camera_model : str
        COLMAP camera model name (``"PINHOLE"``, ``"SIMPLE_RADIAL"``, ``"OPENCV"``, ...).
    camera_params : tuple of float
        COLMAP camera parameters, in COLMAP's pixel convention.
    depth_range : (float, float)
        ``(zmin, zmax)`` of the scene in this camera, used for its segments.

    Examples
    --------
    >>> K = [[100, 0, 49.5], [0, 100, 49.5], [0, 0, 1]]
    >>> a = View("a.png", 1, 1, K, np.eye(3), [0, 0, 0], (100, 100), depth_range=(1, 10))
    >>> b = View("b.png", 2, 1, K, np.eye(3), [-1, 0, 0], (100, 100))   # 1 m to the right of a
    >>> a.camera_params, b.center.tolist()
    ((100.0, 100.0, 50.0, 50.0), [1.0, 0.0, 0.0])
    >>> g = a.geometry_to(b)
    >>> seg = g.segments([[49.5, 49.5]], a.depth_range)
    >>> np.round(seg.start, 1).tolist(), np.round(seg.end, 1).tolist()   # x2 = 49.5 - 100 / z, z in [1, 10]
    ([[-0.5, 49.5]], [[39.5, 49.5]])
    """

    name: str
    image_id: int
    camera_id: int
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    image_size: tuple
    camera_model: str = "PINHOLE"
    camera_params: tuple = field(default=())
    depth_range: tuple = (0.0, float("inf"))

    def __post_init__(self):
        object.__setattr__(self, "K", as_camera_matrix(self.K, f"K of image {self.name!r}"))
        object.__setattr__(self, "R", as_rotation(self.R, f"R of image {self.name!r}"))
        object.__setattr__(self, "t", as_vector3(self.t, f"t of image {self.name!r}"))
        object.__setattr__(self, "image_size", as_image_size(self.image_size, f"image_size of image {self.name!r}"))
        object.__setattr__(self, "depth_range", tuple(float(v) for v in as_depth_range(
            self.depth_range, None, f"depth_range of image {self.name!r}")))
        params = self.camera_params or (self.K[0, 0], self.K[1, 1], self.K[0, 2] + 0.5, self.K[1, 2] + 0.5)
        object.__setattr__(self, "camera_params", tuple(float(p) for p in params))

    def with_depth_range(self, depth_range) -> "View":
        """A copy with another ``depth_range``."""
        return dataclasses.replace(self, depth_range=depth_range)

    def geometry_to(self, other: "View") -> TwoViewGeometry:
        """The :class:`TwoViewGeometry` from this view to ``other`` (pinhole images).

        The same as :meth:`TwoViewGeometry.from_world_poses` on the two poses, without
        checking again what each view checked when it was made (a collection asks for
        every pair, some twice).
        """
        R, t = self.pose_to(other)
        return TwoViewGeometry.from_checked(self.K, other.K, R, t, self.image_size, other.image_size)

    def pose_to(self, other: "View") -> tuple:
        """``(R, t)`` from this camera to ``other``'s, ``X_other = R X_this + t``: ``(3, 3)`` and ``(3,)``
        float64, the pose of :meth:`geometry_to`."""
        R = other.R @ self.R.T  # a product of two rotations: a rotation, to rounding
        return R, other.t - R @ self.t

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in the world, ``-R^T t``."""
        return -self.R.T @ self.t

    def _camera(self):
        pycolmap = require_pycolmap()
        w, h = self.image_size
        return pycolmap.Camera(model=self.camera_model, width=w, height=h, params=list(self.camera_params))

    def undistort(self, points: np.ndarray) -> np.ndarray:
        """Raw keypoints ``(N, 2)`` -> their positions in the pinhole image of ``K``.

        Identity for ``SIMPLE_PINHOLE`` and ``PINHOLE``; otherwise COLMAP's
        own inverse of the camera model (``pycolmap.Camera.cam_from_img``); NaN
        where it has none (see :meth:`undistortable`).
        """
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if self.camera_model in PINHOLE_MODELS or len(pts) == 0:
            return pts.copy()
        rays = np.asarray(self._camera().cam_from_img(pts + 0.5), dtype=np.float64).reshape(-1, 2)
        return rays @ self.K[:2, :2].T + self.K[:2, 2]

    def undistortable(self, points: np.ndarray, tol: float = 0.05) -> np.ndarray:
        """``(N,)`` bool: where the camera model maps the raw pixel back to one pinhole position.

        True when COLMAP's inverse exists, the forward model maps it back to the
        pixel within ``tol`` pixels, and the distortion is locally one-to-one there
        (its Jacobian has a positive determinant). A distortion that folds over
        the image (``k1 = -5``, say) has pixels with no inverse, or an inverse on
        the wrong branch; their keypoints would match on the wrong segment.
        """
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if self.camera_model in PINHOLE_MODELS or len(pts) == 0:
            return np.ones(len(pts), dtype=bool)
        cam = self._camera()
        rays = np.asarray(cam.cam_from_img(pts + 0.5), dtype=np.float64).reshape(-1, 2)
        ok = np.all(np.isfinite(rays), axis=1)
        r = np.where(ok[:, None], rays, 0.0)

        def forward(d):
            xyz = np.column_stack([r + d, np.ones(len(r))])
            return np.asarray(cam.img_from_cam(xyz, check_cheirality=False), dtype=np.float64).reshape(-1, 2)

        eps = 1e-6
        back = forward(np.zeros(2)) - 0.5
        jx = (forward(np.array([eps, 0.0])) - forward(np.array([-eps, 0.0]))) / (2 * eps)
        jy = (forward(np.array([0.0, eps])) - forward(np.array([0.0, -eps]))) / (2 * eps)
        with np.errstate(invalid="ignore"):
            det = jx[:, 0] * jy[:, 1] - jx[:, 1] * jy[:, 0]
            return ok & (np.hypot(*(back - pts).T) <= tol) & (det > 0)


def depth_range_from_depths(depths, percentiles=(2.0, 98.0), margin: float = 0.25, min_points: int = 10):
    """A robust depth range from the depths of the 3D points an image sees.

    ``zmin = p_lo / (1 + margin)``, ``zmax = p_hi * (1 + margin)``, where
    ``p_lo, p_hi`` are the given percentiles of the positive depths.

    Returns
    -------
    (float, float)
        ``(0, inf)`` when fewer than ``min_points`` positive depths are given.

    Examples
    --------
    >>> depth_range_from_depths(np.linspace(2.0, 4.0, 101), percentiles=(0, 100), margin=0.0)
    (2.0, 4.0)
    >>> depth_range_from_depths([1.0, 2.0])
    (0.0, inf)
    """
    d = np.asarray(depths, dtype=np.float64).ravel()
    d = d[np.isfinite(d) & (d > 0)]
    if len(d) < min_points:
        return (0.0, float("inf"))
    lo, hi = np.percentile(d, percentiles)
    return (float(lo / (1.0 + margin)), float(hi * (1.0 + margin)))


def is_bounded(depth_range) -> bool:
    """Whether ``(zmin, zmax)`` says more than ``(0, inf)``."""
    return bool(depth_range[0] > 0 or np.isfinite(depth_range[1]))


# -- multi-camera rigs (pycolmap.Rig: cam_from_world = sensor_from_rig * rig_from_world) --------------------------
def _sensor_from_rig(rig, sensor_id):
    S = np.asarray(rig.sensor_from_rig(sensor_id).matrix(), dtype=np.float64)
    return S[:, :3], S[:, 3]


def rig_pose(rig, sensor_id, R, t):
    """``(R, t)`` of ``rig_from_world`` from the ``cam_from_world`` pose ``(R, t)`` of the camera ``sensor_id``
    of ``rig`` (a ``pycolmap.Rig``): ``X_rig = Rs^T (X_cam - ts)``; the reference camera's pose is the rig's."""
    if rig.is_ref_sensor(sensor_id):
        return np.asarray(R, np.float64), np.asarray(t, np.float64)
    Rs, ts = _sensor_from_rig(rig, sensor_id)
    return Rs.T @ R, Rs.T @ (np.asarray(t, np.float64) - ts)


def camera_pose(rig, sensor_id, R, t):
    """The inverse of :func:`rig_pose`: ``cam_from_world`` of camera ``sensor_id`` from ``rig_from_world`` ``(R, t)``."""
    if rig.is_ref_sensor(sensor_id):
        return np.asarray(R, np.float64), np.asarray(t, np.float64)
    Rs, ts = _sensor_from_rig(rig, sensor_id)
    return Rs @ R, Rs @ t + ts


def poses_agree(R1, t1, R2, t2, tol: float = 1e-6) -> bool:
    """Whether two ``cam_from_world`` (or ``rig_from_world``) poses are the same to ``tol``: rotation entries,
    and translations relative to ``max(1, |t1|)``.

    >>> poses_agree(np.eye(3), np.zeros(3), np.eye(3), [0, 0, 1e-9]), poses_agree(np.eye(3), [0, 0, 1], np.eye(3), [0, 0, 2])
    (True, False)
    """
    t1, t2 = np.asarray(t1, np.float64), np.asarray(t2, np.float64)
    return bool(np.abs(np.asarray(R1) - np.asarray(R2)).max() <= tol
                and np.abs(t1 - t2).max() <= tol * max(1.0, float(np.abs(t1).max())))
