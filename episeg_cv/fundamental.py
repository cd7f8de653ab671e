"""No calibration: an *oriented* fundamental matrix, whose segments are half-lines from the epipole.

With ``F`` alone, depth has no metric meaning, so there is no ``p_inf`` and no
depth range; but the oriented epipolar constraint (Chum, Werner, Matas 2004)
still holds: with ``x1, x2`` homogeneous with a positive last coordinate, every
correct pair satisfies ``e2 x x2 ~+ F x1`` (equal up to a *positive* scale)
once the sign of ``F`` is fixed (``F`` and ``-F`` are the same unoriented
matrix). On the line ``l = F x1`` the points are ``x2 = alpha e2 + beta J l``
with ``J l = (l2, -l1, 0)`` its point at infinity, and ``e2 x x2 = beta e2_3 l``;
with ``e2_3 > 0`` the constraint is ``beta > 0``: the half-line from the
epipole in the direction ``(l2, -l1)``. It excludes the other half of each
line, the side behind the epipole.

That half-line is the library's segment ``w(z) = z a + b``, ``z >= 0``, with
``b = e2`` and ``a = J F x1``, i.e. ``infinity_homography = J F``: the segment
code, the candidate index, the matchers and the filters run on it unchanged.

The sign is fixed by a majority over matches that are mostly right (the
RANSAC inliers): :meth:`FundamentalGeometry.oriented`. The reverse direction
(``inverse()``, used by ``cross_check``) is oriented separately on the same
matches: its majority sign is not the forward one in general. With the
epipole at infinity (rectified stereo: ``e2_3 = 0``) the lines do not meet
and the constraint is all or nothing on each: the whole line is searched.
"""

from __future__ import annotations

import numpy as np

from ._validation import as_array, as_image_size, as_points
from .geometry import EpipolarGeometry, EpipolarSegments, TwoViewGeometry, _rect

__all__ = ["FundamentalGeometry", "orientation_sign"]

#: ``J`` with ``J l = (l2, -l1, 0)``: the point at infinity, in the direction ``(l2, -l1)``, of a line ``l``.
J = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])

#: Third coordinate of the unit epipole below which it is at infinity (rectified): the whole line is searched.
MIN_EPIPOLE_W = 1e-9


def _null_vectors(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit ``(e1, e2)`` with ``F e1 = 0`` and ``F^T e2 = 0``."""
    U, _, Vt = np.linalg.svd(F)
    return Vt[2], U[:, 2]


def _signed(e: np.ndarray) -> np.ndarray:
    """``e`` with a non-negative third coordinate (the first non-zero one, if that is 0)."""
    nz = np.flatnonzero(np.abs(e) > 1e-15)
    ref = 2 if abs(e[2]) > 1e-15 else (nz[-1] if nz.size else 0)
    return -e if e[ref] < 0 else e


def orientation_sign(F, epipole2, points1, points2) -> tuple[float, float]:
    """``(sign, agreement)``: the sign of ``F`` that most pairs satisfy ``e2 x x2 ~+ F x1`` with, and the
    fraction that agree with it (NaN with no pair)."""
    x1 = np.column_stack([points1, np.ones(len(points1))])
    x2 = np.column_stack([points2, np.ones(len(points2))])
    s = np.einsum("ij,ij->i", np.cross(epipole2, x2), x1 @ np.asarray(F).T)
    sign = 1.0 if np.sum(s > 0) >= np.sum(s < 0) else -1.0
    return sign, (float(np.mean(sign * s > 0)) if len(s) else float("nan"))


class FundamentalGeometry(EpipolarGeometry):
    """Two uncalibrated views related by an oriented fundamental matrix (module docstring).

    Parameters
    ----------
    F : (3, 3) array_like
        Fundamental matrix, ``[x2, 1] F [x1, 1] = 0`` in pixels, rank 2, with
        its sign already oriented (use :meth:`oriented` to orient it from matches).
    image_size1, image_size2 : (int, int)
        ``(width, height)`` in pixels.
    reverse_sign : {1, -1} or None, optional
        The orientation of ``F^T`` for :meth:`inverse`; None: unknown
        (``inverse()`` then raises).

    Attributes
    ----------
    fundamental_matrix : (3, 3) float64
        ``F``, scaled to unit Frobenius norm, oriented.
    agreement : float
        Fraction of the matches that agreed with the orientation (NaN if not oriented from matches).

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv import TwoViewGeometry
    >>> K = [[100, 0, 50], [0, 100, 50], [0, 0, 1]]
    >>> g = TwoViewGeometry(K, K, np.eye(3), [0, 0, 1], image_size1=(100, 100), image_size2=(100, 100))
    >>> x1 = np.array([[90.0, 50.0], [50.0, 10.0], [20.0, 80.0]]); x2, _ = g.transfer(x1, 2.0)
    >>> f = FundamentalGeometry.oriented(g.fundamental_matrix, x1, x2, image_size1=(100, 100),
    ...                                  image_size2=(100, 100))
    >>> s = f.segments([[90.0, 50.0]])
    >>> s.start.round(3).tolist(), s.end.round(3).tolist()   # from the epipole outwards: x1 is not the end
    ([[50.0, 50.0]], [[99.5, 50.0]])
    """

    def __init__(self, F, *, image_size1, image_size2, reverse_sign=None):
        F = as_array(F, "F", (3, 3))
        s = np.linalg.svd(F, compute_uv=False)
        if not s[1] > 1e-12 * s[0]:
            raise ValueError(f"F must have rank 2, got singular values {np.round(s, 6).tolist()}")
        if s[2] > 1e-6 * s[0]:
            raise ValueError(f"F must have rank 2 (a zero smallest singular value), got singular values "
                             f"{np.round(s / s[0], 9).tolist()} (relative)")
        if reverse_sign not in (None, 1, -1, 1.0, -1.0):
            raise ValueError(f"reverse_sign must be 1, -1 or None, got {reverse_sign!r}")
        self._set(F / np.linalg.norm(F), as_image_size(image_size1, "image_size1"),
                  as_image_size(image_size2, "image_size2"), reverse_sign, float("nan"))

    def _set(self, F, image_size1, image_size2, reverse_sign, agreement):
        self.fundamental_matrix = np.array(F, dtype=np.float64)
        self.image_size1, self.image_size2 = image_size1, image_size2
        self.reverse_sign = None if reverse_sign is None else float(reverse_sign)
        self.agreement = agreement
        _, e2 = _null_vectors(self.fundamental_matrix)
        #: (3,) the epipole in image 2 (unit, third coordinate >= 0).
        self.epipole_homogeneous = _signed(e2)
        #: True when the epipole is at infinity (rectified): every half-line is then the whole line.
        self.at_infinity = bool(self.epipole_homogeneous[2] < MIN_EPIPOLE_W)
        #: (3, 3) ``J F``: ``a = J F [x1; 1]`` is the point at infinity in the half-line's direction.
        self.infinity_homography = J @ self.fundamental_matrix
        for a in (self.fundamental_matrix, self.epipole_homogeneous, self.infinity_homography):
            a.flags.writeable = False

    @classmethod
    def oriented(cls, F, points1, points2, *, image_size1, image_size2) -> "FundamentalGeometry":
        """``F`` with both orientations (forward and reverse) fixed by the majority of the matches.

        Parameters
        ----------
        F : (3, 3) array_like
            Rank-2 fundamental matrix, either sign.
        points1, points2 : (N, 2) array_like
            Matches that are mostly right (the inliers of the RANSAC that gave ``F``).
        """
        F = as_array(F, "F", (3, 3))
        x1, x2 = as_points(points1, "points1"), as_points(points2, "points2")
        if len(x1) != len(x2):
            raise ValueError(f"points1 and points2 must have the same length, got {len(x1)} and {len(x2)}")
        base = cls(F, image_size1=image_size1, image_size2=image_size2)
        Fn = base.fundamental_matrix
        sign, agreement = orientation_sign(Fn, base.epipole_homogeneous, x1, x2)
        e1 = _signed(_null_vectors(Fn)[0])
        rsign, _ = orientation_sign(Fn.T, e1, x2, x1)
        out = cls.__new__(cls)
        out._set(sign * Fn, base.image_size1, base.image_size2, rsign * sign, agreement)
        return out

    def inverse(self) -> "FundamentalGeometry":
        """The same pair with the views swapped: ``F^T``, with its own orientation."""
        if self.reverse_sign is None:
            raise ValueError("the reverse orientation of F is unknown; build the geometry with "
                             "FundamentalGeometry.oriented(F, points1, points2, ...) to use cross_check")
        inv = FundamentalGeometry.__new__(FundamentalGeometry)
        inv._set(self.reverse_sign * self.fundamental_matrix.T, self.image_size2, self.image_size1,
                 self.reverse_sign, self.agreement)
        return inv

    def segments(self, points1, depth_range=(0.0, np.inf), margin: float = 0.0) -> EpipolarSegments:
        """The oriented half-lines in image 2 of points of image 1 (as :meth:`TwoViewGeometry.segments`).

        ``start`` is the epipole's end. A depth range other than ``(0, inf)`` is refused: without
        a calibration, depth has no unit.
        """
        zmin, zmax = depth_range if len(depth_range) == 2 else (None, None)
        if np.any(np.asarray(zmin) != 0) or np.any(np.asarray(zmax) != np.inf):
            raise ValueError("a FundamentalGeometry has no metric depth: depth_range must be (0, inf)")
        # the segment code needs only infinity_homography, epipole_homogeneous and the sizes
        seg = TwoViewGeometry.segments(self, points1, margin=margin)
        if not self.at_infinity:
            return seg
        # rectified: the lines do not meet at a finite epipole, and the oriented constraint is all or
        # nothing on each of them; the whole line (F x1) clipped to the rectangle
        x1 = np.column_stack([as_points(points1, "points1"), np.ones(len(seg))])
        line = x1 @ self.fundamental_matrix.T
        nrm = np.hypot(line[:, 0], line[:, 1])
        with np.errstate(divide="ignore", invalid="ignore"):
            line = line / np.where(nrm > 0, nrm, np.nan)[:, None]
        rect = _rect(self.image_size2, margin)
        args = dict(line=line, infinity_point=seg.infinity_point, epipole=seg.epipole, margin=seg.margin,
                    _a=x1 @ self.infinity_homography.T, _b=np.array(self.epipole_homogeneous), _rect=rect)
        nan = np.full((len(seg), 2), np.nan)
        whole = EpipolarSegments(nan, nan.copy(), np.zeros(len(seg), dtype=bool), **args)
        start, end = np.array(whole.line_start), np.array(whole.line_end)
        return EpipolarSegments(start, end, np.all(np.isfinite(start), axis=1), **args)

    def __repr__(self) -> str:
        e = self.epipole
        return (f"FundamentalGeometry(epipole={np.round(e, 2).tolist()}, image_size1={self.image_size1}, "
                f"image_size2={self.image_size2})")
