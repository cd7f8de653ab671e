"""FundamentalGeometry: the oriented half-line, its orientation, the reverse direction, rectified pairs."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from episeg_cv import (FundamentalGeometry, SearchConfig, TwoViewGeometry, filter_pairs, guided_matches,
                       match_descriptors)
from episeg_cv.geometry import as_geometry

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
SIZE = dict(image_size1=(640, 480), image_size2=(640, 480))


def _rot(w):
    th = np.linalg.norm(w)
    if th == 0:
        return np.eye(3)
    k = np.asarray(w) / th
    S = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * S + (1 - np.cos(th)) * S @ S


def _views(g, n=300, seed=0):
    """Points of a random cloud seen in both views (positive depths, inside both images)."""
    rng = np.random.default_rng(seed)
    x1 = rng.uniform([0, 0], [640, 480], (n, 2))
    z = rng.uniform(1, 20, n)
    x2, z2 = g.transfer(x1, z)
    ok = (z2 > 0) & np.all((x2 > 0) & (x2 < [639, 479]), axis=1)
    return x1[ok], x2[ok]


def test_hand_case_the_half_line_starts_at_the_epipole():
    # camera 2 behind camera 1: the epipole is the image centre, the matches lie between it and x1 and beyond
    g = TwoViewGeometry(K, K, np.eye(3), [0, 0, 1], **SIZE)
    x1, x2 = _views(g)
    f = FundamentalGeometry.oriented(-3.0 * g.fundamental_matrix, x1, x2, **SIZE)
    assert f.agreement == 1.0 and not f.is_calibrated and f.covariance is None
    np.testing.assert_allclose(f.epipole, [320, 240])
    s = f.segments([[420.0, 240.0], [320.0, 100.0]])
    np.testing.assert_allclose(s.start, [[320, 240], [320, 240]], atol=1e-9)
    np.testing.assert_allclose(s.end, [[639.5, 240], [320, -0.5]], atol=1e-9)
    # the other side of the epipole is excluded; the line test would keep it
    pairs = np.array([[0, 0], [0, 1]])
    p2 = np.array([[500.0, 240.0], [100.0, 240.0]])
    assert filter_pairs(pairs, [[420.0, 240.0]], p2, f).tolist() == [True, False]
    assert filter_pairs(pairs, [[420.0, 240.0]], p2, f, constraint="line").tolist() == [True, True]
    assert as_geometry(f) is f


@settings(max_examples=30, deadline=None)
@given(w=st.lists(st.floats(-0.4, 0.4), min_size=3, max_size=3), t=st.lists(st.floats(-1, 1), min_size=3, max_size=3),
       scale=st.floats(-5, 5).filter(lambda v: abs(v) > 0.01), seed=st.integers(0, 10**6))
def test_property_every_true_match_is_on_its_half_line(w, t, scale, seed):
    t = np.asarray(t)
    if np.linalg.norm(t) < 0.1:
        return
    g = TwoViewGeometry(K, K, _rot(np.asarray(w)), t, **SIZE)
    x1, x2 = _views(g, seed=seed)
    if len(x1) < 20:
        return
    f = FundamentalGeometry.oriented(scale * g.fundamental_matrix, x1, x2, **SIZE)
    assert f.agreement == 1.0
    d = f.segments(x1, margin=2.0).distance(x2)
    assert np.all(d < 1e-6 * 640)
    # and the reverse direction, oriented on its own
    inv = f.inverse()
    assert np.all(inv.segments(x2, margin=2.0).distance(x1) < 1e-6 * 640)
    np.testing.assert_allclose(inv.inverse().fundamental_matrix, f.fundamental_matrix)
    # the calibrated segment lies inside the half-line (it is the part up to p_inf)
    seg, half = g.segments(x1), f.segments(x1, margin=1.0)
    ok = seg.valid
    assert np.all(half.distance(seg.start[ok]) < 1e-3) and np.all(half.distance(seg.end[ok]) < 1e-3)


def test_rectified_pair_searches_the_whole_line():
    g = TwoViewGeometry(K, K, np.eye(3), [-1, 0, 0], **SIZE)  # rectified stereo: the epipole at infinity
    x1, x2 = _views(g)
    f = FundamentalGeometry.oriented(g.fundamental_matrix, x1, x2, **SIZE)
    assert f.at_infinity
    s = f.segments([[300.0, 100.0]])
    np.testing.assert_allclose(s.start, [[-0.5, 100]]) and np.testing.assert_allclose(s.end, [[639.5, 100]])
    assert np.all(f.segments(x1).distance(x2) < 1e-6)


def test_matching_on_the_half_line_equals_matching_on_the_calibrated_geometry_when_it_covers_it():
    """Descriptors that identify their matches: both find every one."""
    g = TwoViewGeometry(K, K, _rot([0, 0.1, 0]), [-1, 0.1, 0.3], **SIZE)
    x1, x2 = _views(g, 200, seed=1)
    d = np.random.default_rng(0).random((len(x1), 16)).astype(np.float32)
    f = FundamentalGeometry.oriented(g.fundamental_matrix, x1, x2, **SIZE)
    a = match_descriptors(d, d, x1, x2, f, pad=0)[0]
    b = match_descriptors(d, d, x1, x2, g, pad=0)[0]
    assert np.array_equal(a, b) and len(a) == len(x1)
    gm = guided_matches(d, d, x1, x2, f, cross_check=True, pad=0)
    assert gm.keep().sum() == len(x1)


@pytest.mark.parametrize("F, message", [
    (np.eye(3), "rank 2"), (np.zeros((3, 3)), "rank 2"), (np.diag([1.0, 0, 0]), "rank 2"),
    (np.full((3, 3), np.nan), "finite"), (np.eye(2), r"shape \(3, 3\)"),
])
def test_bad_fundamental_matrices(F, message):
    with pytest.raises(ValueError, match=message):
        FundamentalGeometry(F, **SIZE)


def test_uncalibrated_limits():
    g = TwoViewGeometry(K, K, np.eye(3), [0, 0, 1], **SIZE)
    f = FundamentalGeometry(g.fundamental_matrix, **SIZE)  # no points: the reverse orientation is unknown
    with pytest.raises(ValueError, match="reverse orientation"):
        f.inverse()
    with pytest.raises(ValueError, match="no metric depth"):
        f.segments([[1.0, 2.0]], depth_range=(1.0, 5.0))
    with pytest.raises(ValueError, match="no metric depth"):
        match_descriptors(np.eye(2, 4, dtype=np.float32), np.eye(2, 4, dtype=np.float32), [[1.0, 2.0], [3, 4]],
                          [[1.0, 2.0], [3, 4]], f, search=SearchConfig(depth_range=(1, 2)))
    with pytest.raises(ValueError, match="reverse_sign"):
        FundamentalGeometry(g.fundamental_matrix, reverse_sign=2, **SIZE)
    assert not hasattr(f, "with_covariance")  # no pose to perturb
    assert "FundamentalGeometry(epipole=" in repr(f)
