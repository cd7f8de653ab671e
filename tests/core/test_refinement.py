"""The refinement as a maximum a posteriori estimate: its prior, its noise weighting and its posterior covariance."""

import numpy as np
import pytest

from episeg_cv import TwoViewGeometry, pose_covariance, refine_pose

K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
SIZE = dict(image_size1=(640, 480), image_size2=(640, 480))


def _rot(w):
    th = float(np.linalg.norm(w))
    if th == 0:
        return np.eye(3)
    k = np.asarray(w, float) / th
    S = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * S + (1 - np.cos(th)) * S @ S


def _log(R):
    th = np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return v * (0.5 if th < 1e-12 else th / (2 * np.sin(th)))


def _scene(rng, noise, n=200):
    true = TwoViewGeometry(K, K, _rot(rng.normal(0, 0.05, 3)), np.array([-1.0, 0.1, 0.3]) + rng.normal(0, 0.1, 3),
                           **SIZE)
    x1 = rng.uniform([0, 0], [640, 480], (n, 2))
    x2, _ = true.transfer(x1, rng.uniform(3, 10, n))
    ok = np.all(np.isfinite(x2), axis=1)
    return true, x1[ok], x2[ok] + rng.normal(0, noise, (ok.sum(), 2))


def _off(true, rng, rot_sd=0.01, t_sd=0.05):
    t = true.t + rng.normal(0, t_sd, 3)
    R = _rot(rng.normal(0, rot_sd, 3)) @ true.R
    return TwoViewGeometry(K, K, R, t / np.linalg.norm(t) * np.linalg.norm(true.t), **SIZE)


def test_with_too_few_matches_the_posterior_is_the_prior():
    g = TwoViewGeometry(K, K, np.eye(3), [3.0, 0, 4.0], **SIZE)
    ref = refine_pose(g, [[1.0, 2.0]] * 5, [[3.0, 4.0]] * 5, prior_deg=2.0)
    a = np.deg2rad(2.0) ** 2
    u = np.array([0.6, 0, 0.8])
    np.testing.assert_allclose(ref.covariance[:3, :3], a * np.eye(3))  # by hand: the isotropic prior
    np.testing.assert_allclose(ref.covariance[3:, 3:], 25 * a * (np.eye(3) - np.outer(u, u)), atol=1e-15)
    C = pose_covariance(g, 0.5, 2.0, scale=0.1)
    np.testing.assert_array_equal(refine_pose(g.with_covariance(C), [[1.0, 2.0]] * 5, [[3.0, 4.0]] * 5).covariance, C)


def test_the_posterior_covariance_is_calibrated():
    """Over poses refined from noisy matches, the error of the refined pose in the metric of its posterior
    covariance (5 degrees of freedom: |t| is kept) is chi-square distributed: mean 5, 95 % below 11.07."""
    rng = np.random.default_rng(1)
    m2 = []
    for _ in range(60):
        true, x1, x2 = _scene(rng, 0.5)
        ref = refine_pose(_off(true, rng), x1, x2)
        u = ref.geometry.t / np.linalg.norm(ref.geometry.t)
        dt = true.t - ref.geometry.t
        e = np.concatenate([_log(true.R @ ref.geometry.R.T), dt - (dt @ u) * u])
        m2.append(e @ np.linalg.pinv(ref.covariance, rcond=1e-9) @ e)
    m2 = np.array(m2)
    assert 3.8 < m2.mean() < 6.5 and np.mean(m2 < 11.07) > 0.88


def test_the_posterior_keeps_the_prior_where_the_matches_do_not_see():
    """|t| is not refined: the posterior's variance along the refined t is the prior's; the matches narrow
    the rest."""
    rng = np.random.default_rng(2)
    true, x1, x2 = _scene(rng, 0.5)
    off = _off(true, rng)
    C = pose_covariance(off, 0.5, 2.0, scale=0.1)
    ref = refine_pose(off.with_covariance(C), x1, x2)
    u = ref.geometry.t / np.linalg.norm(ref.geometry.t)
    assert u @ ref.covariance[3:, 3:] @ u == pytest.approx((0.1 * np.linalg.norm(off.t)) ** 2, rel=1e-3)
    assert np.trace(ref.covariance[:3, :3]) < 0.01 * np.trace(C[:3, :3])


def test_the_prior_weighs_more_against_noisier_matches():
    """A maximum a posteriori estimate: the same prior (0.2 deg, about the given pose) and the same
    matches with ten times the noise: the correction shrinks towards the given pose, about as the ratio
    of the data's information to the prior's predicts (it does not without the 1 / sigma^2 weight)."""
    rng = np.random.default_rng(4)
    true, x1, x2 = _scene(rng, 0.0, n=60)
    off = TwoViewGeometry(K, K, _rot([0.0, 0.0, np.deg2rad(0.3)]) @ true.R, true.t, **SIZE)
    prior = off.with_covariance(pose_covariance(off, 0.2, 0.2))
    noise = np.random.default_rng(5).normal(0, 1.0, x2.shape)
    clean = refine_pose(prior, x1, x2 + 0.2 * noise)
    noisy = refine_pose(prior, x1, x2 + 2.0 * noise)
    assert clean.rotation_change_deg > 0.25  # the data win: the truth is 0.3 deg away
    assert noisy.rotation_change_deg < 0.8 * clean.rotation_change_deg
    assert noisy.sigma > 5 * clean.sigma
