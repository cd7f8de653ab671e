"""``tol="auto"``: the band, and a correction of the pose when it matters, found from the data.

Poses from odometry, GPS/IMU or a drifted calibration are off by fractions of a
degree, which moves the true matches several pixels off their segments; a
fixed ``tol`` then either loses them or lets in more wrong candidates. The
estimate (:func:`estimate_band`), with :class:`~.config.AutoTol`'s constants:

1. **Confident matches**: guided matching in a wide band (``band``, 64 px
   at 640 x 480) with a strict rule (mutual, ratio < 0.6); and, when that finds
   too little that agrees with a pose (pose errors larger than the band),
   plain mutual nearest neighbours over all keypoints with the same rule.
2. **Refinement** of ``R`` and the direction of ``t`` on them, robustly, with
   the distance to the *segment* (:func:`episeg_cv.refine_pose`), on at most
   300 of them spread over image 1.
3. **Keep the given pose unless the correction matters**: it is kept when the
   refined pose does not explain the confident matches significantly better
   (chi-square, 5 degrees of freedom, 99 %) or moves their lines by less than
   ``tol_min / 2`` at 95 % of them. Otherwise a second strict pass around the
   refined pose gathers more confident matches and the pose is refined again.
4. **The band**: ``k = 3`` robust standard deviations of the confident
   matches' distances to their lines under the chosen pose, clamped to
   ``[tol_min, tol_max]`` = ``[2, band]``.
5. **When the pose was corrected**: the matches in that band under the usual
   rule (mutual, ratio 0.68, the strict rule's padding) and the last refinement on
   them, from the given pose as in step 2; the band is ``k`` robust sigmas of
   the confident matches' distances under that pose. With few confident matches
   (a narrow lens: dinoSparseRing, ``f`` = 3310 px, about 80) their refinement
   can land off (one draw at (1 deg, 5 deg): 8 deg off, a 7.4 px band); the
   band's matches are more. Measured over pose errors up to (1 deg, 5 deg),
   3 draws each, the lowest precision at the default rule: dinoSparseRing 15-0
   0.962 -> 0.979, 6-7 0.824 -> 0.890, templeSparseRing 0-1 0.977 -> 0.985,
   unchanged on the synthetic pairs, dinoSparseRing 8-9 and 3-4; Motorcycle
   0.9497 -> 0.9490 (one match).

On exact poses the given pose is kept and the band is 2 px: the result is
the fixed default's. A geometry with no calibrated pose (an oriented
fundamental matrix) gets step 4 only; a geometry with a pose covariance uses
it as the prior of step 2 (and matches without it: the estimate replaces it).

With a covariance and a numeric ``tol``, :func:`plan` matches in the bands of
the posterior (:func:`posterior`, :mod:`episeg_cv.uncertainty`): steps 1 and
2 with the bands of the covariance as the first pass and the covariance as
the prior, no step 3 (the prior already weighs the given pose), and the
posterior covariance instead of step 4.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .._validation import as_positive_int
from ..geometry import EpipolarGeometry, TwoViewGeometry, as_geometry
from ..refinement import PoseRefinement, refine, robust_sigma, segment_residuals, spread_subset
from ..uncertainty import KAPPA, EpipolarBands
from . import banded, guided
from .config import AcceptRule, AutoTol, SearchConfig, resolve
from .distances import Distances
from .guided import MatchInputs

__all__ = ["BandEstimate", "estimate_band", "estimate", "estimate_from_pairs", "unguided_mutual", "Plan", "plan",
           "plan_pairs", "posterior", "nearest", "match", "knn", "radius"]


@dataclass(frozen=True, eq=False)
class BandEstimate:
    """What ``tol="auto"`` found (:func:`estimate_band`).

    Attributes
    ----------
    tol : float
        The band, pixels.
    sigma : float
        Robust standard deviation of the confident matches' distances to their lines, pixels.
    geometry : EpipolarGeometry
        The geometry to match with: the refined pose, or the given one (without its covariance).
    pose_kept : bool
        True when the given pose is used as it is.
    confident : (K, 2) intp
        The confident matches the estimate rests on.
    rotation_change_deg, translation_change_deg : float
        The correction of the rotation and of the direction of ``t`` (0 when kept).
    unguided : bool
        Whether the plain nearest-neighbour pass ran.
    fallback : bool
        True when there were too few confident matches: the given pose with ``2 tol_min``.
    """

    tol: float
    sigma: float
    geometry: EpipolarGeometry
    pose_kept: bool
    confident: np.ndarray
    rotation_change_deg: float = 0.0
    translation_change_deg: float = 0.0
    unguided: bool = False
    fallback: bool = False


def unguided_mutual(dist: Distances, ratio: float, chunk: int = 1024) -> np.ndarray:
    """``(K, 2)`` mutual nearest neighbours over all keypoints with ``d1 < ratio * d2``, by query.

    Dense, in row chunks: L2 by one matrix product per chunk (BLAS), Hamming by a
    product of the unpacked bits, L1 by differences. Ties: the smaller index.
    """
    n1, n2 = len(dist.raw1), len(dist.raw2)
    if n1 == 0 or n2 < 2:
        return np.zeros((0, 2), dtype=np.intp)
    if dist.norm == "hamming":
        A = np.unpackbits(dist.raw1, axis=1).astype(np.float32)
        B = np.unpackbits(dist.raw2, axis=1).astype(np.float32)
    else:
        A, B = dist.a, dist.b
    bt = np.ascontiguousarray(B.T)
    bb = np.einsum("ij,ij->i", B, B)
    best_j = np.empty(n1, dtype=np.intp)
    s1 = np.empty(n1, dtype=np.float32)
    s2 = np.empty(n1, dtype=np.float32)
    col_s = np.full(n2, np.inf, dtype=np.float32)
    col_i = np.full(n2, -1, dtype=np.intp)
    step = chunk if dist.norm != "l1" else 16
    for a in range(0, n1, step):
        z = min(a + step, n1)
        r = A[a:z]
        if dist.norm == "l1":
            p = np.abs(r[:, None, :] - B[None, :, :]).sum(axis=2, dtype=np.float32)
        else:  # |a|^2 + |b|^2 - 2 a.b (squared L2, or the Hamming count of 0/1 vectors)
            p = r @ bt
            p *= -2.0
            p += np.einsum("ij,ij->i", r, r)[:, None]
            p += bb
            np.maximum(p, 0.0, out=p)
        j = np.argmin(p, axis=1)
        best_j[a:z] = j
        two = np.partition(p, 1, axis=1)
        s1[a:z], s2[a:z] = two[:, 0], two[:, 1]
        cm, ca = p.min(axis=0), np.argmin(p, axis=0) + a
        better = cm < col_s
        col_s[better], col_i[better] = cm[better], ca[better]
    to_d = np.sqrt if dist.norm == "l2" else (lambda v: v)
    d1, d2 = to_d(s1.astype(np.float64)), to_d(s2.astype(np.float64))
    i = np.arange(n1)
    keep = (col_i[best_j] == i) & (d1 < ratio * d2)
    return np.column_stack([i[keep], best_j[keep]]).astype(np.intp)


def _union(*parts) -> np.ndarray:
    parts = [p for p in parts if len(p)]
    return np.unique(np.concatenate(parts), axis=0).astype(np.intp) if parts else np.zeros((0, 2), dtype=np.intp)


def strict_rule(options: AutoTol, rule: AcceptRule) -> AcceptRule:
    # the usual padding even when the call's rule has none (knnMatch with crossCheck): confidence needs it
    return AcceptRule(ratio=options.strict_ratio, mutual=True, pad=max(rule.pad, AcceptRule().pad))


def clip_tol(sigma: float, options: AutoTol, image_size2) -> float:
    lo, hi = options.bounds(image_size2)
    return float(np.clip(options.k * sigma, lo, hi)) if np.isfinite(sigma) else float(np.clip(2 * lo, lo, hi))


def refine_on(geometry, p1, p2, pairs, options) -> PoseRefinement:
    """Step 2: :func:`~episeg_cv.refinement.refine` on at most ``options.max_refine_matches`` of ``pairs`` spread
    over image 1, with the geometry's covariance (or ``options.prior_deg``) as the prior."""
    x1, x2 = p1[pairs[:, 0]], p2[pairs[:, 1]]
    sub = spread_subset(x1, options.max_refine_matches)
    return refine(geometry, x1[sub], x2[sub], prior_deg=options.prior_deg, covariance=geometry.covariance)


def _keep_given(given, ref: PoseRefinement, x1, x2, options) -> tuple[bool, float]:
    """Whether to keep the given pose, and the scale under the pose chosen (step 3 of the module docstring)."""
    sigma = ref.sigma if np.isfinite(ref.sigma) else robust_sigma(segment_residuals(given, x1, x2))
    s = max(sigma, 0.1) if np.isfinite(sigma) else 1.0
    c = 3.0 * s
    r_ref = segment_residuals(ref.geometry, x1, x2)
    r_giv = segment_residuals(given, x1, x2)
    stat = (np.minimum(r_giv**2, c * c).sum() - np.minimum(r_ref**2, c * c).sum()) / s**2
    inl = np.abs(r_ref) <= c
    effect = float(np.percentile(np.abs(r_giv - r_ref)[inl], 95)) if inl.sum() >= 8 else np.inf
    keep_px = options.keep_px if options.keep_px is not None else 0.5 * options.tol_min
    if stat < options.keep_test or effect < keep_px:
        inl_g = np.abs(r_giv) <= c
        if inl_g.sum() >= 8:
            sigma = float(np.sqrt(np.mean(r_giv[inl_g] ** 2)) / 0.9866)
        return True, sigma
    return False, sigma


def _plain(geometry):
    return geometry.with_covariance(None) if getattr(geometry, "covariance", None) is not None else geometry


def estimate_from_pairs(pairs: np.ndarray, p1: np.ndarray, p2: np.ndarray, geometry: EpipolarGeometry,
                        options: AutoTol, unguided: bool = False) -> BandEstimate:
    """Steps 2-4 (module docstring) on given confident matches (checked inputs)."""
    size2 = geometry.image_size2
    if len(pairs) < options.min_matches:
        return BandEstimate(clip_tol(np.nan, options, size2), float("nan"), _plain(geometry), True, pairs,
                            unguided=unguided, fallback=True)
    x1, x2 = p1[pairs[:, 0]], p2[pairs[:, 1]]
    if not (options.refine and isinstance(geometry, TwoViewGeometry)):
        sigma = robust_sigma(segment_residuals(geometry, x1, x2))
        return BandEstimate(clip_tol(sigma, options, size2), sigma, _plain(geometry), True, pairs, unguided=unguided)
    ref = refine_on(geometry, p1, p2, pairs, options)
    keep, sigma = _keep_given(geometry, ref, x1, x2, options)
    if keep:
        return BandEstimate(clip_tol(sigma, options, size2), sigma, _plain(geometry), True, pairs, unguided=unguided)
    return BandEstimate(clip_tol(sigma, options, size2), sigma, ref.geometry, False, pairs, ref.rotation_change_deg,
                        ref.translation_change_deg, unguided)


def _confident(inputs: MatchInputs, geometry: EpipolarGeometry, conf: np.ndarray, options: AutoTol):
    """Step 1's fallback and step 2: the confident matches ``conf`` of a first pass, with plain mutual
    nearest neighbours when they are too few or too few agree with the refined pose, and the refinement on
    them: ``(conf, refinement or None, unguided)`` (None: uncalibrated, or fewer than ``min_matches``)."""
    p1, p2 = inputs.points1, inputs.points2
    unguided = options.unguided_pass is True or (options.unguided_pass == "auto" and len(conf) < options.min_support)
    if unguided:
        conf = _union(conf, unguided_mutual(inputs.distances, options.strict_ratio))
    if not (options.refine and isinstance(geometry, TwoViewGeometry)) or len(conf) < options.min_matches:
        return conf, None, unguided
    ref = refine_on(geometry, p1, p2, conf, options)
    if not unguided and options.unguided_pass == "auto":
        support = np.abs(segment_residuals(ref.geometry, p1[conf[:, 0]], p2[conf[:, 1]]))
        if (support <= max(options.k * ref.sigma, options.tol_min)).sum() < options.min_support:
            unguided = True
            conf = _union(conf, unguided_mutual(inputs.distances, options.strict_ratio))
            ref = refine_on(geometry, p1, p2, conf, options)
    return conf, ref, unguided


def estimate(inputs: MatchInputs, geometry: EpipolarGeometry, search: SearchConfig, rule: AcceptRule,
             options: AutoTol, rng=0, bucket_size: int = 64) -> BandEstimate:
    """:func:`estimate_band` on checked inputs."""
    p1, p2 = inputs.points1, inputs.points2
    strict = strict_rule(options, rule)
    band = options.first_band(geometry.image_size2)
    # the wide band even with a covariance: its bands as the first pass were measured no better (and
    # worse where the covariance understates the error)
    conf = guided.match(inputs, _plain(geometry), search.replace(tol=band), strict, rng, bucket_size)[0]
    conf, ref, unguided = _confident(inputs, geometry, conf, options)
    if ref is None:
        return estimate_from_pairs(conf, p1, p2, geometry, options, unguided)
    keep, sigma = _keep_given(geometry, ref, p1[conf[:, 0]], p2[conf[:, 1]], options)
    if not keep:  # a second strict pass around the refined pose: more confident matches, better spread
        lo, _ = options.bounds(geometry.image_size2)
        b2 = float(np.clip(max(options.k * sigma, 2 * lo), lo, band)) if np.isfinite(sigma) else band
        conf2 = guided.match(inputs, ref.geometry, search.replace(tol=b2), strict, rng, bucket_size)[0]
        if len(conf2) >= options.min_matches:
            conf = conf2
            ref = refine_on(geometry, p1, p2, conf, options)
            keep, sigma = _keep_given(geometry, ref, p1[conf[:, 0]], p2[conf[:, 1]], options)
    tol = clip_tol(sigma, options, geometry.image_size2)
    if keep:
        return BandEstimate(tol, sigma, _plain(geometry), True, conf, unguided=unguided)
    # step 5: the matches of that band under the usual rule (the strict rule's padding), the last refinement on them
    final = guided.match(inputs, ref.geometry, search.replace(tol=tol), AcceptRule(pad=strict.pad), rng,
                         bucket_size)[0]
    if len(final) >= options.min_matches:
        ref = refine_on(geometry, p1, p2, final, options)
        s5 = robust_sigma(segment_residuals(ref.geometry, p1[conf[:, 0]], p2[conf[:, 1]]))
        if np.isfinite(s5):
            sigma = s5
            tol = clip_tol(sigma, options, geometry.image_size2)
    return BandEstimate(tol, sigma, ref.geometry, False, conf, ref.rotation_change_deg, ref.translation_change_deg,
                        unguided)


def _noise(search: SearchConfig, ref: PoseRefinement) -> float:
    """The keypoint-noise term of the posterior bands: ``search.tol``, or ``KAPPA`` robust sigmas of the
    confident matches' distances to their lines when that is more (a model error the pose cannot absorb)."""
    return max(search.tol, KAPPA * ref.sigma) if np.isfinite(ref.sigma) else search.tol


def posterior(inputs: MatchInputs, geometry: TwoViewGeometry, search: SearchConfig, rule: AcceptRule,
              options: AutoTol, rng=0, bucket_size: int = 64) -> tuple[TwoViewGeometry, float]:
    """The pose covariance as a prior (module docstring of :mod:`episeg_cv.uncertainty`): ``(geometry, tol)``
    to match with, the refined pose with its posterior covariance and the noise term of its bands.

    Confident matches (the strict rule) in the bands of the prior, with the fallback of step 1; the pose
    refined on them with the prior (step 2); a second strict pass in the bands of that posterior and a
    second refinement. With fewer than ``options.min_matches`` confident matches, the given geometry.
    """
    p1, p2 = inputs.points1, inputs.points2
    strict = strict_rule(options, rule)
    conf = banded.match(inputs, geometry, banded.bands_for(geometry, p1, search), search, strict, rng,
                        bucket_size)[0]
    conf, ref, _ = _confident(inputs, geometry, conf, options)
    if ref is None:
        return geometry, search.tol
    first = ref.geometry.with_covariance(ref.covariance)
    s1 = search.replace(tol=_noise(search, ref))
    conf = banded.match(inputs, first, banded.bands_for(first, p1, s1), s1, strict, rng, bucket_size)[0]
    if len(conf) >= options.min_matches:
        ref = refine_on(geometry, p1, p2, conf, options)
    return ref.geometry.with_covariance(ref.covariance), _noise(search, ref)


def estimate_band(descriptors1, descriptors2, points1, points2, geometry, *, options: AutoTol | None = None,
                  norm="l2", search: SearchConfig | None = None, rule: AcceptRule | None = None, rng=0,
                  bucket_size: int = 64, **fields) -> BandEstimate:
    """The band (and the pose) that ``tol="auto"`` matches with.

    Parameters
    ----------
    descriptors1, descriptors2, points1, points2, norm
        As in :func:`~episeg_cv.match_descriptors`.
    geometry : TwoViewGeometry or FundamentalGeometry
        The given pose, ``X2 = R @ X1 + t`` (perhaps wrong by a degree or so).
        With a covariance, it is the refinement's prior. An uncalibrated
        geometry gets a band only.
    options : AutoTol, optional
        The constants (default: ``search.tol`` when it is an ``AutoTol``, else
        ``AutoTol()``); its fields may also be given as keywords (``k=4``).
    search : SearchConfig, optional
        The constraint and depth range of the passes (its ``tol`` is not used).
    rule : AcceptRule, optional
        Only its ``pad`` is used (the confident matches have their own strict rule).
    rng : int or numpy.random.Generator, optional
        Seed of the padding draw.

    Returns
    -------
    BandEstimate
        ``tol``, ``sigma``, the ``geometry`` to match with, ``pose_kept``, the
        ``confident`` matches and the size of the correction.

    Examples
    --------
    >>> from episeg_cv import scenes
    >>> import cv2, numpy as np
    >>> pair = scenes.make_pair("forward", image_size=(320, 240))
    >>> sift = cv2.SIFT_create(nfeatures=1500)
    >>> (k1, d1), (k2, d2) = (sift.detectAndCompute(im, None) for im in (pair.image1, pair.image2))
    >>> p1, p2 = (np.array([k.pt for k in kk]) for kk in (k1, k2))
    >>> est = estimate_band(d1, d2, p1, p2, pair.geometry)     # the exact pose: kept, 2 px
    >>> est.pose_kept, est.tol
    (True, 2.0)
    """
    search, rule = resolve(search, rule, {})
    base = options if options is not None else (search.auto or AutoTol())
    if not isinstance(base, AutoTol):
        raise TypeError(f"options must be an AutoTol or None, got {type(base).__name__}")
    allowed = [f.name for f in dataclasses.fields(AutoTol)]
    unknown = [k for k in fields if k not in allowed]
    if unknown:
        raise TypeError(f"unknown option {unknown[0]!r}; the options are {', '.join(allowed)}")
    options = base.replace(**fields) if fields else base
    inputs = MatchInputs.check(descriptors1, descriptors2, points1, points2, norm)
    if search.constraint == "none":
        raise ValueError("estimate_band needs constraint 'segment' or 'line'")
    return estimate(inputs, as_geometry(geometry), search, rule, options, rng,
                    as_positive_int(bucket_size, "bucket_size"))


# -- the plan of a matching call: which geometry, which tol, which bands ------------------------
@dataclass(frozen=True, eq=False)
class Plan:
    """How a matching call runs once ``tol="auto"`` and the covariance are resolved.

    Attributes
    ----------
    geometry : EpipolarGeometry
    search : SearchConfig
        With a numeric ``tol``.
    bands : EpipolarBands or None
        Per-query bands (the geometry has a covariance), or None: the fixed ``tol``.
    estimate : BandEstimate or None
        What ``tol="auto"`` found, or None.
    """

    geometry: EpipolarGeometry
    search: SearchConfig
    bands: EpipolarBands | None = None
    estimate: BandEstimate | None = None


def plan(inputs: MatchInputs, geometry: EpipolarGeometry, search: SearchConfig, rule: AcceptRule, rng=0,
         bucket_size: int = 64) -> Plan:
    """Resolve ``tol="auto"`` (:func:`estimate`) and the geometry's covariance (bands) for one call."""
    est = None
    if search.auto is not None:
        if search.constraint == "none":
            return Plan(geometry, search.replace(tol=search.auto.tol_min))
        est = estimate(inputs, geometry, search, rule, search.auto, rng, bucket_size)
        geometry, search = est.geometry, search.replace(tol=est.tol)
    bands = None
    if getattr(geometry, "covariance", None) is not None and search.constraint != "none":
        if est is None:
            geometry, tol = posterior(inputs, geometry, search, rule, AutoTol(), rng, bucket_size)
            search = search.replace(tol=tol)
        bands = banded.bands_for(geometry, inputs.points1, search)
    return Plan(geometry, search, bands, est)


def plan_pairs(pairs: np.ndarray, points1: np.ndarray, points2: np.ndarray, geometry: EpipolarGeometry,
               search: SearchConfig) -> Plan:
    """:func:`plan` for filtering given matches: ``tol="auto"`` is estimated from the pairs themselves."""
    est = None
    if search.auto is not None and search.constraint != "none":
        est = estimate_from_pairs(pairs, points1, points2, geometry, search.auto)
        geometry, search = est.geometry, search.replace(tol=est.tol)
    elif search.auto is not None:
        search = search.replace(tol=search.auto.tol_min)
    bands = None
    if getattr(geometry, "covariance", None) is not None and search.constraint != "none":
        bands = banded.bands_for(geometry, points1, search)
    return Plan(geometry, search, bands, est)


def _plain_plan(p: Plan, index) -> None:
    if index is not None and (p.bands is not None or p.estimate is not None):
        raise ValueError("index= is for a fixed numeric tol and a geometry without covariance; "
                         "with tol='auto' or a covariance each call builds its own index")


def nearest(inputs, geometry, search, rule, rng=0, bucket_size=64, prefilter=False, index=None):
    """:func:`~.guided.nearest` after :func:`plan`: ``((i, j, ratio, mutual, counts), plan)``."""
    p = plan(inputs, geometry, search, rule, rng, bucket_size)
    _plain_plan(p, index)
    if p.bands is not None:
        return banded.nearest(inputs, p.geometry, p.bands, p.search, rule, rng, bucket_size), p
    return guided.nearest(inputs, p.geometry, p.search, rule, rng, bucket_size, prefilter, index=index), p


def match(inputs, geometry, search, rule, rng=0, bucket_size=64, index=None):
    """:func:`~.guided.match` after :func:`plan`."""
    p = plan(inputs, geometry, search, rule, rng, bucket_size)
    _plain_plan(p, index)
    if p.bands is not None:
        return banded.match(inputs, p.geometry, p.bands, p.search, rule, rng, bucket_size)
    return guided.match(inputs, p.geometry, p.search, rule, rng, bucket_size, index=index)


def knn(inputs, geometry, search, k, rule=None, rng=0, index=None):
    """:func:`~.guided.knn` after :func:`plan`."""
    p = plan(inputs, geometry, search, rule or AcceptRule(), rng)
    _plain_plan(p, index)
    if p.bands is not None:
        return banded.knn(inputs, p.geometry, p.bands, p.search, k)
    return guided.knn(inputs, p.geometry, p.search, k, index=index)


def radius(inputs, geometry, search, max_distance, rule=None, rng=0, index=None):
    """:func:`~.guided.radius` after :func:`plan`."""
    p = plan(inputs, geometry, search, rule or AcceptRule(), rng)
    _plain_plan(p, index)
    if p.bands is not None:
        return banded.radius(inputs, p.geometry, p.bands, p.search, max_distance)
    return guided.radius(inputs, p.geometry, p.search, max_distance, index=index)
