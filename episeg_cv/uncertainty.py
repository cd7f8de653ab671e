"""Pose uncertainty: the search band of each query from a pose covariance (first-order propagation).

Model
-----
The true pose is ``R = expm([dtheta]_x) R0``, ``t = t0 + dt`` with
``xi = (dtheta, dt) ~ N(0, C)``: ``C`` is ``6 x 6``, the rotation vector in
camera 2's frame (radians; a *left* perturbation) then the translation (unit
of ``t``). For a query ``x1`` with ``n1 = K1^-1 [x1; 1]``, the homogeneous
``p_inf`` ``a = K2 R0 n1`` and epipole ``b = K2 t0`` move by::

    da = -K2 [R0 n1]_x dtheta,      db = K2 dt.

The segment is ``w(s) = U + s (V - U)`` with ``U = zmin a + b`` and ``V = a``
(``zmax = inf``) or ``zmax a + b``, clipped to ``s`` in ``[lo, hi]``; its point
at ``s`` moves by ``dw(s) = alpha(s) da + beta(s) db`` with ``alpha = (1 - s)
zmin + s (1 or zmax)`` and ``beta = (1 - s) + s (0 or 1)``. With the unit line
``l`` (``l . [x; 1]`` is the signed distance) and its unit direction ``m``, the
displacement across the line is ``l^T dw / w3`` and along it
``(m, -m . x)^T dw / w3``: rows ``J`` with variances ``J C J^T``.

Across the line the displacement is an affine function of the position along
the segment (numerator and denominator are affine in ``s``, and so is the
pixel position, with the same denominator): at the fraction ``f`` of the way
from the start to the end it is ``(1 - f) d_start + f d_end``, whose variance
is ``(1 - f)^2 sigma_start^2 + 2 f (1 - f) c + f^2 sigma_end^2`` with ``c`` the
covariance of the two ends' displacements. The band's half-width there is
``w(f) = sqrt(kappa^2 var(f) + tol^2)``: ``w(f)^2 = (1 - f)^2 w_start^2 + 2 f (1 - f)
w_cross + f^2 w_end^2`` with ``w_k = sqrt((kappa sigma_k)^2 + tol^2)`` and
``w_cross = kappa^2 c + tol^2``. It is never wider than the *trapezoid* joining
the ends' half-widths (equal to it when the ends move together), and much
narrower in the middle when they do not: a pose known well from the depths of
the data but not at zero or infinite depth (a narrow lens, where rotation and
translation trade off). Past an end the band has an elliptical cap that
reaches ``e_k = sqrt((kappa sigma_along_k)^2 + tol^2)`` beyond an end that is
geometric (the epipole, ``p_inf`` or a depth bound) and ``w_k`` beyond one the
image border made. ``kappa = 2.576`` is the two-sided 99 % point of a
Gaussian. With ``C = 0`` it is the fixed ``tol`` stadium of the plain matcher.

Checked by Monte Carlo (200 poses drawn at errors of 0.5 deg and 2.5 deg, 400
points at depths 2-30, 60 random pairs): the true match was inside the band
for 98.0-99.95 % of the draws (99.0 % on average), and inside the band at
``kappa = 1`` for 63-68 % (a Gaussian: 68.3 %). The trapezoid joining the
ends' half-widths, used before, held 99.6-100 % and 69-84 %: safe, but wider
than the covariance says.

Matching with a covariance
--------------------------
A covariance describes what is known before the images are seen; the
confident matches then tell more. So a geometry with a covariance and a
numeric ``tol`` is matched in the bands of the *posterior*
(:func:`episeg_cv.matching.auto.posterior`): confident matches (mutual, ratio
0.6) in the bands of the prior, the pose refined on them with the covariance
as its prior (a maximum a posteriori estimate, :func:`episeg_cv.refine_pose`),
its posterior covariance (Laplace: ``(J^T J / sigma^2 + C^-1)^-1``), a second
strict pass and refinement in the bands of that posterior, then the bands of
the final posterior, with ``tol`` raised to ``kappa`` times the confident
matches' robust sigma when the residuals say the keypoints are noisier. The
posterior is narrow where the matches constrain the pose and stays wide where
they do not (the trade-off of rotation and translation of a narrow lens, at
depths the matches do not reach): with the exact band above, that width
reaches only the parts of the segments the data do not pin down. Filtering
given pairs (:func:`episeg_cv.filter_pairs`) tests them against the bands of
the covariance itself: it has no confident matches to learn from.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._validation import as_depth_range, as_nonnegative, as_points
from .geometry import as_calibrated

__all__ = ["EpipolarBands", "epipolar_bands", "pose_covariance", "KAPPA"]

#: Two-sided 99 % point of a unit Gaussian: the band's half-width in standard deviations.
KAPPA = 2.576


@dataclass(frozen=True, eq=False)
class EpipolarBands:
    """Per-query search bands around the nominal segments (:func:`epipolar_bands`).

    Attributes
    ----------
    start, end : (N, 2) float64
        Ends of the nominal segment (clipped to image 2 grown by ``margin``); NaN where empty.
    valid : (N,) bool
        False where the nominal segment is empty.
    w_start, w_end : (N,) float64
        Half-width of the band across the line at each end, pixels.
    e_start, e_end : (N,) float64
        How far the band reaches beyond each end along the line, pixels.
    sigma_start, sigma_end : (N,) float64
        Standard deviation of the displacement across the line at each end, pixels.
    w_cross : (N,) float64
        ``kappa^2 c + tol^2`` (pixels^2, ``c`` the covariance of the two ends' displacements), at most
        ``w_start w_end``: the half-width at the fraction ``f`` along the segment is
        ``sqrt((1 - f)^2 w_start^2 + 2 f (1 - f) w_cross + f^2 w_end^2)``. None: ``w_start w_end`` (the
        trapezoid joining the ends).
    """

    start: np.ndarray
    end: np.ndarray
    valid: np.ndarray
    w_start: np.ndarray
    w_end: np.ndarray
    e_start: np.ndarray
    e_end: np.ndarray
    sigma_start: np.ndarray
    sigma_end: np.ndarray
    w_cross: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.valid)

    @property
    def reach(self) -> np.ndarray:
        """(N,) the farthest the band reaches from its nominal segment, pixels (0 where empty)."""
        r = np.maximum(np.maximum(self.w_start, self.w_end), np.maximum(self.e_start, self.e_end))
        return np.where(self.valid, r, 0.0)

    @property
    def cross(self) -> np.ndarray:
        """(N,) :attr:`w_cross`, or ``w_start w_end`` where it is None (the trapezoid)."""
        trap = self.w_start * self.w_end
        return trap if self.w_cross is None else np.minimum(self.w_cross, trap)

    def contains(self, queries, points2) -> np.ndarray:
        """(K,) bool: is ``points2[k]`` inside the band of query ``queries[k]``?

        Along the segment, within the half-width ``w(f)`` of the line (module docstring), or inside
        the elliptical cap ``(across / w)^2 + (beyond / e)^2 <= 1`` past an end.
        """
        qi = np.asarray(queries, dtype=np.intp)
        y = np.asarray(points2, dtype=np.float64).reshape(-1, 2)
        P, Q = np.nan_to_num(self.start[qi]), np.nan_to_num(self.end[qi])
        D = Q - P
        L = np.hypot(D[:, 0], D[:, 1])
        safe = np.where(L > 0, L, 1.0)
        m = np.where((L > 0)[:, None], D / safe[:, None], np.array([1.0, 0.0]))
        rel = y - P
        u = rel[:, 0] * m[:, 0] + rel[:, 1] * m[:, 1]
        a = np.abs(rel[:, 1] * m[:, 0] - rel[:, 0] * m[:, 1])
        ws, we, wc = self.w_start[qi], self.w_end[qi], self.cross[qi]
        f = np.clip(u / safe, 0.0, 1.0)
        inside = (u >= 0) & (u <= L) & (a * a <= (1 - f) ** 2 * ws * ws + 2 * f * (1 - f) * wc + f * f * we * we)
        with np.errstate(divide="ignore", invalid="ignore"):
            cap_s = (u < 0) & ((a / ws) ** 2 + (u / self.e_start[qi]) ** 2 <= 1 + 1e-12)
            cap_e = (u > L) & ((a / we) ** 2 + ((u - L) / self.e_end[qi]) ** 2 <= 1 + 1e-12)
        return (inside | cap_s | cap_e) & self.valid[qi]


def pose_covariance(geometry, rotation_deg: float, translation_deg: float, *, scale: float = 0.0) -> np.ndarray:
    """The ``6 x 6`` covariance of isotropic pose errors of a given size.

    Parameters
    ----------
    geometry : TwoViewGeometry
        The pose the errors are about (for the direction and length of ``t``).
    rotation_deg : float >= 0
        RMS angle of the rotation error, degrees (about any axis): covariance
        ``a^2 / 3 I`` of the rotation vector.
    translation_deg : float >= 0
        RMS angle between the true and the given direction of ``t``, degrees:
        covariance ``|t|^2 a^2 / 2 (I - u u^T)``, ``u = t / |t|``.
    scale : float >= 0, optional
        RMS relative error of ``|t|``: adds ``(scale |t|)^2 u u^T``. Default 0
        (a known baseline; the length of ``t`` does not move the lines, only
        the ends of depth-bounded segments).

    Returns
    -------
    (6, 6) float64
        For :meth:`TwoViewGeometry.with_covariance` (rotation vector in camera 2's frame, then ``t``).

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv import TwoViewGeometry
    >>> K = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]
    >>> g = TwoViewGeometry(K, K, np.eye(3), [-2, 0, 0], image_size1=(640, 480), image_size2=(640, 480))
    >>> C = pose_covariance(g, 1.0, 5.0)
    >>> round(float(np.degrees(np.sqrt(np.trace(C[:3, :3])))), 6)   # RMS rotation angle
    1.0
    >>> np.round(np.diag(C)[3:] / np.deg2rad(5.0) ** 2, 6).tolist()  # |t|^2 / 2 across t, 0 along it
    [0.0, 2.0, 2.0]
    """
    g = as_calibrated(geometry)
    a_r = np.deg2rad(as_nonnegative(rotation_deg, "rotation_deg"))
    a_t = np.deg2rad(as_nonnegative(translation_deg, "translation_deg"))
    s = as_nonnegative(scale, "scale")
    C = np.zeros((6, 6))
    C[:3, :3] = a_r**2 / 3.0 * np.eye(3)
    nt = float(np.linalg.norm(g.t))
    if nt > 0:
        u = g.t / nt
        C[3:, 3:] = nt**2 * a_t**2 / 2.0 * (np.eye(3) - np.outer(u, u)) + (s * nt) ** 2 * np.outer(u, u)
    return C


def _params(U: np.ndarray, V: np.ndarray, P: np.ndarray) -> np.ndarray:
    """``s`` with ``U + s (V - U) ~ [P; 1]``, per row, solved in the better-conditioned coordinate."""
    D = V - U
    den1 = D[:, 0] - P[:, 0] * D[:, 2]
    den2 = D[:, 1] - P[:, 1] * D[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s1 = (P[:, 0] * U[:, 2] - U[:, 0]) / den1
        s2 = (P[:, 1] * U[:, 2] - U[:, 1]) / den2
    return np.clip(np.nan_to_num(np.where(np.abs(den1) >= np.abs(den2), s1, s2)), 0.0, 1.0)


def epipolar_bands(geometry, points1, *, tol: float = 2.0, kappa: float = KAPPA, depth_range=(0.0, np.inf),
                   margin: float | None = None, max_reach: float | None = None) -> EpipolarBands:
    """The search band of each query for the geometry's pose covariance (module docstring).

    Parameters
    ----------
    geometry : TwoViewGeometry
        With a :attr:`~episeg_cv.TwoViewGeometry.covariance` (none: every band is the ``tol`` stadium).
    points1 : (N, 2) array_like
        Query pixels of image 1.
    tol : float, optional
        Keypoint noise, pixels, added in quadrature. Default 2.
    kappa : float, optional
        Half-width in standard deviations. Default 2.576 (99 %).
    depth_range : (zmin, zmax), optional
        As for :meth:`~episeg_cv.TwoViewGeometry.segments`.
    margin : float, optional
        Clipping margin of the nominal segments; default ``max_reach``.
    max_reach : float, optional
        Cap of every half-width and extension, pixels; default a quarter of image 2's diagonal.

    Returns
    -------
    EpipolarBands

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv import TwoViewGeometry
    >>> K = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]
    >>> g = TwoViewGeometry(K, K, np.eye(3), [0, 0, 1], image_size1=(640, 480), image_size2=(640, 480))
    >>> C = np.zeros((6, 6)); C[3, 3] = C[4, 4] = 0.01 ** 2   # only t moves: 1 cm sideways
    >>> b = g.with_covariance(C).bands([[420.0, 240.0]], tol=0.0, kappa=1.0)
    >>> b.start.round(2).tolist(), b.end.round(2).tolist()   # from the epipole to p_inf (x1 itself)
    ([[320.0, 240.0]], [[420.0, 240.0]])
    >>> round(float(b.sigma_start[0]), 6), round(float(b.sigma_end[0]), 6)   # 5 px at the epipole, 0 at p_inf
    (5.0, 0.0)
    """
    g = as_calibrated(geometry)
    p1 = as_points(points1, "points1")
    tol = as_nonnegative(tol, "tol")
    kappa = as_nonnegative(kappa, "kappa")
    n = len(p1)
    cov = g.covariance if g.covariance is not None else np.zeros((6, 6))
    w2, h2 = g.image_size2
    max_reach = 0.25 * float(np.hypot(w2, h2)) if max_reach is None else as_nonnegative(max_reach, "max_reach")
    margin = max(max_reach, tol) if margin is None else as_nonnegative(margin, "margin")
    zmin, zmax = (np.broadcast_to(z, (n,)) for z in as_depth_range(depth_range, n))
    seg = g.segments(p1, (zmin, zmax), margin=margin)
    K2 = g.K2
    Rn1 = (np.column_stack([p1, np.ones(n)]) @ np.linalg.inv(g.K1).T) @ g.R.T
    a = Rn1 @ K2.T
    b = K2 @ g.t
    far = np.isfinite(zmax)
    zfar = np.where(far, zmax, 1.0)
    U = zmin[:, None] * a + b
    V = np.where(far[:, None], zfar[:, None] * a + b, a)
    line = np.nan_to_num(seg.line)
    m = np.column_stack([-line[:, 1], line[:, 0]])
    Ja = -np.einsum("ij,njk->nik", K2, _skew_rows(Rn1))  # d a / d dtheta, (N, 3, 3)
    K2n = np.broadcast_to(K2, (n, 3, 3))

    def end(P, s, geometric):
        alpha = (1 - s) * zmin + s * zfar
        beta = (1 - s) + s * far
        w3 = (U + s[:, None] * (V - U))[:, 2]
        x = np.nan_to_num(P)
        Jw = np.concatenate([alpha[:, None, None] * Ja, beta[:, None, None] * K2n], axis=2)  # (N, 3, 6)
        m_h = np.column_stack([m, -(m * x).sum(axis=1)])
        with np.errstate(divide="ignore", invalid="ignore"):
            Jd = np.einsum("ni,nij->nj", line, Jw) / w3[:, None]
            Jg = np.einsum("ni,nij->nj", m_h, Jw) / w3[:, None]
        sd = np.sqrt(np.maximum(np.einsum("ni,ij,nj->n", Jd, cov, Jd), 0.0))
        sg = np.sqrt(np.maximum(np.einsum("ni,ij,nj->n", Jg, cov, Jg), 0.0))
        sd = np.where(np.isfinite(sd), sd, np.inf)
        sg = np.where(geometric, np.where(np.isfinite(sg), sg, np.inf), 0.0)
        return sd, sg, np.nan_to_num(Jd)

    lo, hi = _params(U, V, np.nan_to_num(seg.start)), _params(U, V, np.nan_to_num(seg.end))
    sd_s, sg_s, J_s = end(seg.start, lo, lo <= 1e-9)
    sd_e, sg_e, J_e = end(seg.end, hi, hi >= 1 - 1e-9)
    cap = max(max_reach, tol)

    def q(v):
        return np.minimum(np.sqrt((kappa * v) ** 2 + tol**2), cap)

    ws, we = q(sd_s), q(sd_e)
    # the ends' covariance; where an end's width is capped (or not finite), the trapezoid
    with np.errstate(invalid="ignore", over="ignore"):
        wc = kappa**2 * np.einsum("ni,ij,nj->n", J_s, cov, J_e) + tol**2
    capped = ~((np.sqrt((kappa * sd_s) ** 2 + tol**2) < cap) & (np.sqrt((kappa * sd_e) ** 2 + tol**2) < cap))
    wc = np.where(capped | ~np.isfinite(wc), ws * we, np.minimum(wc, ws * we))
    # an end made by the image border does not move along the line: q(0) = tol there
    es, ee = q(sg_s), q(sg_e)
    out = EpipolarBands(seg.start, seg.end, seg.valid, ws, we, es, ee, sd_s, sd_e, wc)
    for f in ("w_start", "w_end", "e_start", "e_end", "sigma_start", "sigma_end", "w_cross"):
        getattr(out, f).flags.writeable = False
    return out


def _skew_rows(v: np.ndarray) -> np.ndarray:
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out

