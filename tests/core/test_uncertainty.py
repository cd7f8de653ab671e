"""Pose covariance: validation, propagation computed by hand, Monte Carlo, the band test, and matching in bands."""

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from episeg_cv import (SegmentMatcher, TwoViewGeometry, filter_pairs, guided_matches, knn_descriptors,
                       match_descriptors, pose_covariance, radius_descriptors, scenes)
from episeg_cv.geometry import point_segment_distance

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
SIZE = dict(image_size1=(640, 480), image_size2=(640, 480))


def _rot(w):
    th = np.linalg.norm(w)
    if th == 0:
        return np.eye(3)
    k = w / th
    S = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * S + (1 - np.cos(th)) * S @ S


# --- validation -----------------------------------------------------------------------------------
G = TwoViewGeometry(K, K, np.eye(3), [0, 0, 1], **SIZE)


@pytest.mark.parametrize("cov, message", [
    (np.eye(5), r"cov must have shape \(6, 6\)"), (np.eye(6)[:, :5], r"cov must have shape \(6, 6\)"),
    (np.full((6, 6), np.nan), "cov must be finite"), (np.diag([1, 1, 1, 1, 1, -1.0]), "positive semi-definite"),
    (np.eye(6) + np.triu(np.ones((6, 6)), 1), "symmetric"), ("eye", "cov must be a numeric array"),
])
def test_bad_covariance_is_refused(cov, message):
    with pytest.raises((ValueError, TypeError), match=message):
        G.with_covariance(cov)


def test_with_covariance_makes_a_new_read_only_geometry():
    C = np.diag([1e-6] * 3 + [1e-4] * 3)
    g = G.with_covariance(C)
    assert G.covariance is None and np.array_equal(g.covariance, C) and g is not G
    with pytest.raises(ValueError):
        g.covariance[0, 0] = 1.0
    assert g.with_covariance(None).covariance is None
    tiny = G.with_covariance(np.diag([1e-20] + [0.0] * 5) - 1e-30 * np.eye(6))  # rounding below 0 is accepted
    assert tiny.covariance.shape == (6, 6)


def test_inverse_propagates_the_covariance():
    """dtheta' = -R^T dtheta, dt' = -R^T dt - R^T [t]x dtheta, checked by finite differences of the inverse pose."""
    R0, t0 = _rot(np.array([0.1, -0.2, 0.05])), np.array([0.3, -1.0, 0.5])
    g = TwoViewGeometry(K, K, R0, t0, **SIZE)
    J = np.zeros((6, 6))
    h = 1e-7
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = h
        R, t = _rot(xi[:3]) @ R0, t0 + xi[3:]
        Ri, ti = R.T, -R.T @ t
        dR = Ri @ R0  # the inverse's left perturbation: Ri = expm([d]) R0^T
        d = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / 2
        J[:3, k], J[3:, k] = d / h, (ti - (-R0.T @ t0)) / h
    C = np.diag([1e-4, 2e-4, 3e-4, 1e-2, 2e-2, 3e-2])
    np.testing.assert_allclose(g.with_covariance(C).inverse().covariance, J @ C @ J.T, rtol=1e-5, atol=1e-12)
    np.testing.assert_allclose(g.with_covariance(C).inverse().inverse().covariance, C, atol=1e-15)


def test_pose_covariance_by_hand():
    g = TwoViewGeometry(K, K, np.eye(3), [3, 0, 4], **SIZE)
    C = pose_covariance(g, 2.0, 3.0, scale=0.1)
    a, b = np.deg2rad(2.0), np.deg2rad(3.0)
    np.testing.assert_allclose(C[:3, :3], a**2 / 3 * np.eye(3))
    u = np.array([0.6, 0, 0.8])
    np.testing.assert_allclose(C[3:, 3:], 25 * b**2 / 2 * (np.eye(3) - np.outer(u, u)) + 0.25 * np.outer(u, u))
    assert np.all(C[:3, 3:] == 0)
    with pytest.raises(ValueError, match="rotation_deg"):
        pose_covariance(g, -1, 1)


# --- propagation by hand ----------------------------------------------------------------------------
def test_translation_moves_only_the_epipole_end():
    """Camera 2 behind camera 1 (t = (0, 0, 1)): the segment of x1 runs from the epipole (image centre) to
    p_inf = x1. A sideways error of t with sigma s moves the epipole by f s / t3 and p_inf not at all."""
    C = np.zeros((6, 6))
    C[3, 3] = C[4, 4] = 0.02**2
    b = G.with_covariance(C).bands([[420.0, 240.0], [320.0, 340.0]], tol=0.0, kappa=1.0)
    np.testing.assert_allclose(b.sigma_start, [10.0, 10.0], atol=1e-9)  # 500 * 0.02 / 1
    np.testing.assert_allclose(b.sigma_end, [0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(b.w_start, 10.0) and np.testing.assert_allclose(b.w_end, 0.0, atol=1e-9)
    # along the line: the epipole moves along it by the same 10 px (isotropic), p_inf does not
    np.testing.assert_allclose(b.e_start, 10.0, atol=1e-9)


def test_rotation_moves_p_inf_by_f_times_the_angle():
    """A rotation error about the y axis moves p_inf = x1 (on the image centre row, 100 px right of the
    centre) sideways by f (1 + (100 / f)^2) * angle to first order, and the epipole not at all: across the
    horizontal line that is 0, along it 520 * angle; about the x axis, across the line by f * angle."""
    s = 1e-3
    for axis, across, along in ((1, 0.0, 520 * s), (0, 500 * s, 0.0)):
        C = np.zeros((6, 6))
        C[axis, axis] = s**2
        b = G.with_covariance(C).bands([[420.0, 240.0]], tol=0.0, kappa=1.0)
        np.testing.assert_allclose(b.sigma_end, [across], atol=1e-9)
        np.testing.assert_allclose(b.e_end, [along], atol=1e-9, rtol=1e-6)
        np.testing.assert_allclose(b.sigma_start, [0.0], atol=1e-9)


def test_quadrature_and_cap():
    C = np.zeros((6, 6))
    C[3, 3] = C[4, 4] = 0.02**2
    b = G.with_covariance(C).bands([[420.0, 240.0]], tol=2.0, kappa=2.0)
    np.testing.assert_allclose(b.w_start, [np.hypot(20.0, 2.0)]) and np.testing.assert_allclose(b.w_end, [2.0])
    capped = G.with_covariance(C * 1e4).bands([[420.0, 240.0]], max_reach=50.0)
    assert capped.w_start[0] == 50.0 and capped.reach[0] == 50.0


def _coverage(seed, kappa):
    """Draw poses from the covariance: the fraction of true matches (3-D points seen by the drawn pose)
    inside the band of the nominal pose."""
    rng = np.random.default_rng(seed)
    R0 = _rot(rng.normal(0, 0.2, 3))
    t0 = rng.normal(0, 1, 3)
    t0[2] = abs(t0[2]) + 0.2
    g = TwoViewGeometry(K, K, R0, t0, **SIZE)
    C = pose_covariance(g, 0.5, 2.5)
    n = 400
    x1 = rng.uniform([0, 0], [640, 480], (n, 2))
    z = rng.uniform(2, 30, n)
    b = g.with_covariance(C).bands(x1, tol=0.0, kappa=kappa)
    val, vec = np.linalg.eigh(C)
    L = vec * np.sqrt(np.maximum(val, 0.0))
    inside, total = 0, 0
    for _ in range(200):  # (poses move all points together: few draws make a noisy fraction)
        xi = L @ rng.normal(size=6)
        true = TwoViewGeometry(K, K, _rot(xi[:3]) @ R0, t0 + xi[3:], **SIZE)
        x2, z2 = true.transfer(x1, z)
        seen = (z2 > 0) & np.all((x2 > 0) & (x2 < [639, 479]), axis=1) & b.valid
        inside += int(b.contains(np.flatnonzero(seen), x2[seen]).sum())
        total += int(seen.sum())
    assert total > 500
    return inside / total


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 10**6))
def test_monte_carlo_the_true_match_stays_in_its_band(seed):
    """99 % by construction (first order): at least 96 % (measured 97.2-99.95 % over 300 seeds, median 99.0 %;
    96.6 % at seed 1347, which hypothesis found: the first-order bands at 0.5 deg, 2.5 deg miss a tail)."""
    assert _coverage(seed, 2.576) >= 0.96


def test_monte_carlo_the_band_is_calibrated_not_only_safe():
    """At one standard deviation the band holds about 68 % of the true matches, as a Gaussian does (measured
    0.63-0.68 a seed); the trapezoid joining the ends' half-widths held 0.69-0.84 (0.81 on average)."""
    assert 0.62 < np.mean([_coverage(seed, 1.0) for seed in range(4)]) < 0.74


def test_half_width_between_the_ends_by_hand():
    """Ends 10 px wide whose displacements are anticorrelated: at the middle w^2 = (100 + 2 w_cross + 100) / 4."""
    from episeg_cv.uncertainty import EpipolarBands
    P, Q = np.array([[0.0, 0.0]]), np.array([[100.0, 0.0]])
    ten, one = np.array([10.0]), np.array([1.0])
    b = EpipolarBands(P, Q, np.array([True]), ten, ten, ten, ten, one, one, np.array([-96.0]))  # w(0.5) = sqrt(2)
    assert b.contains([0, 0], [[50.0, 1.40], [50.0, -1.40]]).all()
    assert not b.contains([0, 0], [[50.0, 1.43], [50.0, -1.43]]).any()
    assert b.contains([0], [[0.0, 9.99]])[0] and not b.contains([0], [[0.0, 10.01]])[0]
    w = np.sqrt(0.75**2 * 100 + 2 * 0.75 * 0.25 * -96 + 0.25**2 * 100)  # at a quarter: 6.80 px
    assert b.contains([0], [[25.0, w - 0.01]])[0] and not b.contains([0], [[25.0, w + 0.01]])[0]
    # without w_cross: the trapezoid (10 px all along here)
    trap = EpipolarBands(P, Q, np.array([True]), ten, ten, ten, ten, one, one)
    assert trap.contains([0], [[50.0, 9.99]])[0] and np.array_equal(trap.cross, [100.0])


def test_a_pivoting_line_has_a_narrow_waist():
    """A pose error that keeps one 3-D point fixed in camera 2 (a rotation dtheta with dt = -dtheta x X)
    turns the line about that point's image: the band is tol wide there, wider at both ends."""
    g = TwoViewGeometry(K, K, np.eye(3), [-1.0, 0, 0], **SIZE)
    x1 = np.array([[320.0, 300.0]])
    X = 5.0 * np.linalg.inv(K) @ np.array([320.0, 300.0, 1.0])
    dtheta = np.array([1.0, 0.0, 0.0])  # about x: the horizontal line tilts
    xi = np.concatenate([dtheta, np.cross(X, dtheta)])  # X2 + dX2 = (I + [dtheta]x) X + t + dt = X2
    b = g.with_covariance(1e-6 * np.outer(xi, xi)).bands(x1, tol=1.0)
    x2, _ = g.transfer(x1, 5.0)
    u = (x2[0] - b.start[0]) @ (b.end[0] - b.start[0]) / np.sum((b.end[0] - b.start[0]) ** 2)
    w2 = (1 - u) ** 2 * b.w_start[0] ** 2 + 2 * u * (1 - u) * b.w_cross[0] + u**2 * b.w_end[0] ** 2
    assert np.sqrt(w2) == pytest.approx(1.0, abs=0.01)
    assert (1 - u) * b.w_start[0] + u * b.w_end[0] > 2.3  # the trapezoid: 2.4 px there
    assert b.contains([0], [x2[0] + [0, 0.99]])[0] and not b.contains([0], [x2[0] + [0, 1.05]])[0]


@settings(max_examples=25, deadline=None)
@given(w=st.floats(0.5, 20), e=st.floats(0.5, 20), px=st.floats(-100, 700), py=st.floats(-100, 600))
def test_band_with_equal_widths_is_the_stadium(w, e, px, py):
    """With w = e everywhere the band is the set within w of the segment (the plain matcher's test)."""
    from episeg_cv.uncertainty import EpipolarBands
    P, Q = np.array([[100.0, 100.0]]), np.array([[500.0, 300.0]])
    one = np.array([w])
    b = EpipolarBands(P, Q, np.array([True]), one, one, one, one, one, one)
    d = point_segment_distance(np.array([[px, py]]), P, Q)[0]
    if abs(d - w) > 1e-6:
        assert bool(b.contains([0], [[px, py]])[0]) == (d <= w)
    # a trapezoid between the two half-widths, with elliptical caps
    b2 = EpipolarBands(P, Q, np.array([True]), np.array([w]), np.array([w]), np.array([e]), np.array([e]), one, one)
    m = (Q - P)[0] / np.linalg.norm(Q - P)
    before = P[0] - 0.999 * e * m
    assert b2.contains([0], [before])[0] and not b2.contains([0], [P[0] - 1.001 * e * m])[0]


# --- matching in the bands -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def forward():
    pair = scenes.make_pair("forward", image_size=(320, 240))
    sift = cv2.SIFT_create(nfeatures=1500, contrastThreshold=0.02)
    (k1, d1), (k2, d2) = (sift.detectAndCompute(im, None) for im in (pair.image1, pair.image2))
    p1, p2 = (np.array([k.pt for k in kk]) for kk in (k1, k2))
    return pair, d1, d2, p1, p2


@pytest.mark.parametrize("tol, cross_check", [(2.0, False), (5.0, False), (2.0, True)])
def test_zero_covariance_gives_the_plain_matcher(forward, tol, cross_check):
    pair, d1, d2, p1, p2 = forward
    g = pair.geometry
    a = guided_matches(d1, d2, p1, p2, g, tol=tol, cross_check=cross_check)
    b = guided_matches(d1, d2, p1, p2, g.with_covariance(np.zeros((6, 6))), tol=tol, cross_check=cross_check)
    assert np.array_equal(a.pairs, b.pairs) and np.array_equal(a.mutual, b.mutual)
    np.testing.assert_array_equal(a.ratio, b.ratio) and np.testing.assert_array_equal(a.candidates, b.candidates)
    ka = knn_descriptors(d1, d2, p1, p2, g, k=3, tol=tol)
    kb = knn_descriptors(d1, d2, p1, p2, g.with_covariance(np.zeros((6, 6))), k=3, tol=tol)
    assert np.array_equal(ka.indices, kb.indices) and np.array_equal(ka.column_best, kb.column_best)
    ra = radius_descriptors(d1, d2, p1, p2, g, max_distance=200.0, tol=tol)
    rb = radius_descriptors(d1, d2, p1, p2, g.with_covariance(np.zeros((6, 6))), max_distance=200.0, tol=tol)
    assert np.array_equal(ra[0], rb[0])


def test_covariance_band_recovers_matches_of_a_wrong_pose(forward):
    pair, d1, d2, p1, p2 = forward
    gt = pair.ground_truth(p1, p2)
    g = pair.geometry
    rng = np.random.default_rng(3)
    axis = rng.normal(size=3)
    off = TwoViewGeometry(g.K1, g.K2, _rot(np.deg2rad(0.5) * axis / np.linalg.norm(axis)) @ g.R, g.t,
                          image_size1=g.image_size1, image_size2=g.image_size2)
    plain = match_descriptors(d1, d2, p1, p2, off)[0]
    banded = match_descriptors(d1, d2, p1, p2, off.with_covariance(pose_covariance(off, 0.5, 0.5)))[0]
    assert gt.is_correct(banded).sum() > 1.3 * gt.is_correct(plain).sum()
    assert gt.is_correct(banded).mean() > 0.9
    # the same through SegmentMatcher, and filtering in the bands keeps what matching in them found
    m = SegmentMatcher(off.with_covariance(pose_covariance(off, 0.5, 0.5)))
    kp1 = [cv2.KeyPoint(float(x), float(y), 3) for x, y in p1]
    kp2 = [cv2.KeyPoint(float(x), float(y), 3) for x, y in p2]
    assert [(d.queryIdx, d.trainIdx) for d in m.match(d1, d2, kp1, kp2)] == [tuple(p) for p in banded.tolist()]
    assert filter_pairs(banded, p1, p2, m.geometry).all()
    assert not filter_pairs(banded, p1, p2, off).all()
    labels, counts = m.explain(m.match(d1, d2, kp1, kp2), kp1, kp2)
    assert counts["on_segment"] == len(banded)


def _perturbed(g, rot_deg, t_deg, seed):
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    R = _rot(np.deg2rad(rot_deg) * axis / np.linalg.norm(axis)) @ g.R
    u = g.t / np.linalg.norm(g.t)
    d = rng.normal(size=3)
    d -= (d @ u) * u
    t = np.linalg.norm(g.t) * (np.cos(np.deg2rad(t_deg)) * u + np.sin(np.deg2rad(t_deg)) * d / np.linalg.norm(d))
    return TwoViewGeometry(g.K1, g.K2, R, t, image_size1=g.image_size1, image_size2=g.image_size2)


def test_matching_with_a_covariance_uses_its_posterior(forward):
    """Off by (1 deg, 5 deg) with the true covariance of that error: the posterior pose is much nearer the
    truth, and the bands of its posterior find at least what the best fixed band chosen in hindsight finds."""
    from episeg_cv import AcceptRule, AutoTol, SearchConfig
    from episeg_cv.matching import auto
    from episeg_cv.matching.guided import MatchInputs
    from episeg_cv.refinement import rotation_angle_deg
    pair, d1, d2, p1, p2 = forward
    gt = pair.ground_truth(p1, p2)
    off = _perturbed(pair.geometry, 1.0, 5.0, seed=3)
    prior = off.with_covariance(pose_covariance(off, 1.0, 5.0))
    post, tol = auto.posterior(MatchInputs.check(d1, d2, p1, p2, "l2"), prior, SearchConfig(), AcceptRule(),
                               AutoTol())
    assert rotation_angle_deg(post.R @ pair.geometry.R.T) < 0.1 and tol == 2.0
    assert np.all(np.sqrt(np.diag(post.covariance)[:3]) < 0.05 * np.sqrt(np.diag(prior.covariance)[:3]))
    ours = gt.is_correct(match_descriptors(d1, d2, p1, p2, prior)[0])
    fixed = [gt.is_correct(match_descriptors(d1, d2, p1, p2, off, tol=t)[0]).sum() for t in (2.0, 4.0, 8.0, 16.0)]
    exact = gt.is_correct(match_descriptors(d1, d2, p1, p2, pair.geometry)[0])
    assert ours.sum() >= max(fixed) and ours.sum() >= 0.97 * exact.sum() and ours.mean() >= exact.mean() - 0.01


def test_with_too_few_confident_matches_the_prior_bands_are_used(forward):
    from episeg_cv import AcceptRule, AutoTol, SearchConfig
    from episeg_cv.matching import auto
    from episeg_cv.matching.guided import MatchInputs
    pair, d1, d2, p1, p2 = forward
    prior = pair.geometry.with_covariance(pose_covariance(pair.geometry, 0.5, 2.5))
    inputs = MatchInputs.check(d1[:8], d2[:8], p1[:8], p2[:8], "l2")
    assert auto.posterior(inputs, prior, SearchConfig(tol=3.0), AcceptRule(), AutoTol()) == (prior, 3.0)
