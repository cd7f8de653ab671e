"""No pose: estimate the geometry from the images' keypoints, then match on its segments (cv2 at this edge).

Two images and nothing else (:func:`estimate_geometry`):

1. a first pass as users run it today: ``cv2.BFMatcher`` nearest neighbours
   with Lowe's ratio (0.8);
2. ``cv2.findFundamentalMat(USAC_MAGSAC)`` on them; ``F`` is *oriented* by the
   majority of its inliers (:class:`~episeg_cv.FundamentalGeometry`): each
   query's candidates lie on the half-line from the epipole; the band is three
   robust standard deviations of the inliers' distances to their lines,
   clamped to ``[2, 8]`` pixels.

With the intrinsics ``K1, K2`` (and no pose), step 2 is
``cv2.findEssentialMat(USAC_MAGSAC)`` + ``cv2.recoverPose`` instead: a
calibrated :class:`~episeg_cv.TwoViewGeometry` with ``|t| = 1``, then
``tol="auto"`` (:func:`~episeg_cv.estimate_band`), which refines ``R`` and the
direction of ``t`` with the distance to the segment. The pose's covariance
from its confident matches (first order) is then the prior of the posterior
(:func:`~episeg_cv.matching.auto.posterior`): the geometry returned is the
posterior's pose *with* its covariance, and the matching runs in its bands
(:mod:`episeg_cv.uncertainty`; ``tol`` is their keypoint-noise term, 2 px or
``KAPPA`` robust sigmas), as tight as the estimate allows: wide only where
the matches leave the pose free (a narrow lens: rotation against
translation). The segments are the full ones (the epipole to ``p_inf``).
Measured against the fixed ``tol="auto"`` band (guided matches plus the
first pass): dinoSparseRing 3-4 70 correct at precision 0.933 -> 70 at 0.959,
11-12 24 at 0.615 -> 23 at 0.639, 15-0 271 at 0.948 -> 286 at 0.947, 6-7 109
at 0.924 -> 109 at 0.916, templeSparseRing 0-1 500 -> 501 at 0.980,
Motorcycle 1215 at 0.945 -> 1215 at 0.946, the synthetic pairs within 2
matches.

:func:`match_without_pose` does both steps and the guided matching, and
returns the guided matches together with the first-pass matches that lie
on their final segment, for the queries and keypoints the guided pass left
free (they passed the ratio test over all keypoints and the geometry).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ._validation import as_camera_matrix, as_image_size, as_nonnegative, as_positive_int, as_ratio
from .fundamental import FundamentalGeometry
from .geometry import EpipolarGeometry, TwoViewGeometry
from .matching import auto, banded, guided, repeats
from .matching.consistency import consistent_pairs
from .matching.config import AcceptRule, AutoTol, SearchConfig, resolve
from .matching.filtering import keep_mask
from .refinement import robust_sigma, segment_residuals

__all__ = ["EstimatedGeometry", "GeometryEstimationError", "estimate_geometry", "match_without_pose"]

#: Band of the fundamental-matrix path: three robust sigmas of the inliers, clamped to [2, 8] px.
F_TOL = AutoTol(tol_min=2.0, tol_max=8.0, refine=False)


class GeometryEstimationError(ValueError):
    """The images do not give enough matches to estimate the geometry (too few, or degenerate)."""


@dataclass(frozen=True, eq=False)
class EstimatedGeometry:
    """The result of :func:`estimate_geometry`.

    Attributes
    ----------
    geometry : TwoViewGeometry or FundamentalGeometry
        Calibrated (``K1, K2`` given: ``|t| = 1``, with the covariance of the estimate) or an oriented
        fundamental matrix.
    tol : float
        The band to match with, pixels (with a covariance: the keypoint-noise term of its bands).
    first_pass : (M, 2) intp
        The first-pass matches (nearest neighbour over all keypoints, ratio test).
    inliers : (K, 2) intp
        Those that the robust estimate of ``F`` (or ``E``) kept.
    method : {"fundamental", "essential"}
    estimate : BandEstimate or None
        The ``tol="auto"`` estimate of the essential path.
    """

    geometry: EpipolarGeometry
    tol: float
    first_pass: np.ndarray
    inliers: np.ndarray
    method: str
    estimate: auto.BandEstimate | None = None


def _first_pass(dist, ratio: float) -> np.ndarray:
    """``cv2.BFMatcher.knnMatch(k=2)`` + Lowe's ratio: ``(M, 2)`` pairs."""
    norms = {"l1": cv2.NORM_L1, "l2": cv2.NORM_L2, "l2sqr": cv2.NORM_L2, "hamming": cv2.NORM_HAMMING}
    d1, d2 = dist.raw1, dist.raw2
    if d1.dtype == np.float64:
        d1, d2 = d1.astype(np.float32), d2.astype(np.float32)
    if len(d1) == 0 or len(d2) < 2:
        return np.zeros((0, 2), dtype=np.intp)
    knn = cv2.BFMatcher(norms[dist.norm]).knnMatch(d1, d2, k=2)
    out = [(m[0].queryIdx, m[0].trainIdx) for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    return np.array(out, dtype=np.intp).reshape(-1, 2)


def _usac(x1, x2, threshold, confidence, max_iters, rng, essential=False, focal=1.0):
    cv2.setRNGSeed(int(rng))
    if essential:
        E, mask = cv2.findEssentialMat(x1, x2, np.eye(3), cv2.USAC_MAGSAC, confidence, threshold / focal,
                                       maxIters=max_iters)
    else:
        E, mask = cv2.findFundamentalMat(x1, x2, cv2.USAC_MAGSAC, threshold, confidence, max_iters)
    if E is None or E.shape != (3, 3) or mask is None:
        return None, None
    return E, mask.ravel().astype(bool)


def estimate(inputs: guided.MatchInputs, image_size1, image_size2, K1=None, K2=None, *, ratio=0.8, threshold=1.0,
             confidence=0.999, max_iters=10000, rng=0, search: SearchConfig | None = None) -> EstimatedGeometry:
    """:func:`estimate_geometry` on checked inputs."""
    p1, p2 = inputs.points1, inputs.points2
    first = _first_pass(inputs.distances, ratio)
    need = 5 if K1 is not None else 8
    if len(first) < need:
        raise GeometryEstimationError(f"too few matches to estimate the geometry: {len(first)} passed the first "
                                      f"pass (nearest neighbour, ratio {ratio}); at least {need} are needed")
    x1, x2 = p1[first[:, 0]], p2[first[:, 1]]
    if K1 is None:
        F, inl = _usac(x1, x2, threshold, confidence, max_iters, rng)
        if F is None or inl.sum() < 8:
            raise GeometryEstimationError(f"cv2.findFundamentalMat found no fundamental matrix from {len(first)} "
                                          "first-pass matches (too few, or degenerate: a plane or no motion)")
        geom = FundamentalGeometry.oriented(F, x1[inl], x2[inl], image_size1=image_size1, image_size2=image_size2)
        inliers = first[inl]
        sigma = robust_sigma(segment_residuals(geom, x1[inl], x2[inl]))
        tol = float(np.clip(F_TOL.k * sigma, F_TOL.tol_min, F_TOL.tol_max)) if np.isfinite(sigma) else 2 * F_TOL.tol_min
        return EstimatedGeometry(geom, tol, first, inliers, "fundamental")
    n1 = np.column_stack([x1, np.ones(len(x1))]) @ np.linalg.inv(K1).T
    n2 = np.column_stack([x2, np.ones(len(x2))]) @ np.linalg.inv(K2).T
    focal = 0.25 * (K1[0, 0] + K1[1, 1] + K2[0, 0] + K2[1, 1])
    E, inl = _usac(n1[:, :2], n2[:, :2], threshold, confidence, max_iters, rng, essential=True, focal=focal)
    if E is None or inl.sum() < 5:
        raise GeometryEstimationError(f"cv2.findEssentialMat found no essential matrix from {len(first)} "
                                      "first-pass matches (too few, or degenerate)")
    # distanceThresh: the default overload counts a point farther than 50 |t| as not in front (a short baseline,
    # a narrow lens: on dinoSparseRing 15-0 all 271 inliers, the same R and t); the decomposition chosen is the same
    _, R, t, mask, _ = cv2.recoverPose(E[:3], n1[:, :2], n2[:, :2], np.eye(3), distanceThresh=1e9,
                                       mask=inl.astype(np.uint8)[:, None] * 255)
    inl = mask.ravel() > 0
    U, _, Vt = np.linalg.svd(R)
    geom = TwoViewGeometry(K1, K2, U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt, t.ravel(),
                           image_size1=image_size1, image_size2=image_size2)
    search = (search or SearchConfig()).replace(depth_range=(0.0, np.inf))
    opts = AutoTol()
    est = auto.estimate(inputs, geom, search, AcceptRule(), opts, rng)
    if est.fallback:
        return EstimatedGeometry(est.geometry, est.tol, first, first[inl], "essential", est)
    # the covariance of that pose from the confident matches (first order) as the prior of the posterior's bands
    cov = auto.refine_on(est.geometry, p1, p2, est.confident, opts).covariance
    post, tol = auto.posterior(inputs, est.geometry.with_covariance(cov), search.replace(tol=opts.tol_min),
                               AcceptRule(), opts, rng)
    return EstimatedGeometry(post, tol, first, first[inl], "essential", est)


def estimate_geometry(descriptors1, descriptors2, points1, points2, *, image_size1, image_size2, K1=None, K2=None,
                      norm="l2", ratio: float = 0.8, threshold: float = 1.0, confidence: float = 0.999,
                      max_iters: int = 10000, rng: int = 0) -> EstimatedGeometry:
    """Estimate the geometry of two views from their keypoints (module docstring).

    Parameters
    ----------
    descriptors1, descriptors2, points1, points2, norm
        As in :func:`~episeg_cv.match_descriptors`.
    image_size1, image_size2 : (int, int)
        ``(width, height)`` of the images.
    K1, K2 : (3, 3) array_like, optional
        Intrinsics (both or neither): with them, the essential path and a calibrated pose.
    ratio : float, optional
        Lowe's ratio of the first pass. Default 0.8.
    threshold : float, optional
        RANSAC inlier threshold, pixels. Default 1.
    confidence, max_iters : optional
        Of ``cv2.findFundamentalMat`` / ``cv2.findEssentialMat``.
    rng : int, optional
        Seed of OpenCV's random generator (``cv2.setRNGSeed``).

    Returns
    -------
    EstimatedGeometry

    Raises
    ------
    GeometryEstimationError
        Too few first-pass matches (fewer than 8 for ``F``, 5 for ``E``) or no estimate.
    ValueError, TypeError
        Bad input.

    Examples
    --------
    >>> import cv2, numpy as np
    >>> from episeg_cv import scenes
    >>> pair = scenes.make_pair("lateral", image_size=(320, 240))
    >>> sift = cv2.SIFT_create(nfeatures=1500)
    >>> (k1, d1), (k2, d2) = (sift.detectAndCompute(im, None) for im in (pair.image1, pair.image2))
    >>> p1, p2 = (np.array([k.pt for k in kk]) for kk in (k1, k2))
    >>> est = estimate_geometry(d1, d2, p1, p2, image_size1=(320, 240), image_size2=(320, 240))
    >>> est.method, type(est.geometry).__name__, 2.0 <= est.tol <= 8.0
    ('fundamental', 'FundamentalGeometry', True)
    """
    inputs = guided.MatchInputs.check(descriptors1, descriptors2, points1, points2, norm)
    size1, size2 = as_image_size(image_size1, "image_size1"), as_image_size(image_size2, "image_size2")
    if (K1 is None) != (K2 is None):
        raise ValueError("K1 and K2 must be given together (both for the essential path, neither for F)")
    if K1 is not None:
        K1, K2 = as_camera_matrix(K1, "K1"), as_camera_matrix(K2, "K2")
    return estimate(inputs, size1, size2, K1, K2, ratio=as_ratio(ratio, "ratio"),
                    threshold=_positive(threshold, "threshold"), confidence=_confidence(confidence),
                    max_iters=as_positive_int(max_iters, "max_iters"), rng=int(rng))


def _positive(x, name):
    v = as_nonnegative(x, name)
    if v <= 0:
        raise ValueError(f"{name} must be > 0, got {x!r}")
    return v


def _confidence(x):
    v = as_nonnegative(x, "confidence")
    if not 0 < v < 1:
        raise ValueError(f"confidence must be in (0, 1), got {x!r}")
    return v


def union(inputs: guided.MatchInputs, pairs: np.ndarray, est: EstimatedGeometry,
          search: SearchConfig) -> tuple[np.ndarray, np.ndarray]:
    """The guided ``pairs`` plus the first-pass matches on the final segments whose query and keypoint
    the guided pass left free: ``(pairs, distances)``, sorted by query."""
    extra = est.first_pass
    if len(extra):
        extra = extra[keep_mask(extra, inputs.points1, inputs.points2, est.geometry, search.replace(tol=est.tol))]
        free = ~np.isin(extra[:, 0], pairs[:, 0]) & ~np.isin(extra[:, 1], pairs[:, 1])
        extra = extra[free]
        # one match per keypoint of image 2 (the first pass need not be mutual): the nearest
        d = inputs.distances.exact(extra[:, 0], extra[:, 1])
        o = np.lexsort((extra[:, 0], d))
        _, first = np.unique(extra[o, 1], return_index=True)
        extra = extra[o[first]]
    out = np.concatenate([pairs, extra]).astype(np.intp) if len(extra) else pairs
    out = out[np.argsort(out[:, 0], kind="stable")]
    return out, inputs.distances.exact(out[:, 0], out[:, 1])


def match_without_pose(descriptors1, descriptors2, points1, points2, *, image_size1, image_size2, K1=None, K2=None,
                       norm="l2", search: SearchConfig | None = None, rule: AcceptRule | None = None, rng: int = 0,
                       first_ratio: float = 0.8, threshold: float = 1.0, reject_repeats: bool = False,
                       consistency: bool = False, **options) -> tuple[np.ndarray, np.ndarray, EstimatedGeometry]:
    """Match two views with no pose: estimate the geometry, match on its segments, add the first pass.

    Parameters
    ----------
    descriptors1, descriptors2, points1, points2, image_size1, image_size2, K1, K2, norm
        As in :func:`estimate_geometry`.
    search, rule, **options
        As in :func:`~episeg_cv.match_descriptors`; ``search.tol`` is replaced by
        the estimated band, and a depth range needs ``K1, K2`` (it is then in
        units of the recovered ``|t| = 1``).
    first_ratio, threshold : float, optional
        Ratio of the first pass and RANSAC threshold (pixels) of :func:`estimate_geometry`.
    reject_repeats : bool, optional
        Leave out the matches whose keypoints have a twin in their own image inside the same band
        (:mod:`episeg_cv.matching.repeats`: ``d(match) >= first_ratio * d(twin)``, Lowe's test against
        the twin). For repeated structure; default False (it also drops a few correct matches of
        ordinary pairs: numbers in ``benchmarks/results/compare.md``).
    consistency : bool, optional
        Leave out the matches that disagree with the affine map of their nearest first-pass matches
        (:func:`~episeg_cv.matching.consistency.consistent_pairs`, the anchors being the matches that passed
        the first pass's ratio test over all keypoints). For repeated structure, where it removes most of the
        wrong matches that the twin test leaves; default False (it costs 1-5 % of the correct matches of
        ordinary pairs, more where the anchors are sparse: numbers in ``benchmarks/results/compare.md``).

    Returns
    -------
    pairs : (K, 2) intp
        Guided matches (the rule) and the first-pass matches on their final segment, sorted by query.
    distances : (K,) float32
    estimated : EstimatedGeometry
    """
    search, rule = resolve(search, rule, options)
    if search.constraint == "none":
        raise ValueError("match_without_pose needs constraint 'segment' or 'line'")
    inputs = guided.MatchInputs.check(descriptors1, descriptors2, points1, points2, norm)
    size1, size2 = as_image_size(image_size1, "image_size1"), as_image_size(image_size2, "image_size2")
    if (K1 is None) != (K2 is None):
        raise ValueError("K1 and K2 must be given together (both for the essential path, neither for F)")
    if K1 is None and search.bounded:
        raise ValueError("a depth range needs K1 and K2 (without a calibration, depth has no unit)")
    for name, flag in (("reject_repeats", reject_repeats), ("consistency", consistency)):
        if not isinstance(flag, (bool, np.bool_)):
            raise TypeError(f"{name} must be True or False, got {flag!r}")
    if K1 is not None:
        K1, K2 = as_camera_matrix(K1, "K1"), as_camera_matrix(K2, "K2")
    first_ratio = as_ratio(first_ratio, "first_ratio")
    est = estimate(inputs, size1, size2, K1, K2, ratio=first_ratio, threshold=_positive(threshold, "threshold"),
                   rng=rng, search=search)
    s = search.replace(tol=est.tol)
    if getattr(est.geometry, "covariance", None) is not None:  # the essential path: the bands of the estimate's posterior
        pairs, _ = banded.match(inputs, est.geometry, banded.bands_for(est.geometry, inputs.points1, s), s, rule, rng)
    else:
        pairs, _ = guided.match(inputs, est.geometry, s, rule, rng)
    out, dist = union(inputs, pairs, est, s)
    if reject_repeats:  # Lowe's test against the twin: the first pass's ratio
        keep = ~repeats.ambiguous(inputs, out, est.geometry, s, first_ratio)
        out, dist = out[keep], dist[keep]
    if consistency:  # anchors: the matches that Lowe's test over all keypoints found too
        n2 = len(inputs.points2)
        anchors = np.isin(out[:, 0] * n2 + out[:, 1], est.first_pass[:, 0] * n2 + est.first_pass[:, 1])
        keep = consistent_pairs(inputs.points1, inputs.points2, out, anchors=anchors, tol=est.tol)
        out, dist = out[keep], dist[keep]
    return out, dist, est
