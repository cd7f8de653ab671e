"""Two-view geometry with a known relative pose, and the correct epipolar segment.

Conventions (used throughout episeg_cv)
---------------------------------------
- Pose: a 3D point with coordinates ``X1`` in camera 1 has coordinates
  ``X2 = R @ X1 + t`` in camera 2 (the paper's, ``cv2.recoverPose``'s and
  ``cv2.stereoCalibrate``'s convention).
- Pixels: ``x = K n`` with ``n`` the normalised image point. Pixel centres are
  at integer coordinates, as for ``cv2.KeyPoint``, so an image of size
  ``(width, height)`` covers ``[-0.5, width - 0.5] x [-0.5, height - 0.5]``.

The formulation (``docs/geometry.md``)
-----------------------------------
For a pixel ``x1`` of image 1 and a depth ``z1`` along its ray, the homogeneous
image in view 2 is ``w(z1) = z1 * a + b`` with ``a = K2 R K1^-1 [x1; 1]``
(the homogeneous virtual infinity point) and ``b = K2 t`` (the homogeneous
epipole); ``w3`` is the depth in camera 2. With ``z1`` in ``[zmin, zmax]`` the
set of images is the segment ``U + s (V - U)``, ``s`` in ``[0, 1]``, of
``U = zmin a + b`` and ``V = zmax a + b`` (``V = a`` when ``zmax = inf``), up to
positive scale. Cheirality (``w3 > 0``) and the image rectangle are linear
inequalities in ``s``; clipping them (Liang-Barsky in homogeneous coordinates)
gives the visible segment. Every case of the paper's Proposition 2, the empty
case it misses, the epipole or ``p_inf`` at infinity, and pure rotation come
out of the same few array operations.

References
----------
S. Li, Q. Cai, Y. Wu, "Segmenting Epipolar Line", Proposition 2.
R. Hartley, A. Zisserman, Multiple View Geometry, 2nd ed., sec. 9.2 (p. 243)
for the fundamental matrix, and sec. 21 (p. 515) for cheirality.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from . import _geometry_kernels as _gk
from . import threads
from ._validation import (
    as_array,
    as_camera_matrix,
    as_covariance,
    as_depth_range,
    as_image_size,
    as_nonnegative,
    as_points,
    as_rotation,
    as_vector3,
)

__all__ = ["EpipolarGeometry", "TwoViewGeometry", "EpipolarSegments", "Rejection", "as_geometry", "as_calibrated"]

#: Relative tolerance of the strict cheirality test ``w3 > eps * (|U| + |V|)``.
CHEIRALITY_EPS = 1e-12


class Rejection:
    """Labels returned by :meth:`EpipolarSegments.classify`, one per point.

    ``ON_SEGMENT`` is acceptance; every other label is a reason for rejection.
    """

    ON_SEGMENT = 0  #: within ``tol`` of the visible segment
    BEYOND_INFINITY = 1  #: on the line, past the virtual infinity point
    BEYOND_EPIPOLE = 2  #: on the line, past the epipole
    OFF_LINE = 3  #: farther than ``tol`` from the epipolar line
    EMPTY_SEGMENT = 4  #: on the line, but the segment is empty (ray behind camera 2)
    OUT_OF_RANGE = 5  #: on the correct side of both, but outside the depth range (or the image)

    NAMES = ("on_segment", "beyond_infinity", "beyond_epipole", "off_line", "empty_segment", "out_of_range")


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _camera_inverse(K: np.ndarray) -> np.ndarray:
    """``K^-1`` of a checked camera matrix (upper triangular, last row ``[0, 0, 1]``), in closed form:
    a collection derives two per pair, and ``np.linalg.inv`` costs more than the arithmetic."""
    (fx, s, cx), (_, fy, cy), _ = K.tolist()
    return np.array([[1 / fx, -s / (fx * fy), (s * cy - cx * fy) / (fx * fy)], [0.0, 1 / fy, -cy / fy],
                     [0.0, 0.0, 1.0]])


def _rect(size: tuple[int, int], margin: float) -> np.ndarray:
    """``(4,)`` float64 ``(xmin, xmax, ymin, ymax)``: the image ``size = (w, h)`` grown by ``margin``. An
    array, as the kernels' own ``_pair_kernel._rect``: a tuple would compile the segment kernel once more."""
    w, h = size
    return np.array([-0.5 - margin, w - 0.5 + margin, -0.5 - margin, h - 0.5 + margin])


def point_segment_distance(p: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """(N,) distance from ``p[i]`` to the segment ``start[i] -> end[i]`` (all ``(N, 2)``, finite)."""
    d = end - start
    dd = np.einsum("ij,ij->i", d, d)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        u = np.clip(np.einsum("ij,ij->i", p - start, d) / dd, 0.0, 1.0)
    u = np.where(dd > 0, u, 0.0)
    return np.hypot(*(p - start - u[:, None] * d).T)


def _segment_distance(p: np.ndarray, start: np.ndarray, end: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """:meth:`EpipolarSegments.distance` of checked ``(N, 2)`` float64 points: inf where not ``valid``."""
    return np.where(valid, point_segment_distance(p, np.nan_to_num(start), np.nan_to_num(end)), np.inf)


@dataclass(frozen=True, eq=False)
class EpipolarSegments:
    """The visible epipolar segments in image 2 of ``N`` points of image 1.

    Made by :meth:`TwoViewGeometry.segments`; all arrays are in pixels of
    image 2 and are read-only.

    Attributes
    ----------
    start, end : (N, 2) float64
        Endpoints of the visible segment. ``start`` is the end at the smaller
        depth ``z1`` (towards the epipole), ``end`` the one at the larger
        depth (towards ``p_inf``). NaN where the segment is empty.
    valid : (N,) bool
        False where the segment is empty: the ray is wholly behind camera 2,
        or its image misses the (grown) image rectangle.
    line : (N, 3) float64
        Epipolar lines ``(a, b, c)`` with ``a**2 + b**2 = 1``, proportional to
        ``F @ [x1, 1]``. NaN when undefined (``t = 0``, or ``x1`` is the
        epipole of image 1).
    infinity_point : (N, 2) float64
        Virtual infinity points ``p_inf = (K2 R K1^-1 x1)`` dehomogenised;
        inf or NaN where ``(K2 R n1)_3 = 0``.
    epipole : (2,) float64
        The epipole in image 2; inf or NaN where ``t_3 = 0``.
    line_start, line_end : (N, 2) float64
        The whole epipolar line clipped to the same rectangle; NaN if it misses.
    margin : float
        How far the clipping rectangle was grown beyond the image, in pixels.
    """

    start: np.ndarray
    end: np.ndarray
    valid: np.ndarray
    line: np.ndarray
    infinity_point: np.ndarray
    epipole: np.ndarray
    margin: float
    _a: np.ndarray  # (N, 3) homogeneous p_inf
    _b: np.ndarray  # (3,) homogeneous epipole
    _rect: np.ndarray  # (4,) (xmin, xmax, ymin, ymax) of the clipping rectangle

    def __post_init__(self):
        for f in ("start", "end", "valid", "line", "infinity_point", "epipole", "_a", "_b"):
            getattr(self, f).flags.writeable = False

    @cached_property
    def _line_clip(self) -> tuple[np.ndarray, np.ndarray]:
        # computed on first use: guided matching on the segment never needs it. A writable copy of the
        # (frozen) lines, as the candidate index passes its own: numba types an array's flags, and a
        # read-only one compiled _line_clip once more (0.8 s of a first run)
        line = np.array(self.line, dtype=np.float64, order="C")
        start, end = np.empty((len(line), 2)), np.empty((len(line), 2))
        threads.run(_gk.line_clip, _gk.line_clip_parallel, len(line), line, self._rect, start, end)
        start.flags.writeable = end.flags.writeable = False
        return start, end

    @property
    def line_start(self) -> np.ndarray:
        """(N, 2) one end of the whole epipolar line clipped to the rectangle; NaN if it misses."""
        return self._line_clip[0]

    @property
    def line_end(self) -> np.ndarray:
        """(N, 2) the other end of the clipped epipolar line; NaN if it misses."""
        return self._line_clip[1]

    def __len__(self) -> int:
        return self.start.shape[0]

    @property
    def length(self) -> np.ndarray:
        """(N,) visible length in pixels; 0 where empty."""
        return np.where(self.valid, np.hypot(*(self.end - self.start).T), 0.0)

    @property
    def line_length(self) -> np.ndarray:
        """(N,) length of the whole epipolar line clipped to the rectangle; 0 where it misses."""
        d = np.hypot(*(self.line_end - self.line_start).T)
        return np.where(np.isfinite(d), d, 0.0)

    @property
    def reduction(self) -> np.ndarray:
        """(N,) ``1 - length / line_length``: the paper's "reduced search space".

        NaN where the line misses the image (``line_length == 0``).
        """
        ll = self.line_length
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            return np.where(ll > 0, 1.0 - np.minimum(self.length, ll) / ll, np.nan)

    def take(self, indices) -> "EpipolarSegments":
        """The segments at ``indices`` (any integer array), for pairwise tests."""
        idx = np.asarray(indices, dtype=np.intp)
        return EpipolarSegments(
            self.start[idx], self.end[idx], self.valid[idx], self.line[idx], self.infinity_point[idx],
            self.epipole, self.margin, self._a[idx], self._b, self._rect,
        )

    def _paired_points(self, points2) -> np.ndarray:
        p = as_points(points2, "points2")
        if p.shape[0] != len(self):
            raise ValueError(f"points2 must have shape ({len(self)}, 2), one point per segment, got shape {p.shape}")
        return p

    def distance(self, points2) -> np.ndarray:
        """Pixel distance from ``points2[i]`` to segment ``i``.

        Parameters
        ----------
        points2 : (N, 2) array_like
            Pixels of image 2, paired with the segments.

        Returns
        -------
        (N,) float64
            Euclidean distance in pixels; ``inf`` where the segment is empty.
        """
        return _segment_distance(self._paired_points(points2), self.start, self.end, self.valid)

    def line_distance(self, points2) -> np.ndarray:
        """(N,) pixel distance from ``points2[i]`` to epipolar line ``i``; inf where undefined."""
        p = self._paired_points(points2)
        d = np.abs((self.line[:, :2] * p).sum(axis=1) + self.line[:, 2])
        return np.where(np.isfinite(d), d, np.inf)

    def classify(self, points2, tol: float) -> np.ndarray:
        """Why ``points2[i]`` is, or is not, a possible match of point ``i``.

        Parameters
        ----------
        points2 : (N, 2) array_like
            Pixels of image 2, paired with the segments.
        tol : float
            Tolerance in pixels, for both the segment and the line.

        Returns
        -------
        (N,) int8
            :class:`Rejection` labels. A point within ``tol`` of the segment is
            ``ON_SEGMENT``; one farther than ``tol`` from the line is
            ``OFF_LINE``; the rest lie on the line but off the segment, and are
            labelled by the first of ``p_inf`` and the epipole that one crosses
            walking from the point to the segment.
        """
        tol = as_nonnegative(tol, "tol")
        p = self._paired_points(points2)
        on_seg = self.distance(p) <= tol
        on_line = self.line_distance(p) <= tol
        out = np.full(len(self), Rejection.OFF_LINE, dtype=np.int8)
        out[on_line & ~self.valid] = Rejection.EMPTY_SEGMENT
        rest = on_line & self.valid & ~on_seg
        if rest.any():
            out[rest] = self._side_labels(p[rest], np.flatnonzero(rest), tol)
        out[on_seg] = Rejection.ON_SEGMENT
        return out

    def _side_labels(self, p, idx, tol):
        line = self.line[idx]
        d = np.column_stack([-line[:, 1], line[:, 0]])  # unit direction along the line

        def coord(w):  # position along the line of homogeneous points; inf at infinity (never crossed)
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                u = np.einsum("ij,ij->i", w[:, :2], d) / w[:, 2]
            return np.where(w[:, 2] != 0, u, np.inf)

        u_p = np.einsum("ij,ij->i", p, d)
        u_s = np.einsum("ij,ij->i", self.start[idx], d)
        u_t = np.einsum("ij,ij->i", self.end[idx], d)
        lo, hi = np.minimum(u_s, u_t), np.maximum(u_s, u_t)
        u_e = coord(np.broadcast_to(self._b, (len(idx), 3)))
        u_i = coord(self._a[idx])
        below = u_p < lo
        # the stretch walked from the point to the segment, widened by tol at the segment's end
        a = np.where(below, u_p, hi - tol)
        b = np.where(below, lo + tol, u_p)

        def crossed(u):
            return (u >= a) & (u <= b)

        ce, ci = crossed(u_e), crossed(u_i)
        # first crossed from the point: the nearer to u_p
        e_first = ce & (~ci | (np.abs(u_e - u_p) < np.abs(u_i - u_p)))
        return np.where(e_first, Rejection.BEYOND_EPIPOLE, np.where(ci, Rejection.BEYOND_INFINITY, Rejection.OUT_OF_RANGE)).astype(np.int8)


class EpipolarGeometry:
    """What the segments and the matchers need from two views: the base of every geometry.

    A segment in image 2 is the set of ``w(z) = z a + b``, ``z >= 0`` (up to
    positive scale), with ``a = infinity_homography @ [x1, 1]`` and ``b =
    epipole_homogeneous``, clipped to image 2 (:meth:`TwoViewGeometry.segments`).
    :class:`TwoViewGeometry` (a calibrated pose) and
    :class:`~episeg_cv.FundamentalGeometry` (an oriented fundamental matrix:
    the half-line from the epipole) provide it; :class:`~episeg_cv.CandidateIndex`,
    the matchers and the filters accept either.

    Attributes
    ----------
    infinity_homography : (3, 3) float64
    epipole_homogeneous : (3,) float64
    image_size1, image_size2 : (int, int)
    is_calibrated : bool
        True when ``K1, K2, R, t`` are known (depth along each ray is metric).
    covariance : (6, 6) float64 or None
        Pose covariance (:meth:`TwoViewGeometry.with_covariance`); None for none.
    """

    is_calibrated = False
    covariance = None

    @property
    def epipole(self) -> np.ndarray:
        """(2,) the epipole in image 2, in pixels; inf or NaN when it is at infinity."""
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            return self.epipole_homogeneous[:2] / self.epipole_homogeneous[2]


class TwoViewGeometry(EpipolarGeometry):
    """Two calibrated pinhole views with a known relative pose.

    Parameters
    ----------
    K1, K2 : (3, 3) array_like
        Intrinsics, upper triangular with last row ``[0, 0, 1]``, in pixels.
    R : (3, 3) array_like
        Rotation from camera 1 to camera 2: ``X2 = R @ X1 + t``.
    t : (3,) array_like
        Translation, in any length unit (the unit of ``depth_range``).
    image_size1, image_size2 : (int, int)
        ``(width, height)`` of each image in pixels.

    Raises
    ------
    ValueError
        Wrong shapes, NaN or inf, a ``K`` that is not upper triangular with last
        row ``[0, 0, 1]`` or is singular, an ``R`` that is not a rotation within
        1e-6, a zero or negative image size.
    TypeError
        Non-numeric input.

    Examples
    --------
    >>> import numpy as np
    >>> K = [[50, 0, 50], [0, 50, 50], [0, 0, 1]]
    >>> geom = TwoViewGeometry(K, K, np.eye(3), [0, 0, 1], image_size1=(100, 100), image_size2=(100, 100))
    >>> seg = geom.segments([[90.0, 50.0]])
    >>> seg.start.round(3).tolist(), seg.end.round(3).tolist()   # from the epipole to p_inf = x1
    ([[50.0, 50.0]], [[90.0, 50.0]])
    >>> round(float(seg.reduction[0]), 4)
    0.6
    """

    def __init__(self, K1, K2, R, t, *, image_size1, image_size2):
        self._set(as_camera_matrix(K1, "K1"), as_camera_matrix(K2, "K2"), as_rotation(R, "R"), as_vector3(t, "t"),
                  as_image_size(image_size1, "image_size1"), as_image_size(image_size2, "image_size2"))

    is_calibrated = True

    @classmethod
    def from_checked(cls, K1, K2, R, t, image_size1, image_size2) -> "TwoViewGeometry":
        """A geometry from values that were checked already, with no checks at all.

        For code that holds checked values: another geometry's, or a
        :class:`~episeg_cv.colmap.View`'s (a collection asks for every pair).
        ``K1, K2`` ``(3, 3)`` and ``R`` ``(3, 3)`` (a rotation), ``t`` ``(3,)``, all
        C-contiguous float64; sizes ``(width, height)`` tuples of int. Anything else
        gives wrong results, not an error: from user input, use the constructor.
        """
        out = cls.__new__(cls)
        out._set(K1, K2, R, t, image_size1, image_size2)
        return out

    def _set(self, K1, K2, R, t, image_size1, image_size2):
        """Store checked values and derive the rest (the one place that does, for every constructor)."""
        self.K1, self.K2, self.R, self.t = K1, K2, R, t
        self.image_size1, self.image_size2 = image_size1, image_size2
        for a in (self.K1, self.K2, self.R, self.t):
            a.flags.writeable = False
        #: (3, 3) the infinite homography ``K2 R K1^-1``: ``a = H [x1; 1]``.
        self.infinity_homography = self.K2 @ self.R @ _camera_inverse(self.K1)
        #: (3,) the homogeneous epipole in image 2, ``K2 t``.
        self.epipole_homogeneous = self.K2 @ self.t
        self.infinity_homography.flags.writeable = False
        self.epipole_homogeneous.flags.writeable = False

    # -- alternative constructors -------------------------------------------------
    @classmethod
    def from_world_poses(cls, K1, R1, t1, K2, R2, t2, *, image_size1, image_size2) -> "TwoViewGeometry":
        """Build from world-to-camera poses ``X_cam = R X_w + t`` (OpenCV, COLMAP).

        Examples
        --------
        >>> import numpy as np
        >>> K = np.diag([500.0, 500.0, 1.0]); K[:2, 2] = 320, 240
        >>> g = TwoViewGeometry.from_world_poses(K, np.eye(3), [0, 0, 0], K, np.eye(3), [-1, 0, 0],
        ...                                      image_size1=(640, 480), image_size2=(640, 480))
        >>> g.t.tolist()
        [-1.0, 0.0, 0.0]
        """
        R1, R2 = as_rotation(R1, "R1"), as_rotation(R2, "R2")
        t1, t2 = as_vector3(t1, "t1"), as_vector3(t2, "t2")
        R = R2 @ R1.T
        return cls(K1, K2, R, t2 - R @ t1, image_size1=image_size1, image_size2=image_size2)

    @classmethod
    def from_projection_matrices(cls, P1, P2, *, image_size1, image_size2) -> "TwoViewGeometry":
        """Build from two finite ``3 x 4`` cameras ``P = K [R | t]`` (any non-zero scale, either sign).

        ``P`` and ``-P`` are the same projective camera but differ in which
        side is "in front"; the sign is fixed so that ``det(P[:, :3]) > 0``,
        which holds for ``K [R | t]`` with positive focal lengths.
        """
        Ks, Rs, ts = [], [], []
        for name, P in (("P1", P1), ("P2", P2)):
            P = as_array(P, name, (3, 4))
            scale = np.abs(P[:, :3]).max()
            det = np.linalg.det(P[:, :3] / scale) if scale > 0 else 0.0  # scale-free, cannot overflow
            if not abs(det) > 1e-12:
                raise ValueError(f"{name} must be a finite camera K [R | t] with an invertible left 3x3 block")
            P = P * np.sign(det)
            K, R = _rq(P[:, :3])
            Ks.append(K / K[2, 2])
            Rs.append(R)
            ts.append(np.linalg.solve(K, P[:, 3]))
        return cls.from_world_poses(Ks[0], Rs[0], ts[0], Ks[1], Rs[1], ts[1], image_size1=image_size1, image_size2=image_size2)

    def inverse(self) -> "TwoViewGeometry":
        """The same pair with the views swapped: ``R.T``, ``-R.T @ t``, sizes and ``K`` swapped.

        Built from this geometry's checked values, with no second validation.
        """
        inv = TwoViewGeometry.from_checked(self.K2, self.K1, np.ascontiguousarray(self.R.T), -self.R.T @ self.t,
                                       self.image_size2, self.image_size1)
        if self.covariance is not None:
            # R' = R^T, t' = -R^T t: to first order dtheta' = -R^T dtheta, dt' = -R^T dt - R^T [t]x dtheta
            G = np.zeros((6, 6))
            G[:3, :3] = -self.R.T
            G[3:, :3] = -self.R.T @ _skew(self.t)
            G[3:, 3:] = -self.R.T
            inv.covariance = _frozen(G @ self.covariance @ G.T)
        return inv

    def with_covariance(self, cov) -> "TwoViewGeometry":
        """The same pose with an uncertainty: a new geometry whose :attr:`covariance` is ``cov``.

        Parameters
        ----------
        cov : (6, 6) array_like
            Covariance of ``xi = (dtheta, dt)``, the error of the pose, with the
            true pose ``R = expm([dtheta]_x) @ R0`` (a *left* perturbation: the
            rotation vector ``dtheta`` is in camera 2's frame, radians) and
            ``t = t0 + dt`` (the unit of ``t``). Symmetric positive
            semi-definite; ``None`` removes the covariance.

        Returns
        -------
        TwoViewGeometry
            Matchers given it search, for each query, a band that is ``kappa``
            standard deviations of the propagated error wide (and a little
            longer at the geometric ends), instead of a fixed ``tol``
            (:meth:`bands`, :func:`~episeg_cv.pose_covariance`).

        Raises
        ------
        ValueError
            Not ``(6, 6)``, not finite, not symmetric, or not positive semi-definite.

        Examples
        --------
        >>> import numpy as np
        >>> K = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]
        >>> g = TwoViewGeometry(K, K, np.eye(3), [-1, 0, 0], image_size1=(640, 480), image_size2=(640, 480))
        >>> gc = g.with_covariance(np.diag([1e-6] * 3 + [1e-4] * 3))
        >>> gc.covariance.shape, g.covariance is None
        ((6, 6), True)
        """
        out = TwoViewGeometry.from_checked(self.K1, self.K2, self.R, self.t, self.image_size1, self.image_size2)
        out.covariance = None if cov is None else _frozen(as_covariance(cov, "cov"))
        return out

    def bands(self, points1, *, tol: float = 2.0, kappa: float = 2.576, depth_range=(0.0, np.inf),
              margin: float | None = None, max_reach: float | None = None):
        """The per-query search bands that :attr:`covariance` implies (:func:`episeg_cv.uncertainty.epipolar_bands`)."""
        from .uncertainty import epipolar_bands  # (uncertainty builds on this module)
        return epipolar_bands(self, points1, tol=tol, kappa=kappa, depth_range=depth_range, margin=margin,
                              max_reach=max_reach)

    # -- classic quantities ----------------------------------------------------
    @property
    def essential_matrix(self) -> np.ndarray:
        """(3, 3) ``E = [t]_x R``, with ``n2^T E n1 = 0`` for normalised points."""
        return _skew(self.t) @ self.R

    @property
    def fundamental_matrix(self) -> np.ndarray:
        """(3, 3) ``F = K2^-T E K1^-1``, with ``[x2, 1] F [x1, 1] = 0`` in pixels."""
        return _camera_inverse(self.K2).T @ self.essential_matrix @ _camera_inverse(self.K1)

    def __repr__(self) -> str:
        return (f"TwoViewGeometry(R=rotvec {np.round(_rotvec(self.R), 4).tolist()}, t={np.round(self.t, 4).tolist()}, "
                f"image_size1={self.image_size1}, image_size2={self.image_size2})")

    # -- the segment ---------------------------------------------------------------
    def transfer(self, points1, depths) -> tuple[np.ndarray, np.ndarray]:
        """Project the points of image 1 at depths ``z1`` into image 2.

        Parameters
        ----------
        points1 : (N, 2) array_like
            Pixels of image 1.
        depths : float or (N,) array_like
            Depth ``z1`` along each ray, in camera 1 (the unit of ``t``).

        Returns
        -------
        points2 : (N, 2) float64
            Pixels in image 2 (meaningful only where ``z2 > 0``).
        z2 : (N,) float64
            Depth in camera 2.
        """
        x1 = as_points(points1, "points1")
        z = np.asarray(depths, dtype=np.float64)
        if z.ndim > 1 or (z.ndim == 1 and z.shape[0] != x1.shape[0]) or not np.all(np.isfinite(z)):
            raise ValueError(f"depths must be a finite scalar or have shape ({x1.shape[0]},), got {z.shape}")
        z = np.broadcast_to(z, (x1.shape[0],))
        w = z[:, None] * (x1 @ self.infinity_homography[:, :2].T + self.infinity_homography[:, 2]) + self.epipole_homogeneous
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            return w[:, :2] / w[:, 2:3], w[:, 2].copy()

    def segments(self, points1, depth_range=(0.0, np.inf), margin: float = 0.0) -> EpipolarSegments:
        """The correct, visible epipolar segment in image 2 of each point of image 1.

        Parameters
        ----------
        points1 : (N, 2) array_like
            Pixels of image 1 (``N = 0`` is allowed).
        depth_range : (zmin, zmax), optional
            Bounds on the depth ``z1`` in camera 1, in the unit of ``t``: two
            scalars, or two ``(N,)`` arrays for per-point bounds.
            ``0 <= zmin < zmax <= inf``. Default ``(0, inf)``: cheirality only.
        margin : float, optional
            Grow the image-2 rectangle used for clipping by this many pixels.

        Returns
        -------
        EpipolarSegments

        Raises
        ------
        ValueError
            ``points1`` not ``(N, 2)`` or not finite, a bad depth range, a
            negative margin.

        Notes
        -----
        Covers every case of the paper's Proposition 2 and those it misses:
        the epipole or ``p_inf`` at infinity, the ray wholly behind camera 2
        (empty: ``valid`` is False) and pure rotation (a single point).

        One compiled pass per point (numba; float64 without fast-math or
        fused multiply-adds; division by zero gives inf or NaN, as numpy's),
        on every core for large inputs (:func:`episeg_cv.set_num_threads`),
        with the same bits for every thread count: 10-15 M points/s per core
        on the machines of ``benchmarks/table1.py``. ``a = H [x1; 1]`` is summed as ``x H[:, 0] + y H[:, 1] + H[:, 2]``,
        which may differ from numpy's ``x1 @ H[:, :2].T + H[:, 2]`` by an
        ulp (the array formulation, given the same ``a``, agrees to the last
        bit: ``tests/core/test_segment_kernel.py``).
        """
        x1 = np.ascontiguousarray(as_points(points1, "points1"))
        zmin, zmax = as_depth_range(depth_range, x1.shape[0])
        margin = as_nonnegative(margin, "margin")
        zmin = np.ascontiguousarray(np.atleast_1d(zmin), dtype=np.float64)
        zmax = np.ascontiguousarray(np.atleast_1d(zmax), dtype=np.float64)
        rect = _rect(self.image_size2, margin)
        # (called on a FundamentalGeometry too, which has the operators but not this class's methods)
        start, end, valid, line, p_inf, a = TwoViewGeometry._segment_arrays(self, x1, zmin, zmax, rect)
        return EpipolarSegments(start, end, valid, line, p_inf, self.epipole, margin, a,
                                self.epipole_homogeneous.copy(), rect)

    def _segment_arrays(self, x1: np.ndarray, zmin: np.ndarray, zmax: np.ndarray, rect: np.ndarray) -> tuple:
        """The arrays of :meth:`segments` on checked inputs, as the kernel gives them (writable, no
        :class:`EpipolarSegments`): ``(start, end, valid, line, p_inf, a)``. ``x1 (N, 2)`` C-contiguous
        float64, ``zmin`` / ``zmax`` ``(1,)`` or ``(N,)`` float64, ``rect`` from ``_rect``."""
        n = x1.shape[0]
        H, b = np.ascontiguousarray(self.infinity_homography), self.epipole_homogeneous
        # numpy allocates the outputs: its large arrays get huge pages (numba's would fault page by page)
        start, end, p_inf = np.empty((n, 2)), np.empty((n, 2)), np.empty((n, 2))
        valid, line, a = np.empty(n, dtype=np.bool_), np.empty((n, 3)), np.empty((n, 3))
        threads.run(_gk.segments, _gk.segments_parallel, n, x1, H, b, zmin, zmax, rect, CHEIRALITY_EPS,
                    start, end, valid, line, p_inf, a)
        return start, end, valid, line, p_inf, a


def as_geometry(geometry, name: str = "geometry") -> EpipolarGeometry:
    """``geometry`` itself, or ``TypeError`` naming ``name`` when it is not an :class:`EpipolarGeometry`
    (a :class:`TwoViewGeometry` or a :class:`~episeg_cv.FundamentalGeometry`)."""
    if not isinstance(geometry, EpipolarGeometry):
        raise TypeError(f"{name} must be a TwoViewGeometry or a FundamentalGeometry, got {type(geometry).__name__}")
    return geometry


def as_calibrated(geometry, name: str = "geometry") -> TwoViewGeometry:
    """``geometry`` itself when it is a :class:`TwoViewGeometry` (a calibrated pose), else ``TypeError``."""
    if not isinstance(geometry, TwoViewGeometry):
        raise TypeError(f"{name} must be a TwoViewGeometry (K1, K2, R, t), got {type(geometry).__name__}")
    return geometry


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64)
    a.flags.writeable = False
    return a


def _rq(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RQ decomposition ``M = K R`` with ``diag(K) > 0`` and ``R`` orthonormal."""
    J = np.flipud(np.eye(3))
    Q, U = np.linalg.qr((J @ M).T)
    K = J @ U.T @ J
    R = J @ Q.T
    S = np.diag(np.sign(np.diag(K)))
    return K @ S, S @ R


def _rotvec(R: np.ndarray) -> np.ndarray:
    angle = np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    n = np.linalg.norm(axis)
    return axis / n * angle if n > 1e-12 else np.zeros(3)
