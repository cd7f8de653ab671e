"""Ground truth: the true match of every keypoint, from depth maps or a disparity map.

Used for the synthetic renders (:mod:`episeg_cv.scenes`, exact depth) and for
real pairs with a disparity map (Middlebury Motorcycle). :class:`ImagePair`
holds two images with their geometry and what their ground truth needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._validation import as_image_size, as_nonnegative, as_points
from .geometry import TwoViewGeometry, as_geometry

__all__ = ["GroundTruth", "ground_truth_matches", "disparity_ground_truth", "ImagePair", "nearest_within"]


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """The true match in view 2 of every keypoint of view 1.

    Attributes
    ----------
    match : (N1,) intp
        Index into ``points2`` of the true match, ``-1`` where there is none
        (not visible in view 2, or no view-2 keypoint within ``max_px``).
    projected : (N1,) x 2 float64
        Where the keypoint's surface point projects in image 2, in pixels;
        NaN where its depth (or disparity) is unknown or it is behind camera 2.
    visible : (N1,) bool
        The surface point is in front of camera 2, inside image 2 and not
        occluded there.
    distance : (N1,) float64
        Pixel distance from ``projected`` to the true match; ``inf`` where
        there is none.
    points2 : (N2, 2) float64
        The view-2 keypoints searched.
    max_px : float
        The matching radius, pixels.

    Notes
    -----
    A returned match ``(i1, i2)`` is *correct* (:meth:`is_correct`) when
    keypoint ``i1`` is visible and ``points2[i2]`` lies within ``max_px`` of
    its projection. This is not ``match[i1] == i2``: detectors such as SIFT
    return several keypoints at one position (one per orientation), and any
    of them is a right answer. ``match`` is the nearest one.
    """

    match: np.ndarray
    projected: np.ndarray
    visible: np.ndarray
    distance: np.ndarray
    points2: np.ndarray
    max_px: float

    def __post_init__(self):
        for f in ("match", "projected", "visible", "distance", "points2"):
            getattr(self, f).flags.writeable = False

    def __len__(self) -> int:
        return self.match.shape[0]

    @property
    def matchable(self) -> np.ndarray:
        """(N1,) bool: the keypoint has a true match."""
        return self.match >= 0

    @property
    def num_matchable(self) -> int:
        """Number of view-1 keypoints with a true match (the denominator of recall)."""
        return int(np.count_nonzero(self.match >= 0))

    def is_correct(self, matches) -> np.ndarray:
        """Which of the ``(K, 2)`` index pairs ``(i1, i2)`` are correct.

        ``(i1, i2)`` is correct iff keypoint ``i1`` is visible in view 2 and
        ``points2[i2]`` lies within ``max_px`` of its projection (see Notes of
        :class:`GroundTruth`).

        Returns
        -------
        (K,) bool
        """
        m = np.asarray(matches)
        if m.size == 0:
            return np.zeros(0, dtype=bool)
        if m.ndim != 2 or m.shape[1] != 2 or not np.issubdtype(m.dtype, np.integer):
            raise ValueError(f"matches must be a (K, 2) integer array, got shape {m.shape} and dtype {m.dtype}")
        if m.min() < 0 or m[:, 0].max() >= len(self) or m[:, 1].max() >= len(self.points2):
            raise ValueError(f"matches must index the {len(self)} view-1 and {len(self.points2)} view-2 keypoints")
        with np.errstate(invalid="ignore"):
            return self.visible[m[:, 0]] & (self.error(m) <= self.max_px)

    def error(self, matches) -> np.ndarray:
        """(K,) pixel distance from ``points2[i2]`` to the projection of keypoint ``i1``; NaN if unknown."""
        m = np.asarray(matches, dtype=np.intp).reshape(-1, 2)
        return np.hypot(*(self.points2[m[:, 1]] - self.projected[m[:, 0]]).T)


def _as_map(a, name: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 2 or a.shape[0] < 1 or a.shape[1] < 1 or not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"{name} must be a floating (H, W) array, got shape {a.shape} and dtype {a.dtype}")
    return a.astype(np.float64, copy=False)


def _inside(p: np.ndarray, shape) -> np.ndarray:
    h, w = shape
    with np.errstate(invalid="ignore"):
        return (p[:, 0] >= -0.5) & (p[:, 0] <= w - 0.5) & (p[:, 1] >= -0.5) & (p[:, 1] <= h - 0.5)


def _sample_map(m: np.ndarray, p: np.ndarray, rtol: float | None, atol: float | None, inverse: bool) -> np.ndarray:
    """Values of ``m`` (depth or disparity) at points ``p``; NaN outside or unknown.

    Bilinear when the four neighbours are finite, positive and agree within
    ``rtol`` (relative) or ``atol`` (absolute), otherwise the nearest pixel.
    With ``inverse`` the interpolation is done on ``1 / m``: the inverse depth of a
    plane is affine in the pixel, so this is exact on a plane.
    """
    n = p.shape[0]
    out = np.full(n, np.nan)
    ok = _inside(p, m.shape) & np.all(np.isfinite(p), axis=1)
    if not ok.any():
        return out
    h, w = m.shape
    q = p[ok]
    ix = np.clip(np.floor(q[:, 0] + 0.5).astype(np.intp), 0, w - 1)
    iy = np.clip(np.floor(q[:, 1] + 0.5).astype(np.intp), 0, h - 1)
    nearest = m[iy, ix]
    x0 = np.clip(np.floor(q[:, 0]).astype(np.intp), 0, max(w - 2, 0))
    y0 = np.clip(np.floor(q[:, 1]).astype(np.intp), 0, max(h - 2, 0))
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx = np.clip(q[:, 0] - x0, 0.0, 1.0)
    fy = np.clip(q[:, 1] - y0, 0.0, 1.0)
    v = np.stack([m[y0, x0], m[y0, x1], m[y1, x0], m[y1, x1]])
    with np.errstate(invalid="ignore", divide="ignore"):
        good = np.all(np.isfinite(v) & (v > 0), axis=0)
        lo, hi = v.min(axis=0), v.max(axis=0)
        agree = (hi - lo <= rtol * lo) if rtol is not None else (hi - lo <= atol)
        f = 1.0 / v if inverse else v
        wts = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
        bil = (f * wts).sum(axis=0)
        if inverse:
            bil = 1.0 / bil
    val = np.where(good & agree, bil, nearest)
    val = np.where(np.isfinite(val) & (val > 0), val, np.nan)
    out[ok] = val
    return out


def nearest_within(query: np.ndarray, points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Index of the nearest ``points`` row to each ``query`` row if within ``radius``, else -1.

    Buckets ``points`` in a grid of ``radius``-sized cells and looks in the
    3 x 3 cells around each query: ``O((N + M) log M)``, no ``N x M`` array.
    Ties go to the lowest index. NaN queries get -1.
    """
    n = query.shape[0]
    best = np.full(n, -1, dtype=np.intp)
    dist = np.full(n, np.inf)
    valid = np.all(np.isfinite(query), axis=1)
    if n == 0 or points.shape[0] == 0 or not valid.any():
        return best, dist
    cell = max(float(radius), 1e-6)
    qv = query[valid]
    origin = np.minimum(points.min(axis=0), qv.min(axis=0)) - 2 * cell
    pc = np.floor((points - origin) / cell).astype(np.int64)
    qc = np.floor((qv - origin) / cell).astype(np.int64)
    stride = int(max(pc[:, 1].max(), qc[:, 1].max())) + 3
    keys = pc[:, 0] * stride + pc[:, 1]
    order = np.argsort(keys, kind="stable")
    sk = keys[order]
    vb = np.full(qv.shape[0], -1, dtype=np.intp)
    vd = np.full(qv.shape[0], np.inf)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            k = (qc[:, 0] + dx) * stride + (qc[:, 1] + dy)
            lo = np.searchsorted(sk, k, side="left")
            cnt = np.searchsorted(sk, k, side="right") - lo
            j = 0
            while True:
                act = np.flatnonzero(cnt > j)
                if act.size == 0:
                    break
                cand = order[lo[act] + j]
                d = np.hypot(*(qv[act] - points[cand]).T)
                better = (d < vd[act]) | ((d == vd[act]) & (cand < vb[act]))
                vd[act[better]] = d[better]
                vb[act[better]] = cand[better]
                j += 1
    far = vd > radius
    vb[far] = -1
    vd[far] = np.inf
    best[valid] = vb
    dist[valid] = vd
    return best, dist


def ground_truth_matches(points1, points2, depth1, depth2, geometry: TwoViewGeometry, max_px: float = 3.0,
                         depth_rtol: float = 0.01) -> GroundTruth:
    """The true match of every view-1 keypoint, from two depth maps and the true pose.

    For keypoint ``x1``:

    1. its depth ``z1`` is read from ``depth1``: bilinearly (on inverse
       depth, exact on a plane) when the four surrounding pixels are finite and
       agree within ``depth_rtol``, otherwise from the nearest pixel (so no
       depth is invented across an occluding edge);
    2. it is back-projected and projected into view 2 with the true geometry
       (:meth:`TwoViewGeometry.transfer`), giving ``x2`` and ``z2``;
    3. it is *visible* iff ``z2 > 0``, ``x2`` is inside image 2 and it is not
       occluded: ``depth2`` read at ``x2`` the same way agrees with ``z2``
       within ``depth_rtol`` (relative);
    4. its true match is the view-2 keypoint nearest to ``x2``, if one lies
       within ``max_px`` pixels (ties to the lowest index).

    Parameters
    ----------
    points1 : (N1, 2) array_like
        Keypoints of image 1, pixels (centres at integer coordinates).
    points2 : (N2, 2) array_like
        Keypoints of image 2.
    depth1 : (H1, W1) float array
        ``z`` in camera 1 per pixel, in the unit of ``geometry.t``; ``inf``,
        NaN or ``<= 0`` where unknown.
    depth2 : (H2, W2) float array
        The same for camera 2.
    geometry : TwoViewGeometry
        The *true* geometry (``X2 = R X1 + t``).
    max_px : float, optional
        Matching radius in pixels, default 3.
    depth_rtol : float, optional
        Relative depth agreement for the occlusion test and interpolation, default 0.01.

    Returns
    -------
    GroundTruth
        ``match`` (N1,) intp (``-1``: none), ``projected`` (N1, 2),
        ``visible`` (N1,) bool, ``distance`` (N1,).

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv import TwoViewGeometry
    >>> K = [[100, 0, 49.5], [0, 100, 39.5], [0, 0, 1]]
    >>> g = TwoViewGeometry(K, K, np.eye(3), [-0.5, 0, 0], image_size1=(100, 80), image_size2=(100, 80))
    >>> depth = np.full((80, 100), 5.0)                   # a fronto-parallel wall at z = 5
    >>> gt = ground_truth_matches([[50, 40], [5, 40]], [[40.5, 40], [70, 10]], depth, depth, g)
    >>> gt.match.tolist(), gt.projected.round(2).tolist()  # the wall moves by 100 * 0.5 / 5 = 10 px
    ([0, -1], [[40.0, 40.0], [-5.0, 40.0]])
    """
    geometry = as_geometry(geometry)
    p1 = as_points(points1, "points1")
    p2 = as_points(points2, "points2")
    d1 = _as_map(depth1, "depth1")
    d2 = _as_map(depth2, "depth2")
    for name, d, size in (("depth1", d1, geometry.image_size1), ("depth2", d2, geometry.image_size2)):
        if d.shape != (size[1], size[0]):
            raise ValueError(f"{name} must have shape {(size[1], size[0])} (the geometry's image size), got {d.shape}")
    max_px = as_nonnegative(max_px, "max_px")
    depth_rtol = as_nonnegative(depth_rtol, "depth_rtol")
    n = p1.shape[0]
    z1 = _sample_map(d1, p1, depth_rtol, None, inverse=True)
    known = np.isfinite(z1)
    proj = np.full((n, 2), np.nan)
    z2 = np.full(n, np.nan)
    if known.any():
        proj[known], z2[known] = geometry.transfer(p1[known], z1[known])
    with np.errstate(invalid="ignore"):
        front = z2 > 0
    proj[~front] = np.nan
    d2_at = _sample_map(d2, proj, depth_rtol, None, inverse=True)
    with np.errstate(invalid="ignore"):
        visible = front & _inside(proj, d2.shape) & (np.abs(d2_at - z2) <= depth_rtol * z2)
    match, dist = nearest_within(np.where(visible[:, None], proj, np.nan), p2, max_px)
    return GroundTruth(match, proj, visible, dist, p2, max_px)


def disparity_ground_truth(points1, points2, disparity, image_size2, max_px: float = 2.0) -> GroundTruth:
    """True matches of a rectified pair from the left view's disparity map.

    The disparity is indexed by the **left** (view-1) pixel:
    ``x2 = x1 - disparity[y1, x1]``, ``y2 = y1``. It is read bilinearly when the
    four neighbours are finite and within 1 px of each other, else from the
    nearest pixel. A keypoint is visible iff its disparity is finite and
    positive and ``x2`` is inside image 2 (occlusion is already encoded in
    the disparity map as inf/NaN). Its true match is the nearest view-2
    keypoint within ``max_px``.

    Parameters
    ----------
    points1, points2 : (N1, 2), (N2, 2) array_like
        Keypoints, pixels.
    disparity : (H1, W1) float array
        Left disparity in pixels; inf or NaN where unknown.
    image_size2 : (int, int)
        ``(width, height)`` of image 2.
    max_px : float, optional
        Matching radius, default 2.

    Returns
    -------
    GroundTruth

    Examples
    --------
    >>> import numpy as np
    >>> disp = np.full((10, 20), 4.0)
    >>> gt = disparity_ground_truth([[10, 5], [2, 5]], [[6.5, 5]], disp, (20, 10))
    >>> gt.match.tolist(), gt.visible.tolist()
    ([0, -1], [True, False])
    """
    p1 = as_points(points1, "points1")
    p2 = as_points(points2, "points2")
    disp = _as_map(disparity, "disparity")
    w2, h2 = as_image_size(image_size2, "image_size2")
    max_px = as_nonnegative(max_px, "max_px")
    d = _sample_map(disp, p1, None, 1.0, inverse=False)
    proj = np.column_stack([p1[:, 0] - d, p1[:, 1]])
    visible = np.isfinite(d) & _inside(proj, (h2, w2))
    proj[~np.isfinite(d)] = np.nan
    match, dist = nearest_within(np.where(visible[:, None], proj, np.nan), p2, max_px)
    return GroundTruth(match, proj, visible, dist, p2, max_px)


@dataclass(frozen=True, eq=False)
class ImagePair:
    """Two grey images with their calibration and ground truth.

    Made by :func:`make_pair` and by the loaders of :mod:`episeg_cv.datasets`.

    Attributes
    ----------
    name : str
    image1, image2 : (H1, W1), (H2, W2) uint8
        Grey images.
    geometry : TwoViewGeometry
        The geometry to hand to a matcher (perturbed for ``noisy_pose``).
    geometry_true : TwoViewGeometry
        The true geometry, ``X2 = R X1 + t``.
    depth1, depth2 : (H, W) float64 or None
        ``z`` per pixel in each camera (unit of ``t``), ``inf`` where unknown.
    disparity : (H1, W1) float or None
        Left disparity of a rectified pair, ``x2 = x1 - disparity[y1, x1]``.
    max_px : float
        Default matching radius of :meth:`ground_truth`.
    """

    name: str
    image1: np.ndarray
    image2: np.ndarray
    geometry: TwoViewGeometry
    geometry_true: TwoViewGeometry
    depth1: np.ndarray | None = None
    depth2: np.ndarray | None = None
    disparity: np.ndarray | None = None
    max_px: float = 3.0

    def __post_init__(self):
        for f in ("image1", "image2", "depth1", "depth2", "disparity"):
            a = getattr(self, f)
            if a is not None:
                a.flags.writeable = False

    @property
    def K1(self) -> np.ndarray:
        """(3, 3) true intrinsics of camera 1."""
        return self.geometry_true.K1

    @property
    def K2(self) -> np.ndarray:
        """(3, 3) true intrinsics of camera 2."""
        return self.geometry_true.K2

    @property
    def R(self) -> np.ndarray:
        """(3, 3) true relative rotation, ``X2 = R X1 + t``."""
        return self.geometry_true.R

    @property
    def t(self) -> np.ndarray:
        """(3,) true relative translation."""
        return self.geometry_true.t

    def ground_truth(self, points1, points2, max_px: float | None = None) -> GroundTruth:
        """True matches of keypoints ``points1`` among ``points2``.

        Uses :func:`ground_truth_matches` on the depth maps, or
        :func:`disparity_ground_truth` when the pair has a disparity map.
        ``max_px`` defaults to :attr:`max_px`.
        """
        r = self.max_px if max_px is None else max_px
        if self.disparity is not None:
            return disparity_ground_truth(points1, points2, self.disparity, self.geometry_true.image_size2, r)
        if self.depth1 is None or self.depth2 is None:
            raise ValueError(f"pair {self.name!r} has neither depth maps nor a disparity map")
        return ground_truth_matches(points1, points2, self.depth1, self.depth2, self.geometry_true, r)
