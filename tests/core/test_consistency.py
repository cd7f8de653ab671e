"""Local consistency: matches against the affine map of their nearest anchors (matching/consistency.py)."""

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from episeg_cv import consistent_pairs, scenes
from episeg_cv.matching.consistency import affine_residuals


def _jittered_grid(n=12, step=20.0, seed=0):
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(np.arange(n) * step, np.arange(n) * step), -1).reshape(-1, 2)
    return g + rng.uniform(-4, 4, g.shape)


def _identity(n):
    return np.column_stack([np.arange(n), np.arange(n)])


# --------------------------------------------------------------------------------------
# Hand-computed
# --------------------------------------------------------------------------------------
def test_an_affine_flow_is_kept_and_a_displaced_match_is_not():
    """x2 = A x1 + b exactly: every residual is 0. One match sent 12 px off (beyond tol 2 + 0.1 x 24-45 px of
    spacing, the median distance to the 10 nearest on a 20 px grid) is rejected, and only it: its neighbours
    drop it from their fits (deleted residual)."""
    p1 = _jittered_grid()
    A, b = np.array([[1.1, 0.05], [-0.04, 0.95]]), np.array([7.0, -3.0])
    p2 = p1 @ A.T + b
    r, spacing = affine_residuals(p1, p2, np.ones(len(p1), bool), 10, 2.0, 0.1)
    np.testing.assert_allclose(r, 0.0, atol=1e-9)
    assert np.all((spacing > 20) & (spacing < 50))
    p2[70] += [0.0, 12.0]
    ok = consistent_pairs(p1, p2, _identity(len(p1)))
    assert np.flatnonzero(~ok).tolist() == [70]
    # 3 px off stays: within the allowance (noise and a surface that is not a plane)
    p2[70] -= [0.0, 9.0]
    assert consistent_pairs(p1, p2, _identity(len(p1))).all()


def test_tol_and_slack_set_the_allowance():
    p1 = _jittered_grid()
    p2 = p1 + [5.0, 5.0]
    p2[70] += [6.0, 0.0]  # 6 px off
    pairs = _identity(len(p1))
    r, spacing = affine_residuals(p1, p2, np.ones(len(p1), bool), 10, 2.0, 0.1)
    assert r[70] == pytest.approx(6.0)
    assert not consistent_pairs(p1, p2, pairs, tol=2.0, slack=0.0)[70]
    assert consistent_pairs(p1, p2, pairs, tol=6.5, slack=0.0)[70]
    assert consistent_pairs(p1, p2, pairs, tol=0.0, slack=6.5 / spacing[70])[70]


def test_only_anchors_are_neighbours():
    """A block of matches shifted together by 40 px is consistent with itself away from its edges; with the
    other matches as the only anchors it is not (what makes the check work on a wall matched one period off)."""
    p1 = _jittered_grid()
    p2 = p1 + [3.0, 1.0]
    block = (p1[:, 0] < 90) & (p1[:, 1] < 90)
    p2[block] += [40.0, 0.0]
    pairs = _identity(len(p1))
    assert consistent_pairs(p1, p2, pairs)[block & (p1[:, 0] < 40) & (p1[:, 1] < 40)].all()  # its corner survives
    ok = consistent_pairs(p1, p2, pairs, anchors=~block)
    assert not ok[block].any() and ok[~block].all()


def test_the_second_check_is_anchored_on_what_the_first_kept():
    """A curved flow (x2 = x1 + 0.004 (x - 200)^2 along x), every match right, anchors on a sparse 80 px grid:
    the affine map over far anchors misses the curve, and the first check keeps about a third. The second,
    anchored on those, keeps most; with every match an anchor, all pass."""
    rng = np.random.default_rng(0)
    p1 = np.stack(np.meshgrid(np.arange(0, 400, 10.0), np.arange(0, 400, 10.0)), -1).reshape(-1, 2)
    p1 += rng.uniform(-2, 2, p1.shape)
    p2 = p1.copy()
    p2[:, 0] += 0.004 * (p1[:, 0] - 200) ** 2
    pairs = _identity(len(p1))
    sparse = (np.round(p1[:, 0] / 10) % 8 == 0) & (np.round(p1[:, 1] / 10) % 8 == 0)
    r, spacing = affine_residuals(p1, p2, sparse, 10, 2.0, 0.1)
    first = (r <= 2.0 + 0.1 * spacing).mean()
    assert first < 0.5
    assert consistent_pairs(p1, p2, pairs, anchors=sparse).mean() > first + 0.3
    assert consistent_pairs(p1, p2, pairs).all()


# --------------------------------------------------------------------------------------
# cv2 reference
# --------------------------------------------------------------------------------------
def test_prediction_is_the_least_squares_affine_of_the_nearest_anchors():
    """Without a rejected anchor, the prediction is cv2.solve's least-squares affine map (DECOMP_SVD) of the
    k nearest other matches, applied to the query."""
    rng = np.random.default_rng(3)
    p1 = rng.uniform(0, 300, (80, 2))
    p2 = p1 @ np.array([[0.9, 0.1], [-0.1, 1.05]]).T + 20 + rng.normal(0, 0.3, p1.shape)
    k = 10
    r, _ = affine_residuals(p1, p2, np.ones(80, bool), k, 1e9, 0.0)  # nothing is ever rejected
    for q in (0, 17, 55):
        d = np.linalg.norm(p1 - p1[q], axis=1)
        d[q] = np.inf
        nb = np.argsort(d)[:k]
        A = np.column_stack([p1[nb], np.ones(k)]).astype(np.float64)
        ok, M = cv2.solve(A, p2[nb].astype(np.float64), flags=cv2.DECOMP_SVD)
        assert ok
        pred = np.append(p1[q], 1.0) @ M
        assert r[q] == pytest.approx(np.linalg.norm(pred - p2[q]), abs=1e-6)


# --------------------------------------------------------------------------------------
# Synthetic scene
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def forward_bf():
    """BFMatcher + ratio 0.9 on a rendered forward pair: many wrong matches to reject."""
    p = scenes.make_pair("forward", image_size=(480, 360))
    sift = cv2.SIFT_create(nfeatures=2000, contrastThreshold=0.02)
    (k1, d1), (k2, d2) = (sift.detectAndCompute(im, None) for im in (p.image1, p.image2))
    p1, p2 = (np.array([k.pt for k in kk], dtype=np.float64) for kk in (k1, k2))
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    pairs = np.array([[m[0].queryIdx, m[0].trainIdx] for m in knn if m[0].distance < 0.9 * m[1].distance])
    gt = p.ground_truth(p1, p2)
    known = np.all(np.isfinite(gt.projected), axis=1)[pairs[:, 0]]
    strict = np.array([m[0].distance < 0.7 * m[1].distance for m in knn
                       if m[0].distance < 0.9 * m[1].distance])
    return p1, p2, pairs[known], gt.is_correct(pairs[known]), strict[known]


def test_on_a_rendered_pair_it_removes_wrong_matches_and_keeps_correct_ones(forward_bf):
    """Anchors: the matches that also pass ratio 0.7 (mostly right). With every match as an anchor, a fifth of
    them wrong, the fits are spoiled and a third of the correct matches go (measured; not asserted)."""
    p1, p2, pairs, correct, strict = forward_bf
    assert correct.mean() < 0.9 and correct.sum() > 300 and correct[strict].mean() > 0.95
    ok = consistent_pairs(p1, p2, pairs, anchors=strict)
    assert ok[correct].mean() > 0.9                     # keeps the correct matches
    assert (~ok[~correct]).mean() > 0.6                 # removes most wrong ones
    assert correct[ok].mean() > correct.mean() + 0.05


# --------------------------------------------------------------------------------------
# Properties
# --------------------------------------------------------------------------------------
@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), shift1=st.tuples(st.floats(-500, 500), st.floats(-500, 500)),
       shift2=st.tuples(st.floats(-500, 500), st.floats(-500, 500)))
def test_translations_and_the_order_of_matches_do_not_matter(seed, shift1, shift2):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(15, 120))
    p1 = rng.uniform(0, 400, (n, 2))
    p2 = p1 * rng.uniform(0.8, 1.2) + rng.normal(0, 1.0, (n, 2))
    wrong = rng.random(n) < 0.2
    p2[wrong] += rng.uniform(-60, 60, (int(wrong.sum()), 2))
    pairs = _identity(n)
    anchors = rng.random(n) < 0.7
    ok = consistent_pairs(p1, p2, pairs, anchors=anchors)
    moved = consistent_pairs(p1 + shift1, p2 + shift2, pairs, anchors=anchors)
    assert np.array_equal(ok, moved)
    order = rng.permutation(n)
    np.testing.assert_array_equal(consistent_pairs(p1, p2, pairs[order], anchors=anchors[order]), ok[order])


# --------------------------------------------------------------------------------------
# Edge cases and bad input
# --------------------------------------------------------------------------------------
def test_edge_cases():
    p = _jittered_grid(4)
    empty = consistent_pairs(p, p, np.zeros((0, 2), np.intp))
    assert empty.shape == (0,) and empty.dtype == bool
    # fewer than four anchors in all: nothing can be checked, all kept
    far = p + 100.0 * np.arange(len(p))[:, None]
    assert consistent_pairs(p, far, _identity(len(p)), anchors=np.arange(len(p)) < 3).all()
    assert consistent_pairs(p[:3], far[:3], _identity(3)).all()
    # pairs index into the keypoints: unused keypoints do not matter
    pairs = np.array([[i, len(p) - 1 - i] for i in range(len(p))])
    assert consistent_pairs(p, p[::-1], pairs).all()


@pytest.mark.parametrize("kwargs, error, message", [
    ({"points1": np.zeros((5, 3))}, ValueError, "points1 must have shape"),
    ({"points2": np.full((16, 2), np.nan)}, ValueError, "points2 must be finite"),
    ({"pairs": np.array([[0, 99]])}, ValueError, "out of range for points2"),
    ({"pairs": np.zeros((3, 2))}, ValueError, "pairs must be a"),
    ({"anchors": np.ones(3, bool)}, ValueError, "anchors must have shape"),
    ({"anchors": np.ones(16)}, TypeError, "anchors must be a boolean array"),
    ({"k": 2}, ValueError, "k must be at least 3"),
    ({"k": 4.0}, TypeError, "k must be a positive integer"),
    ({"tol": -1.0}, ValueError, "tol must be a finite number >= 0"),
    ({"slack": float("inf")}, ValueError, "slack must be a finite number >= 0"),
])
def test_bad_input(kwargs, error, message):
    p = _jittered_grid(4)
    args = {"points1": p, "points2": p, "pairs": _identity(16), **kwargs}
    with pytest.raises(error, match=message):
        consistent_pairs(args.pop("points1"), args.pop("points2"), args.pop("pairs"), **args)
