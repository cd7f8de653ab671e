"""Pose refinement from matches: ``R`` and the direction of ``t``, with the distance to the *segment*.

The residual of a match ``(x1, x2)`` is the signed distance from ``x2`` to the
epipolar segment of ``x1``: the distance to the line, or, past an end (the
epipole or ``p_inf``), the distance to that end; its sign is the side of the
line. Unlike the Sampson or line distance, it is large for a pose that fits the
lines but puts the points behind a camera, so the refinement cannot fall into
such a twisted pose (measured on dinoSparseRing, a narrow lens where
rotation and translation trade off).

Model: ``R = expm([w]_x) R0`` (a left perturbation, ``w`` in camera 2's frame)
and ``t = |t0| normalise(u0 + B beta)`` with ``u0 = t0 / |t0|`` and ``B`` a
basis of its tangent plane (``|t|`` is kept: the depths of a depth range stay
in its unit). The cost is ``sum rho_c(r_i) / sigma^2 + p^T P^-1 p / 2`` with
``rho_c`` the Cauchy loss, ``sigma`` the robust scale of the residuals (at
least 0.1 px; re-estimated at each stage), ``p = (w, beta)`` and ``P`` the
prior covariance (isotropic, ``prior_deg``, or the geometry's pose
covariance): a maximum a posteriori estimate. ``c`` is annealed from
twice the median residual down to ``max(1 px, 2.5 sigma)`` (graduated
non-convexity), with two damped Gauss-Newton (Levenberg-Marquardt) steps per
stage and the analytic Jacobian of the line distance (past an end of its
segment a match's gradient is its line's; each step is accepted on the exact
cost).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._validation import as_points
from .geometry import TwoViewGeometry, _rect, _segment_distance, as_calibrated

__all__ = ["PoseRefinement", "refine_pose", "segment_residuals", "robust_sigma", "spread_subset", "rotation_angle_deg"]

#: Margin (pixels) of the clipping rectangle for residuals: the image border must not cut a segment here.
RESIDUAL_MARGIN = 1e3
#: Residual added for a match whose segment is empty (the ray is behind camera 2).
EMPTY_PENALTY = 1e3
#: The depth range of :func:`segment_residuals`: cheirality only, ``(zmin, zmax)`` as the segment kernel takes it.
_NO_BOUND = (np.zeros(1), np.full(1, np.inf))
#: Smallest noise scale (pixels) the residuals are weighed with against the prior (keypoints are not
#: located better than a tenth of a pixel).
MIN_SIGMA = 0.1


@dataclass(frozen=True, eq=False)
class PoseRefinement:
    """The result of :func:`refine_pose`.

    Attributes
    ----------
    geometry : TwoViewGeometry
        The refined pose (same ``K1, K2``, sizes and ``|t|``; no covariance).
    residuals : (N,) float64
        Signed distance (pixels) of each ``points2[i]`` to the segment of ``points1[i]`` under it.
    sigma : float
        Robust standard deviation of the matches' distances to their lines, pixels (NaN with too few).
    inliers : (N,) bool
        ``|residual| <= 3 sigma``.
    rotation_change_deg, translation_change_deg : float
        Angle of ``R R0^T`` and between the directions of ``t`` and ``t0``, degrees.
    iterations : int
        Gauss-Newton steps taken.
    covariance : (6, 6) float64
        Posterior covariance of the refined pose (Laplace approximation, in the
        convention of :meth:`TwoViewGeometry.with_covariance`): ``(J^T J / sigma^2
        + P^-1)^-1`` over the inliers, in the refined pose's frame; the variance of
        ``|t|``, which the matches do not see, is the prior's. With fewer than 8
        matches (or no ``sigma``), the prior.
    """

    geometry: TwoViewGeometry
    residuals: np.ndarray
    sigma: float
    inliers: np.ndarray
    rotation_change_deg: float
    translation_change_deg: float
    iterations: int
    covariance: np.ndarray


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _skew_rows(v: np.ndarray) -> np.ndarray:
    """``[v_i]_x`` for each row of ``v (N, 3)``: ``(N, 3, 3)``."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out


def _expm_so3(w: np.ndarray) -> np.ndarray:
    th = float(np.sqrt(w @ w))
    if th < 1e-15:
        return np.eye(3) + _skew(w)
    S = _skew(w / th)
    return np.eye(3) + np.sin(th) * S + (1 - np.cos(th)) * S @ S


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    """``J_l(w)``: ``expm([w + d]_x) = expm([J_l(w) d]_x) expm([w]_x)`` to first order in ``d``."""
    th = float(np.sqrt(w @ w))
    S = _skew(w)
    if th < 1e-8:
        return np.eye(3) + 0.5 * S
    return np.eye(3) + (1 - np.cos(th)) / th**2 * S + (th - np.sin(th)) / th**3 * S @ S


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle of a rotation matrix, degrees, in ``[0, 180]``; exact near 0, where ``arccos`` of the trace
    loses half the digits.

    >>> import cv2
    >>> round(rotation_angle_deg(cv2.Rodrigues(np.array([0.0, 1e-6, 0.0]))[0]) / float(np.degrees(1e-6)), 9)
    1.0
    """
    R = np.asarray(R, dtype=np.float64)
    sine = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return float(np.degrees(np.arctan2(sine, (np.trace(R) - 1.0) / 2.0)))


def _tangent_basis(u: np.ndarray) -> np.ndarray:
    a = np.eye(3)[np.argmin(np.abs(u))]
    b1 = np.cross(u, a)
    b1 /= np.linalg.norm(b1)
    return np.column_stack([b1, np.cross(u, b1)])


def _homog(x: np.ndarray) -> np.ndarray:
    return np.column_stack([x, np.ones(len(x))])


def segment_residuals(geometry: TwoViewGeometry, points1: np.ndarray, points2: np.ndarray) -> np.ndarray:
    """(N,) signed distance (pixels) of ``points2[i]`` to the segment of ``points1[i]`` (checked inputs).

    ``sign(line distance) * max(distance to the segment, |line distance|)``; where the segment
    is empty, ``|line distance| + EMPTY_PENALTY``; a large finite value where the line is undefined.
    """
    if isinstance(geometry, TwoViewGeometry):  # the segments' arrays without the public checks (checked inputs)
        x1 = np.ascontiguousarray(points1, dtype=np.float64)
        start, end, valid, line, _, _ = geometry._segment_arrays(x1, _NO_BOUND[0], _NO_BOUND[1],
                                                                 _rect(geometry.image_size2, RESIDUAL_MARGIN))
    else:
        seg = geometry.segments(points1, margin=RESIDUAL_MARGIN)
        start, end, valid, line = seg.start, seg.end, seg.valid, seg.line
    points2 = np.ascontiguousarray(points2, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        ld = (line[:, :2] * points2).sum(axis=1) + line[:, 2]
    sd = _segment_distance(points2, start, end, valid)
    sd = np.where(np.isfinite(sd), sd, np.abs(ld) + EMPTY_PENALTY)
    out = np.where(ld < 0, -1.0, 1.0) * np.maximum(sd, np.abs(ld))
    # t = 0 (no line): the distance to the single point p_inf; undefined line elsewhere: a large residual
    return np.where(np.isfinite(out), out, np.where(np.isfinite(sd), sd, EMPTY_PENALTY))


def robust_sigma(d: np.ndarray) -> float:
    """Robust standard deviation of residuals ``d``: ``1.4826 median |d|``, then the RMS of those within
    three of it (divided by 0.9866, the RMS of a unit Gaussian truncated at 3). NaN for fewer than 8."""
    d = np.abs(np.asarray(d, dtype=np.float64))
    d = d[np.isfinite(d)]
    if len(d) < 8:
        return float("nan")
    s = 1.4826 * float(np.median(d))
    inl = d <= 3 * s
    if inl.sum() >= 8 and s > 0:
        s = float(np.sqrt(np.mean(d[inl] ** 2)) / 0.9866)
    return s


def spread_subset(points: np.ndarray, n_max: int, cells: int = 8) -> np.ndarray:
    """Sorted indices of at most ``n_max`` of ``points (N, 2)``, spread over their bounding box: taken
    round-robin over a ``cells x cells`` grid (all of them when ``N <= n_max``)."""
    n = len(points)
    if n <= n_max:
        return np.arange(n)
    lo, hi = points.min(axis=0), points.max(axis=0) + 1e-9
    c = np.minimum(np.floor((points - lo) / (hi - lo) * cells).astype(np.intp), cells - 1)
    key = c[:, 0] * cells + c[:, 1]
    # each point's rank within its cell, in index order (a stable counting sort by cell)
    order = np.argsort(key.astype(np.uint16), kind="stable")  # (16-bit keys: numpy's radix sort)
    k_sorted = key[order]
    rank = np.empty(n, dtype=np.intp)
    rank[order] = np.arange(n) - np.searchsorted(k_sorted, k_sorted, side="left")
    # the n_max first in (rank, index) order: every point of rank < r, then those of rank r by index
    cum = np.cumsum(np.bincount(rank))
    r = int(np.searchsorted(cum, n_max, side="left"))
    below = rank < r
    extra = np.flatnonzero(rank == r)[:n_max - int(below.sum())]
    return np.sort(np.concatenate([np.flatnonzero(below), extra]))


class _Problem:
    """Residuals and Jacobians of the pose parameters ``p = (w, beta)`` for fixed matches."""

    def __init__(self, geometry: TwoViewGeometry, x1: np.ndarray, x2: np.ndarray):
        self.g0, self.x1, self.x2 = geometry, x1, x2
        self.R0, self.t0 = geometry.R, geometry.t
        self.norm_t = float(np.linalg.norm(self.t0))
        self.has_t = self.norm_t > 0
        self.u0 = self.t0 / self.norm_t if self.has_t else np.zeros(3)
        self.B = _tangent_basis(self.u0) if self.has_t else np.zeros((3, 0))
        self.n_par = 3 + self.B.shape[1]
        self.n1 = _homog(x1) @ np.linalg.inv(geometry.K1).T
        self.h2 = _homog(x2)

    def pose(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R = _expm_so3(p[:3]) @ self.R0
        if not self.has_t:
            return R, self.t0
        v = self.u0 + self.B @ p[3:]
        return R, self.norm_t * v / np.linalg.norm(v)

    def geometry(self, p: np.ndarray) -> TwoViewGeometry:
        R, t = self.pose(p)
        g = self.g0
        return TwoViewGeometry(g.K1, g.K2, R, t, image_size1=g.image_size1, image_size2=g.image_size2)

    def residuals(self, p: np.ndarray, rows=slice(None)) -> np.ndarray:
        return segment_residuals(self.geometry(p), self.x1[rows], self.x2[rows])

    def jacobian(self, p: np.ndarray, r: np.ndarray) -> np.ndarray:
        """``(N, n_par)``: the analytic Jacobian of the line distance (differences where it is undefined)."""
        if not self.has_t:  # no line (segments are points): all rows by differences
            return self._numeric(p, np.arange(len(r)))
        K2 = self.g0.K2
        R, t = self.pose(p)
        Rn = self.n1 @ R.T
        a = Rn @ K2.T
        b = K2 @ t
        line = np.cross(b, a)
        nrm = np.hypot(line[:, 0], line[:, 1])
        ok = nrm > 0
        nrm = np.where(ok, nrm, 1.0)
        d = np.einsum("ij,ij->i", line, self.h2) / nrm
        # d(line)/dw = [b]x dA/dw with dA/dw = -K2 [R n1]x ;  d(line)/dbeta = -[a]x K2 dt/dbeta
        dl_dw = -np.einsum("ij,njk->nik", _skew(b) @ K2, _skew_rows(Rn)) @ _left_jacobian(p[:3])
        v = self.u0 + self.B @ p[3:]
        nv = float(np.linalg.norm(v))
        dt_db = self.norm_t * (np.eye(3) - np.outer(v, v) / nv**2) @ self.B / nv
        dl_db = -np.einsum("nij,jk->nik", _skew_rows(a), K2 @ dt_db)
        dl = np.concatenate([dl_dw, dl_db], axis=2)  # (N, 3, n_par)
        g = self.h2 - d[:, None] * np.column_stack([line[:, :2] / nrm[:, None], np.zeros(len(d))])
        J = np.einsum("ni,nij->nj", g, dl) / nrm[:, None]
        J *= np.where(d < 0, -1.0, 1.0)[:, None] * np.where(r < 0, -1.0, 1.0)[:, None]  # the residual's sign
        # past an end the residual also grows along the line; its gradient is left to the line's (the cost,
        # which decides every step, is exact): finite differences there cost more than they gained
        if not ok.all():
            J[~ok] = self._numeric(p, np.flatnonzero(~ok))
        return J

    def _numeric(self, p, rows, h=1e-6):
        J = np.empty((len(rows), self.n_par))
        for k in range(self.n_par):
            e = np.zeros(self.n_par)
            e[k] = h
            J[:, k] = (self.residuals(p + e, rows) - self.residuals(p - e, rows)) / (2 * h)
        return J


def _prior_covariance(problem: _Problem, prior_deg: float, covariance) -> np.ndarray:
    """The ``6 x 6`` prior of the pose: the geometry's covariance, or isotropic ``prior_deg`` for the rotation
    and the direction of ``t`` (``|t|`` known)."""
    if covariance is not None:
        return np.asarray(covariance, dtype=np.float64)
    a = np.deg2rad(prior_deg) ** 2
    C = np.zeros((6, 6))
    C[:3, :3] = a * np.eye(3)
    if problem.has_t:
        C[3:, 3:] = problem.norm_t**2 * a * (np.eye(3) - np.outer(problem.u0, problem.u0))
    return C


def _prior_precision(problem: _Problem, prior: np.ndarray) -> np.ndarray:
    """``P^-1`` of the parameters ``p`` for the ``6 x 6`` prior of the pose."""
    n = problem.n_par
    G = np.zeros((n, 6))
    G[:3, :3] = np.eye(3)
    if problem.has_t:  # beta = B^T dt / |t| to first order
        G[3:, 3:] = problem.B.T / problem.norm_t
    P = G @ prior @ G.T
    return np.linalg.inv(P + np.eye(n) * 1e-12 + np.diag(np.diag(P)) * 1e-9)


def _posterior(pb: _Problem, p: np.ndarray, r: np.ndarray, inliers: np.ndarray, sigma: float, prec: np.ndarray,
               prior: np.ndarray) -> np.ndarray:
    """The ``6 x 6`` Laplace posterior at ``p``: ``(J^T J / sigma^2 + P^-1)^-1`` over the inliers, mapped to a
    left perturbation of the refined ``R`` and ``dt``; the variance of ``|t|`` (not refined) is the prior's."""
    if not np.isfinite(sigma) or sigma <= 0 or inliers.sum() < 8:
        return prior.copy()
    J = pb.jacobian(p, r)[inliers]
    cov_p = np.linalg.inv(J.T @ J / sigma**2 + prec)
    G = np.zeros((6, pb.n_par))
    G[:3, :3] = _left_jacobian(p[:3])
    out = np.zeros((6, 6))
    if pb.has_t:
        v = pb.u0 + pb.B @ p[3:]
        nv = float(np.linalg.norm(v))
        G[3:, 3:] = pb.norm_t * (np.eye(3) - np.outer(v, v) / nv**2) @ pb.B / nv
        u = v / nv
        out[3:, 3:] = float(pb.u0 @ prior[3:, 3:] @ pb.u0) * np.outer(u, u)
    else:  # t = 0 is not refined: its prior stays
        out[3:, 3:] = prior[3:, 3:]
    out += G @ cov_p @ G.T
    return 0.5 * (out + out.T)


def _cost(r, c, s2, p, prec):
    return 0.5 * c * c / s2 * float(np.sum(np.log1p((r / c) ** 2))) + 0.5 * float(p @ prec @ p)


def _scale2(r: np.ndarray) -> float:
    """The squared noise scale that weighs the residuals against the prior: the robust sigma of ``r``,
    at least :data:`MIN_SIGMA`."""
    s = robust_sigma(r)
    return max(s if np.isfinite(s) else 1.0, MIN_SIGMA) ** 2


def refine_pose(geometry, points1, points2, *, prior_deg: float = 10.0, use_covariance: bool = True,
                stages: int = 6, iterations: int = 2, min_scale: float = 1.0) -> PoseRefinement:
    """Refine ``R`` and the direction of ``t`` from putative matches, robustly.

    Parameters
    ----------
    geometry : TwoViewGeometry
        The starting pose, ``X2 = R @ X1 + t``; ``|t|`` is kept (with ``t = 0``,
        only ``R`` is refined).
    points1, points2 : (N, 2) array_like
        The matches' pixels (outliers are allowed: the loss is robust).
    prior_deg : float, optional
        Prior standard deviation of the correction, degrees, for the rotation and
        the direction of ``t`` (it keeps unobservable directions at the given pose).
    use_covariance : bool, optional
        When ``geometry`` has a :attr:`~TwoViewGeometry.covariance`, use it as the prior instead.
    stages, iterations : int, optional
        Annealing stages of the Cauchy scale, and Gauss-Newton steps per stage.
    min_scale : float, optional
        Smallest Cauchy scale, pixels.

    Returns
    -------
    PoseRefinement
        With fewer than 8 matches, the given pose, unchanged.

    Notes
    -----
    The residual is the distance to the segment, not the line (module
    docstring): it encodes cheirality. Costs a few milliseconds for 300
    matches; pass a spread subset (:func:`spread_subset`) of larger sets.

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv import TwoViewGeometry
    >>> K = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]
    >>> true = TwoViewGeometry(K, K, np.eye(3), [-1, 0, 0.2], image_size1=(640, 480), image_size2=(640, 480))
    >>> rng = np.random.default_rng(0)
    >>> x1 = rng.uniform([0, 0], [640, 480], (200, 2))
    >>> x2, _ = true.transfer(x1, rng.uniform(3, 10, 200))
    >>> R0 = TwoViewGeometry(K, K, [[1, -0.01, 0], [0.01, 1, 0], [0, 0, 1]], [-1, 0.05, 0.2],
    ...                      image_size1=(640, 480), image_size2=(640, 480)).R
    >>> off = TwoViewGeometry(K, K, R0, [-1, 0.05, 0.2], image_size1=(640, 480), image_size2=(640, 480))
    >>> ref = refine_pose(off, x1, x2)
    >>> bool(np.abs(ref.residuals).max() < 0.01), round(ref.rotation_change_deg, 1)
    (True, 0.6)
    """
    g = as_calibrated(geometry)
    x1, x2 = as_points(points1, "points1"), as_points(points2, "points2")
    if len(x1) != len(x2):
        raise ValueError(f"points1 and points2 must have the same length, got {len(x1)} and {len(x2)}")
    return refine(g, x1, x2, prior_deg=prior_deg, covariance=g.covariance if use_covariance else None,
                  stages=stages, iterations=iterations, min_scale=min_scale)


def refine(geometry: TwoViewGeometry, x1: np.ndarray, x2: np.ndarray, *, prior_deg: float = 10.0,
           covariance=None, stages: int = 6, iterations: int = 2, min_scale: float = 1.0) -> PoseRefinement:
    """:func:`refine_pose` on checked inputs."""
    pb = _Problem(geometry, x1, x2)
    p = np.zeros(pb.n_par)
    r = pb.residuals(p)
    prior = _prior_covariance(pb, prior_deg, covariance)
    prec = _prior_precision(pb, prior)
    if len(r) < 8:
        return _result(pb, p, r, 0, prec, prior)
    c = max(2.0 * float(np.median(np.abs(r))), min_scale)
    mu, steps = 1e-3, 0
    for stage in range(stages):
        s2 = _scale2(r)
        for _ in range(iterations):
            steps += 1
            w = 1.0 / (1.0 + (r / c) ** 2) / s2
            J = pb.jacobian(p, r)
            Jw = J * w[:, None]
            A = Jw.T @ J + prec
            grad = Jw.T @ r + prec @ p
            cost0 = _cost(r, c, s2, p, prec)
            for _ in range(8):
                step = -np.linalg.solve(A + mu * np.diag(np.diag(A)), grad)
                r_new = pb.residuals(p + step)
                if _cost(r_new, c, s2, p + step, prec) <= cost0:
                    p, r = p + step, r_new
                    mu = max(mu / 3, 1e-7)
                    break
                mu *= 4
            else:
                break
        c_next = max(min_scale, 2.5 * 1.4826 * float(np.median(np.abs(r))), c / 2)
        if c_next >= c and stage > 0:
            break
        c = c_next
    return _result(pb, p, r, steps, prec, prior)


def _result(pb: _Problem, p: np.ndarray, r: np.ndarray, steps: int, prec: np.ndarray,
            prior: np.ndarray) -> PoseRefinement:
    g = pb.geometry(p) if np.any(p) else pb.g0
    if g is pb.g0 and g.covariance is not None:
        g = g.with_covariance(None)
    seg = g.segments(pb.x1, margin=RESIDUAL_MARGIN)
    with np.errstate(invalid="ignore"):
        ld = (seg.line[:, :2] * pb.x2).sum(axis=1) + seg.line[:, 2]
    sigma = robust_sigma(ld)
    inliers = np.abs(r) <= 3 * sigma if np.isfinite(sigma) else np.zeros(len(r), dtype=bool)
    t_change = 0.0
    if pb.has_t:
        t_change = float(np.degrees(np.arccos(np.clip(pb.u0 @ g.t / pb.norm_t, -1.0, 1.0))))
    cov = _posterior(pb, p, r, inliers, sigma, prec, prior) if len(r) >= 8 else prior.copy()
    return PoseRefinement(g, r, sigma, inliers, rotation_angle_deg(g.R @ pb.R0.T), t_change, steps, cov)
