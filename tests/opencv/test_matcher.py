"""SegmentMatcher (the cv2.BFMatcher drop-in) and the array API of episeg_cv.matching.

References:
- ``constraint="none"`` against ``cv2.BFMatcher`` itself (must be identical);
- guided ``knnMatch``/``radiusMatch`` against ``cv2.BFMatcher.knnMatch(d1, d2, k, mask=M)``
  and ``radiusMatch(..., mask=M)``, with the dense mask ``M`` built from the
  definition: ``EpipolarSegments.distance`` (or ``line_distance``) ``<= tol``;
- synthetic pairs with known geometry for the planted wrong-segment matches.
"""

import functools

import cv2
import numpy as np
import pytest

from episeg_cv import (CandidateIndex, Rejection, SegmentMatcher, TwoViewGeometry, explain_pairs, filter_pairs,
                       knn_descriptors, match_descriptors, radius_descriptors)
from episeg_cv.datasets import load_default_pair
from episeg_cv.scenes import make_pair

#: One relative tolerance on descriptor distances per descriptor dtype (Hamming is exact).
DIST_RTOL = {np.dtype(np.float32): 1e-4, np.dtype(np.uint8): 0.0}

NORM_NAMES = {cv2.NORM_L2: "l2", cv2.NORM_L1: "l1", cv2.NORM_HAMMING: "hamming"}


# ---------------------------------------------------------------------------------
# fixtures
# ---------------------------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def default_pair():
    return load_default_pair()


def _akaze():
    if hasattr(cv2, "AKAZE_create"):
        return cv2.AKAZE_create()
    return cv2.xfeatures2d.AKAZE_create()  # opencv-contrib 5.x moved it


DETECTORS = {
    "sift": lambda: cv2.SIFT_create(500),
    "orb": lambda: cv2.ORB_create(500),
    "akaze": _akaze,  # binary MLDB descriptors
}


@functools.lru_cache(maxsize=None)
def features(name, n_max=500):
    """Keypoints and descriptors of both images of the default pair, at most ``n_max`` per image."""
    pair = default_pair()
    det = DETECTORS[name]()
    out = []
    for img in (pair.image1, pair.image2):
        kp, des = det.detectAndCompute(img, None)
        if len(kp) > n_max:  # keep the strongest
            order = np.argsort([-k.response for k in kp], kind="stable")[:n_max]
            kp, des = [kp[i] for i in order], des[order]
        out += [list(kp), des]
    kp1, d1, kp2, d2 = out
    return kp1, d1, kp2, d2, pts(kp1), pts(kp2)


def pts(kps):
    return np.array([k.pt for k in kps], dtype=np.float64).reshape(-1, 2)


@functools.lru_cache(maxsize=None)
def dense_mask(name, constraint, tol, depth_range=(0.0, np.inf)):
    """(N1, N2) uint8 mask of the candidates, from the definition (all pairs)."""
    kp1, d1, kp2, d2, p1, p2 = features(name)
    g = default_pair().geometry
    seg = g.segments(p1, depth_range, margin=tol)
    ii, jj = np.meshgrid(np.arange(len(p1)), np.arange(len(p2)), indexing="ij")
    sub = seg.take(ii.ravel())
    y = p2[jj.ravel()]
    d = sub.distance(y) if constraint == "segment" else sub.line_distance(y)
    return (d <= tol).reshape(len(p1), len(p2)).astype(np.uint8)


def cv2_distance(d1, d2, i, j, norm):
    return cv2.norm(d1[i], d2[j], norm)


def rows(matches):
    return [[(m.queryIdx, m.trainIdx, m.distance) for m in row] for row in matches]


def assert_same_dmatches(got, ref):
    """Exactly the same matches: queryIdx, trainIdx and distance."""
    got, ref = list(got), list(ref)
    assert len(got) == len(ref)
    for a, b in zip(got, ref):
        if isinstance(b, (list, tuple)):
            assert isinstance(a, list)
            assert_same_dmatches(a, b)
        else:
            assert isinstance(a, cv2.DMatch)
            assert (a.queryIdx, a.trainIdx, a.distance) == (b.queryIdx, b.trainIdx, b.distance)


def assert_knn_like_reference(got, ref, d1, d2, norm, mask):
    """Per query: the same neighbours and distances as the reference, up to swaps among ties."""
    rtol = DIST_RTOL[d1.dtype]
    assert isinstance(got, list) and len(got) == len(ref)
    for i, (g_row, r_row) in enumerate(zip(got, ref)):
        assert isinstance(g_row, list)
        assert len(g_row) == len(r_row), f"query {i}: {len(g_row)} neighbours, reference {len(r_row)}"
        g_j = [m.trainIdx for m in g_row]
        assert len(set(g_j)) == len(g_j)
        assert all(m.queryIdx == i and m.imgIdx == 0 for m in g_row)
        assert all(mask[i, j] for j in g_j), f"query {i}: a neighbour off its segment"
        g_d = np.array([m.distance for m in g_row])
        r_d = np.array([m.distance for m in r_row])
        # distances: as cv2 reports them, in the reference's order
        np.testing.assert_allclose(g_d, r_d, rtol=rtol, atol=1e-6)
        cv = np.array([cv2_distance(d1, d2, i, j, norm) for j in g_j])
        np.testing.assert_allclose(g_d, cv, rtol=rtol, atol=1e-6)
        # indices: equal, or a different neighbour at the same distance (a tie)
        for pos, (a, b) in enumerate(zip(g_row, r_row)):
            if a.trainIdx != b.trainIdx:
                assert abs(a.distance - b.distance) <= rtol * max(b.distance, 1.0) + 1e-6, \
                    f"query {i}, rank {pos}: train {a.trainIdx} ({a.distance}) vs {b.trainIdx} ({b.distance})"


def geometry_100():
    """The hand-checkable geometry of the docstrings: the segment of (x, y) is the row y, left of x."""
    K = [[100, 0, 50], [0, 100, 50], [0, 0, 1]]
    return TwoViewGeometry(K, K, np.eye(3), [-1, 0, 0], image_size1=(100, 100), image_size2=(100, 100))


def facing_away():
    """Camera 2 looks the other way: every segment is empty."""
    K = [[100, 0, 50], [0, 100, 50], [0, 0, 1]]
    R = cv2.Rodrigues(np.array([[0.0], [np.pi], [0.0]]))[0]
    return TwoViewGeometry(K, K, R, [0, 0, -2.0], image_size1=(100, 100), image_size2=(100, 100))


# ---------------------------------------------------------------------------------
# constraint="none" is cv2.BFMatcher
# ---------------------------------------------------------------------------------
@pytest.mark.parametrize("name, norm, radius", [("sift", cv2.NORM_L2, 250.0), ("sift", cv2.NORM_L1, 2500.0),
                                                ("orb", cv2.NORM_HAMMING, 60.0)])
@pytest.mark.parametrize("as_keypoints", [True, False])
def test_none_equals_bfmatcher(name, norm, radius, as_keypoints):
    kp1, d1, kp2, d2, p1, p2 = features(name)
    q, t = (kp1, kp2) if as_keypoints else (p1, p2)
    g = default_pair().geometry
    m = SegmentMatcher(g, norm, constraint="none")
    bf = cv2.BFMatcher(norm)
    # reference: cv2.BFMatcher(norm).match(d1, d2), .knnMatch(d1, d2, k=2), .radiusMatch(d1, d2, radius)
    assert_same_dmatches(m.match(d1, d2, q, t), bf.match(d1, d2))
    assert_same_dmatches(m.knnMatch(d1, d2, q, t, 2), bf.knnMatch(d1, d2, k=2))
    assert_same_dmatches(m.knnMatch(d1, d2, q, t, k=7), bf.knnMatch(d1, d2, k=7))
    assert_same_dmatches(m.radiusMatch(d1, d2, q, t, radius), bf.radiusMatch(d1, d2, radius))
    assert sum(len(r) for r in m.radiusMatch(d1, d2, q, t, radius)) > 0


@pytest.mark.parametrize("name, norm", [("sift", cv2.NORM_L2), ("orb", cv2.NORM_HAMMING)])
def test_none_crosscheck_equals_bfmatcher(name, norm):
    kp1, d1, kp2, d2, p1, p2 = features(name)
    m = SegmentMatcher(default_pair().geometry, norm, True, constraint="none")
    bf = cv2.BFMatcher(norm, crossCheck=True)
    ref = bf.match(d1, d2)  # cv2.BFMatcher(norm, crossCheck=True).match(d1, d2)
    assert 0 < len(ref) < len(d1)
    assert_same_dmatches(m.match(d1, d2, kp1, kp2), ref)
    assert_same_dmatches(m.knnMatch(d1, d2, kp1, kp2, 1), bf.knnMatch(d1, d2, k=1))


# ---------------------------------------------------------------------------------
# guided knnMatch / radiusMatch against cv2.BFMatcher with the dense mask
# ---------------------------------------------------------------------------------
GUIDED_CASES = [("sift", cv2.NORM_L2), ("sift", cv2.NORM_L1), ("orb", cv2.NORM_HAMMING), ("akaze", cv2.NORM_HAMMING)]


@pytest.mark.parametrize("name, norm", GUIDED_CASES)
@pytest.mark.parametrize("constraint", ["segment", "line"])
def test_knn_equals_masked_bfmatcher(name, norm, constraint):
    kp1, d1, kp2, d2, p1, p2 = features(name)
    mask = dense_mask(name, constraint, 2.0)
    m = SegmentMatcher(default_pair().geometry, norm, tol=2.0, constraint=constraint)
    for k in (1, 3):
        got = m.knnMatch(d1, d2, kp1, kp2, k)
        ref = cv2.BFMatcher(norm).knnMatch(d1, d2, k=k, mask=mask)  # masked brute force
        assert_knn_like_reference(got, ref, d1, d2, norm, mask)
    # the array API gives the same neighbours
    res = knn_descriptors(d1, d2, p1, p2, default_pair().geometry, k=3, norm=NORM_NAMES[norm], constraint=constraint)
    assert res.indices.shape == (len(d1), 3) and res.indices.dtype == np.intp
    np.testing.assert_array_equal(res.counts, mask.sum(1))
    got_idx = [[x.trainIdx for x in row] for row in got]
    assert [list(r[r >= 0]) for r in res.indices] == got_idx
    # ... with the distances cv2 reports (Neighbors holds real distances, not kernel scores)
    got_dist = [[x.distance for x in row] for row in got]
    assert [list(d[r >= 0]) for d, r in zip(res.distances, res.indices)] == got_dist


@pytest.mark.parametrize("depth_range", [(1.0, 4.0), (0.0, 1.5)])
def test_knn_with_depth_range(depth_range):
    kp1, d1, kp2, d2, p1, p2 = features("sift")
    mask = dense_mask("sift", "segment", 3.0, depth_range)
    full = dense_mask("sift", "segment", 3.0)
    assert mask.sum() < full.sum()
    m = SegmentMatcher(default_pair().geometry, cv2.NORM_L2, tol=3.0, depth_range=depth_range)
    ref = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2, mask=mask)
    assert_knn_like_reference(m.knnMatch(d1, d2, kp1, kp2, 2), ref, d1, d2, cv2.NORM_L2, mask)


def test_knn_with_per_point_depth_range():
    kp1, d1, kp2, d2, p1, p2 = features("sift")
    g = default_pair().geometry
    rng = np.random.default_rng(2)
    zmin = rng.uniform(0.0, 3.0, len(p1))
    dr = (zmin, zmin + rng.uniform(0.2, 3.0, len(p1)))
    seg = g.segments(p1, dr, margin=2.0)
    ii, jj = np.meshgrid(np.arange(len(p1)), np.arange(len(p2)), indexing="ij")
    mask = (seg.take(ii.ravel()).distance(p2[jj.ravel()]) <= 2.0).reshape(len(p1), len(p2)).astype(np.uint8)
    m = SegmentMatcher(g, cv2.NORM_L2, depth_range=dr)
    ref = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2, mask=mask)
    assert_knn_like_reference(m.knnMatch(d1, d2, kp1, kp2, 2), ref, d1, d2, cv2.NORM_L2, mask)
    keep = m.filter([cv2.DMatch(i, j, 0, 0.0) for i, j in zip(ii.ravel()[::97], jj.ravel()[::97])], kp1, kp2)
    assert {(x.queryIdx, x.trainIdx) for x in keep} == {(i, j) for i, j in zip(ii.ravel()[::97], jj.ravel()[::97])
                                                       if mask[i, j]}
    with pytest.raises(ValueError, match="depth_range"):
        SegmentMatcher(g, depth_range=(zmin[:5], zmin[:5] + 1)).knnMatch(d1, d2, kp1, kp2, 2)
    with pytest.raises(ValueError, match="depth_range"):
        SegmentMatcher(g, depth_range=(2.0, 1.0))


@pytest.mark.parametrize("name, norm, radius", [("sift", cv2.NORM_L2, 300.0), ("sift", cv2.NORM_L1, 3000.0),
                                                ("orb", cv2.NORM_HAMMING, 70.0), ("akaze", cv2.NORM_HAMMING, 120.0)])
@pytest.mark.parametrize("constraint", ["segment", "line"])
def test_radius_equals_masked_bfmatcher(name, norm, radius, constraint):
    kp1, d1, kp2, d2, p1, p2 = features(name)
    mask = dense_mask(name, constraint, 2.0)
    m = SegmentMatcher(default_pair().geometry, norm, tol=2.0, constraint=constraint)
    got = m.radiusMatch(d1, d2, kp1, kp2, radius)
    ref = cv2.BFMatcher(norm).radiusMatch(d1, d2, radius, mask=mask)  # masked brute force
    rtol = DIST_RTOL[d1.dtype]
    assert isinstance(got, list) and len(got) == len(ref)
    assert sum(len(r) for r in ref) > 0
    for i, (g_row, r_row) in enumerate(zip(got, ref)):
        g_map = {x.trainIdx: x.distance for x in g_row}
        r_map = {x.trainIdx: x.distance for x in r_row}
        assert len(g_map) == len(g_row)
        assert all(x.queryIdx == i for x in g_row)
        # pairs on the radius boundary may go either way
        sym = set(g_map) ^ set(r_map)
        for j in sym:
            dj = g_map.get(j, r_map.get(j))
            assert abs(dj - radius) <= rtol * radius + 1e-6, f"query {i}: train {j} at {dj} vs radius {radius}"
        for j in set(g_map) & set(r_map):
            np.testing.assert_allclose(g_map[j], r_map[j], rtol=rtol, atol=1e-6)
        g_d = [x.distance for x in g_row]
        assert g_d == sorted(g_d), "radiusMatch rows are nearest first"
        assert all(x.distance <= radius for x in g_row)


def test_radius_array_api_matches_the_matcher():
    kp1, d1, kp2, d2, p1, p2 = features("orb")
    g = default_pair().geometry
    pairs, dist = radius_descriptors(d1, d2, p1, p2, g, max_distance=70.0, norm="hamming")
    assert pairs.dtype == np.intp and pairs.shape == (len(dist), 2) and dist.dtype == np.float32
    rows_ = SegmentMatcher(g, cv2.NORM_HAMMING).radiusMatch(d1, d2, kp1, kp2, 70.0)
    flat = [(m.queryIdx, m.trainIdx) for row in rows_ for m in row]
    assert sorted(map(tuple, pairs.tolist())) == sorted(flat)


# ---------------------------------------------------------------------------------
# the acceptance rule of match(), against a dense reference (pad = 0)
# ---------------------------------------------------------------------------------
def dense_l2(d1, d2):
    a, b = d1.astype(np.float64), d2.astype(np.float64)
    return np.sqrt(np.maximum((a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2 * a @ b.T, 0))


def reference_match(D, mask, ratio, mutual, rtol=1e-4):
    """The documented rule on a dense masked distance matrix: (accepted set, ambiguous queries)."""
    Dm = np.where(mask.astype(bool), D, np.inf)
    accepted, ambiguous = set(), set()
    col_order = np.sort(Dm, axis=0)
    for i in range(len(Dm)):
        row = np.sort(Dm[i])
        if not np.isfinite(row[0]):
            continue
        j = int(np.argmin(Dm[i]))
        d1 = row[0]
        d2 = row[1] if len(row) > 1 else np.inf
        tie = np.isclose(d1, d2, rtol=rtol)
        if ratio < 1 and np.isfinite(d2):
            tie |= abs(d1 - ratio * d2) <= rtol * d2
        ok = d1 < ratio * d2
        if mutual:
            c = col_order[:, j]
            tie |= len(c) > 1 and np.isclose(c[0], c[1], rtol=rtol)
            ok &= int(np.argmin(Dm[:, j])) == i
        if tie:
            ambiguous.add(i)
        elif ok:
            accepted.add((i, j))
    return accepted, ambiguous


@pytest.mark.parametrize("constraint", ["segment", "line"])
@pytest.mark.parametrize("ratio, mutual", [(1.0, True), (0.8, True), (0.8, False), (1.0, False)])
def test_match_rule_against_dense_reference(constraint, ratio, mutual):
    kp1, d1, kp2, d2, p1, p2 = features("sift")
    mask = dense_mask("sift", constraint, 2.0)
    m = SegmentMatcher(default_pair().geometry, cv2.NORM_L2, constraint=constraint, ratio=ratio, mutual=mutual, pad=0)
    got = {(x.queryIdx, x.trainIdx) for x in m.match(d1, d2, kp1, kp2)}
    ref, ambiguous = reference_match(dense_l2(d1, d2), mask, ratio, mutual)
    assert len(ambiguous) < 0.05 * len(d1)
    strip = lambda s: {p for p in s if p[0] not in ambiguous}  # noqa: E731
    assert strip(got) == strip(ref)


def test_padding_only_removes_matches():
    kp1, d1, kp2, d2, p1, p2 = features("sift")
    g = default_pair().geometry
    base = {tuple(p) for p in match_descriptors(d1, d2, p1, p2, g, pad=0)[0].tolist()}
    for pad in (8, 64):
        padded = {tuple(p) for p in match_descriptors(d1, d2, p1, p2, g, pad=pad)[0].tolist()}
        assert padded <= base
    # and a fixed default rng: the result repeats
    a = match_descriptors(d1, d2, p1, p2, g)
    b = match_descriptors(d1, d2, p1, p2, g)
    np.testing.assert_array_equal(a[0], b[0])


# ---------------------------------------------------------------------------------
# invariants: subsets, symmetry
# ---------------------------------------------------------------------------------
@pytest.mark.parametrize("name, norm", [("sift", cv2.NORM_L2), ("orb", cv2.NORM_HAMMING)])
@pytest.mark.parametrize("constraint", ["segment", "line"])
def test_guided_results_are_candidates(name, norm, constraint):
    kp1, d1, kp2, d2, p1, p2 = features(name)
    g = default_pair().geometry
    cand = {tuple(p) for p in CandidateIndex(g, p1, p2, tol=2.0, constraint=constraint).pairs().tolist()}
    m = SegmentMatcher(g, norm, constraint=constraint)
    knn = m.knnMatch(d1, d2, kp1, kp2, 4)
    assert {(x.queryIdx, x.trainIdx) for row in knn for x in row} <= cand
    radius = m.radiusMatch(d1, d2, kp1, kp2, 1e9)
    assert {(x.queryIdx, x.trainIdx) for row in radius for x in row} == cand  # every candidate is within 1e9
    matched = m.match(d1, d2, kp1, kp2)
    assert len(matched) > 0
    assert {(x.queryIdx, x.trainIdx) for x in matched} <= cand
    # match() returns nearest neighbours only: a subset of knnMatch(k=1)
    firsts = {(row[0].queryIdx, row[0].trainIdx) for row in m.knnMatch(d1, d2, kp1, kp2, 1) if row}
    assert {(x.queryIdx, x.trainIdx) for x in matched} <= firsts
    assert len({x.queryIdx for x in matched}) == len(matched)  # one match at most per query
    # the segment is a subset of the line: fewer candidates
    if constraint == "segment":
        line = {tuple(p) for p in CandidateIndex(g, p1, p2, tol=2.0, constraint="line").pairs().tolist()}
        assert cand < line


@pytest.mark.parametrize("name, norm", [("sift", cv2.NORM_L2), ("orb", cv2.NORM_HAMMING)])
@pytest.mark.parametrize("constraint", ["segment", "line"])
def test_crosscheck_is_symmetric(name, norm, constraint):
    """crossCheck: mutual nearest neighbours, each direction under its own constraint, so
    swapping the views (and using geometry.inverse()) gives the same pairs reversed."""
    kp1, d1, kp2, d2, p1, p2 = features(name)
    g = default_pair().geometry
    fwd = SegmentMatcher(g, norm, True, constraint=constraint, ratio=1.0).match(d1, d2, kp1, kp2)
    bwd = SegmentMatcher(g.inverse(), norm, True, constraint=constraint, ratio=1.0).match(d2, d1, kp2, kp1)
    a = {(x.queryIdx, x.trainIdx) for x in fwd}
    b = {(x.trainIdx, x.queryIdx) for x in bwd}
    assert len(a) > 0
    if norm == cv2.NORM_HAMMING:  # integer distances tie often: allow the tied queries to differ
        assert len(a ^ b) <= 0.02 * len(a)
    else:
        assert a == b
    # and each is a mutual nearest neighbour under the two constraints (dense reference, SIFT only)
    if norm == cv2.NORM_L2:
        D = dense_l2(d1, d2)
        fwd_mask = dense_mask(name, constraint, 2.0).astype(bool)
        seg_back = g.inverse().segments(p2, margin=2.0)
        ii, jj = np.meshgrid(np.arange(len(p2)), np.arange(len(p1)), indexing="ij")
        sub, y = seg_back.take(ii.ravel()), p1[jj.ravel()]
        dback = sub.distance(y) if constraint == "segment" else sub.line_distance(y)
        back_mask = (dback <= 2.0).reshape(len(p2), len(p1))
        Df = np.where(fwd_mask, D, np.inf)
        Db = np.where(back_mask, D.T, np.inf)
        ref = {(i, int(np.argmin(Df[i]))) for i in range(len(D)) if np.isfinite(Df[i]).any()}
        ref = {(i, j) for i, j in ref if np.isfinite(Db[j]).any() and int(np.argmin(Db[j])) == i}
        assert a == ref
        # knnMatch(k=1) with crossCheck gives the same pairs, one list per query
        knn = SegmentMatcher(g, norm, True, constraint=constraint).knnMatch(d1, d2, kp1, kp2, 1)
        assert len(knn) == len(d1) and all(len(r) <= 1 for r in knn)
        assert {(r[0].queryIdx, r[0].trainIdx) for r in knn if r} == a


def test_crosscheck_is_a_subset_of_plain_nearest():
    kp1, d1, kp2, d2, p1, p2 = features("sift")
    g = default_pair().geometry
    cc = SegmentMatcher(g, cv2.NORM_L2, True, ratio=1.0).match(d1, d2, kp1, kp2)
    firsts = {(r[0].queryIdx, r[0].trainIdx) for r in SegmentMatcher(g).knnMatch(d1, d2, kp1, kp2, 1) if r}
    assert {(x.queryIdx, x.trainIdx) for x in cc} <= firsts


def test_keypoints_and_arrays_give_the_same_result():
    kp1, d1, kp2, d2, p1, p2 = features("sift")
    m = SegmentMatcher(default_pair().geometry)
    assert_same_dmatches(m.match(d1, d2, kp1, kp2), m.match(d1, d2, p1, p2))
    assert_same_dmatches(m.knnMatch(d1, d2, kp1, kp2, 2), m.knnMatch(d1, d2, p1, p2, 2))
    assert_same_dmatches(m.knnMatch(d1, d2, tuple(kp1), tuple(kp2), 2), m.knnMatch(d1, d2, p1, p2, 2))


# ---------------------------------------------------------------------------------
# short knn lists, binary descriptors
# ---------------------------------------------------------------------------------
def small_problem():
    g = geometry_100()
    kp1 = [cv2.KeyPoint(60, 20, 5), cv2.KeyPoint(60, 70, 5), cv2.KeyPoint(60, 90, 5)]
    # query 0: one candidate (40, 20); (80, 20) is on the line beyond p_inf
    # query 1: two candidates (30, 70), (10, 70.5); query 2: none
    kp2 = [cv2.KeyPoint(40, 20, 5), cv2.KeyPoint(80, 20, 5), cv2.KeyPoint(30, 70, 5), cv2.KeyPoint(10, 70.5, 5),
           cv2.KeyPoint(50, 5, 5)]
    rng = np.random.default_rng(0)
    d1 = rng.random((3, 32)).astype(np.float32)
    d2 = rng.random((5, 32)).astype(np.float32)
    return g, kp1, kp2, d1, d2


@pytest.mark.parametrize("k", [1, 2, 3, 10])
def test_knn_lists_shorter_than_k(k):
    g, kp1, kp2, d1, d2 = small_problem()
    seg = SegmentMatcher(g).knnMatch(d1, d2, kp1, kp2, k)
    assert [len(r) for r in seg] == [min(k, 1), min(k, 2), 0]
    assert [x.trainIdx for x in seg[0]] == [0]
    assert {x.trainIdx for x in seg[1]} <= {2, 3}
    line = SegmentMatcher(g, constraint="line").knnMatch(d1, d2, kp1, kp2, k)
    assert [len(r) for r in line] == [min(k, 2), min(k, 2), 0]
    radius = SegmentMatcher(g).radiusMatch(d1, d2, kp1, kp2, 1e6)
    assert [len(r) for r in radius] == [1, 2, 0]
    res = knn_descriptors(d1, d2, pts(kp1), pts(kp2), g, k=k)
    assert res.indices.shape == (3, min(k, 2))  # no more columns than the largest candidate count
    assert (res.indices[2] == -1).all() and np.isinf(res.distances[2]).all()
    np.testing.assert_array_equal(res.counts, [1, 2, 0])


def test_knn_lists_leave_the_garbage_collector_as_they_found_it():
    """The per-query lists are made with the cyclic collector paused: it must come back on, and stay off
    when the program had turned it off."""
    import gc

    g, kp1, kp2, d1, d2 = small_problem()
    matcher = SegmentMatcher(g)
    assert gc.isenabled()
    first = matcher.knnMatch(d1, d2, kp1, kp2, 2)
    assert gc.isenabled()
    gc.disable()
    try:
        assert [[(m.queryIdx, m.trainIdx) for m in r] for r in matcher.knnMatch(d1, d2, kp1, kp2, 2)] == \
            [[(m.queryIdx, m.trainIdx) for m in r] for r in first]
        assert not gc.isenabled()
    finally:
        gc.enable()


def test_huge_k_costs_no_memory():
    """knnMatch(k=10**9) must not allocate N1 x k: the lists are as long as the candidates."""
    g, kp1, kp2, d1, d2 = small_problem()
    got = SegmentMatcher(g).knnMatch(d1, d2, kp1, kp2, 10**9)
    assert [len(r) for r in got] == [1, 2, 0]
    assert knn_descriptors(d1, d2, pts(kp1), pts(kp2), g, k=10**9).indices.shape == (3, 2)


def test_lone_candidate_and_padding():
    g, kp1, kp2, d1, d2 = small_problem()
    d1 = d1.copy()
    d1[0] = d2[0] + 0.01  # query 0 really is keypoint 0
    matched = SegmentMatcher(g, pad=0).match(d1, d2, kp1, kp2)
    assert (0, 0) in {(x.queryIdx, x.trainIdx) for x in matched}
    assert all(x.queryIdx != 2 for x in matched)


@pytest.mark.parametrize("name", ["orb", "akaze"])
def test_binary_descriptors_end_to_end(name):
    kp1, d1, kp2, d2, p1, p2 = features(name)
    assert d1.dtype == np.uint8
    g = default_pair().geometry
    m = SegmentMatcher(g, cv2.NORM_HAMMING)
    matched = m.match(d1, d2, kp1, kp2)
    assert len(matched) > 20
    d = np.array([x.distance for x in matched])
    np.testing.assert_array_equal(d, np.round(d))  # bit counts
    np.testing.assert_array_equal(d, [cv2.norm(d1[x.queryIdx], d2[x.trainIdx], cv2.NORM_HAMMING) for x in matched])
    assert len(m.filter(matched, kp1, kp2)) == len(matched)  # guided matches satisfy the constraint
    gt = default_pair().ground_truth(p1, p2)
    pairs = np.array([(x.queryIdx, x.trainIdx) for x in matched])
    assert gt.is_correct(pairs).mean() > 0.8


# ---------------------------------------------------------------------------------
# filter / explain on synthetic pairs with known geometry: planted wrong-segment matches
# ---------------------------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def lateral_pair():
    return make_pair("lateral", image_size=(320, 240))


def planted_problem(pair, n_queries=40, seed=0):
    """Queries with, in image 2: the true point, a point beyond p_inf, one beyond the epipole, one off the line.

    Returns ``p1, p2, matches, expected_label`` with one match per planted point.
    """
    g = pair.geometry_true
    w, h = g.image_size2
    rng = np.random.default_rng(seed)
    inside = lambda p: (p[0] >= 0) & (p[0] <= w - 1) & (p[1] >= 0) & (p[1] <= h - 1)  # noqa: E731
    # true correspondences from the depth map of image 1
    ys, xs = np.nonzero(np.isfinite(pair.depth1))
    sel = rng.choice(len(xs), 4000, replace=False)
    c1 = np.column_stack([xs[sel], ys[sel]]).astype(np.float64)
    z = pair.depth1[ys[sel], xs[sel]]
    c2, z2 = g.transfer(c1, z)
    seg = g.segments(c1)
    p1, p2, matches, labels = [], [], [], []
    for i in range(len(c1)):
        if len(p1) == n_queries:
            break
        if z2[i] <= 0 or not inside(c2[i]) or not seg.valid[i]:
            continue
        s, e = seg.start[i], seg.end[i]
        if np.linalg.norm(e - s) < 1:
            continue
        d = (e - s) / np.linalg.norm(e - s)
        n = np.array([-d[1], d[0]])
        mid = (s + e) / 2
        cand = {Rejection.ON_SEGMENT: c2[i], Rejection.OFF_LINE: c2[i] + 15.0 * n}
        p_inf, epi = seg.infinity_point[i], seg.epipole
        finite_epi = np.all(np.isfinite(epi))
        # beyond p_inf (an end of the segment when it is in the image), short of the epipole
        end_is_inf = np.all(np.isfinite(p_inf)) and min(np.linalg.norm(e - p_inf), np.linalg.norm(s - p_inf)) < 1e-6
        if end_is_inf:
            away = (p_inf - mid) / np.linalg.norm(p_inf - mid)
            step = 12.0
            if finite_epi and np.dot(epi - p_inf, away) > 0:
                step = min(step, np.linalg.norm(epi - p_inf) / 2)
            if step > 4 and inside(p_inf + step * away):
                cand[Rejection.BEYOND_INFINITY] = p_inf + step * away
        # beyond the epipole, on the side away from the segment
        if finite_epi and np.linalg.norm(epi - mid) > 0:
            away = (epi - mid) / np.linalg.norm(epi - mid)
            if inside(epi + 12.0 * away):
                cand[Rejection.BEYOND_EPIPOLE] = epi + 12.0 * away
        if len(cand) < 3:
            continue
        q = len(p1)
        p1.append(c1[i])
        for label, y in cand.items():
            matches.append(cv2.DMatch(q, len(p2), 0, float(len(matches))))
            p2.append(y)
            labels.append(label)
    return np.array(p1), np.array(p2), matches, np.array(labels)


@pytest.mark.parametrize("which", ["default", "lateral"])
def test_planted_wrong_segment_matches(which):
    pair = default_pair() if which == "default" else lateral_pair()
    p1, p2, matches, labels = planted_problem(pair)
    assert len(p1) >= 10
    planted = (labels == Rejection.BEYOND_INFINITY) | (labels == Rejection.BEYOND_EPIPOLE)
    assert planted.sum() >= 10
    if which == "default":  # forward motion: the epipole is in the image
        assert (labels == Rejection.BEYOND_EPIPOLE).sum() >= 5
    g = pair.geometry
    true = labels == Rejection.ON_SEGMENT
    seg = SegmentMatcher(g, tol=1.0).filter(matches, p1, p2)
    line = SegmentMatcher(g, tol=1.0, constraint="line").filter(matches, p1, p2)
    none = SegmentMatcher(g, tol=1.0, constraint="none").filter(matches, p1, p2)
    kept = lambda out: np.array([m in {id(x) for x in out} for m in map(id, matches)])  # noqa: E731
    np.testing.assert_array_equal(kept(seg), true)  # the true ones survive, the planted ones do not
    np.testing.assert_array_equal(kept(line), true | planted)  # the line keeps the planted ones
    assert len(none) == len(matches)
    labels_got, counts = SegmentMatcher(g, tol=1.0).explain(matches, p1, p2)
    np.testing.assert_array_equal(labels_got, labels)
    assert sum(counts.values()) == len(matches)
    assert set(counts) >= set(Rejection.NAMES)
    for code, name in enumerate(Rejection.NAMES):
        assert counts[name] == int((labels == code).sum())
    # the array API says the same
    pairs = np.array([(m.queryIdx, m.trainIdx) for m in matches])
    np.testing.assert_array_equal(filter_pairs(pairs, p1, p2, g, tol=1.0), true)
    np.testing.assert_array_equal(explain_pairs(pairs, p1, p2, g, tol=1.0)[0], labels)


@pytest.mark.parametrize("which", ["default", "lateral"])
def test_true_matches_of_real_keypoints_survive(which):
    pair = default_pair() if which == "default" else lateral_pair()
    sift = cv2.SIFT_create(800)
    kp1, d1 = sift.detectAndCompute(pair.image1, None)
    kp2, d2 = sift.detectAndCompute(pair.image2, None)
    gt = pair.ground_truth(pts(kp1), pts(kp2))
    i = np.flatnonzero(gt.matchable)
    assert len(i) > 50
    true = [cv2.DMatch(int(a), int(gt.match[a]), 0, 0.0) for a in i]
    # a true match is within max_px of the projection, which lies on the segment
    kept = SegmentMatcher(pair.geometry, tol=pair.max_px).filter(true, kp1, kp2)
    assert len(kept) == len(true)
    labels, counts = SegmentMatcher(pair.geometry, tol=pair.max_px).explain(true, kp1, kp2)
    assert counts["on_segment"] == len(true) and (labels == Rejection.ON_SEGMENT).all()
    # and guided matching finds them: most guided matches are correct
    matched = SegmentMatcher(pair.geometry).match(d1, d2, kp1, kp2)
    pairs = np.array([(m.queryIdx, m.trainIdx) for m in matched]).reshape(-1, 2)
    assert len(pairs) > 20 and gt.is_correct(pairs).mean() >= 0.8  # a sanity bound, not the benchmark


def test_filter_equals_the_definition():
    kp1, d1, kp2, d2, p1, p2 = features("sift")
    g = default_pair().geometry
    bf = cv2.BFMatcher(cv2.NORM_L2).match(d1, d2)  # cv2.BFMatcher(cv2.NORM_L2).match(d1, d2)
    pairs = np.array([(m.queryIdx, m.trainIdx) for m in bf])
    seg = g.segments(p1, margin=2.0).take(pairs[:, 0])
    for constraint, d in (("segment", seg.distance(p2[pairs[:, 1]])), ("line", seg.line_distance(p2[pairs[:, 1]]))):
        out = SegmentMatcher(g, constraint=constraint).filter(bf, kp1, kp2)
        assert [(m.queryIdx, m.trainIdx) for m in out] == [tuple(p) for p in pairs[d <= 2.0].tolist()]
    assert 0 < len(SegmentMatcher(g).filter(bf, kp1, kp2)) < len(SegmentMatcher(g, constraint="line").filter(bf, kp1, kp2))


# ---------------------------------------------------------------------------------
# filter keeps the structure
# ---------------------------------------------------------------------------------
def test_filter_keeps_structure():
    kp1, d1, kp2, d2, p1, p2 = features("sift")
    m = SegmentMatcher(default_pair().geometry)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    flat = bf.match(d1, d2)  # a tuple of DMatch, as cv2 returns
    out = m.filter(flat, kp1, kp2)
    assert isinstance(out, list) and all(isinstance(x, cv2.DMatch) for x in out)
    assert 0 < len(out) < len(flat)
    ids = [id(x) for x in flat]
    pos = [ids.index(id(x)) for x in out]
    assert pos == sorted(pos)  # order kept, the same objects
    out_list = m.filter(list(flat), kp1, kp2)
    assert [(x.queryIdx, x.trainIdx) for x in out_list] == [(x.queryIdx, x.trainIdx) for x in out]
    knn = bf.knnMatch(d1, d2, k=2)
    out = m.filter(knn, kp1, kp2)
    assert isinstance(out, list) and len(out) == len(knn)
    assert all(isinstance(r, list) for r in out)
    for r_in, r_out in zip(knn, out):
        assert len(r_out) <= len(r_in)
        assert all(x.queryIdx == r_in[0].queryIdx for x in r_out)
    assert 0 < sum(len(r) for r in out) < 2 * len(knn)
    # a knn output with some empty rows
    rows_ = [list(r) for r in knn[:10]] + [[]] * 3
    out = m.filter(rows_, kp1, kp2)
    assert len(out) == 13 and out[-3:] == [[], [], []]
    # empty in, empty out
    assert m.filter([], kp1, kp2) == []
    assert m.filter((), kp1, kp2) == []
    assert m.filter([[], []], kp1, kp2) == [[], []]
    labels, counts = m.explain([], kp1, kp2)
    assert labels.shape == (0,) and sum(counts.values()) == 0


def test_filter_on_100k_random_pairs():
    kp1, d1, kp2, d2, p1, p2 = features("sift")
    g = default_pair().geometry
    rng = np.random.default_rng(0)
    pairs = np.column_stack([rng.integers(0, len(p1), 100_000), rng.integers(0, len(p2), 100_000)])
    keep = filter_pairs(pairs, p1, p2, g)
    assert keep.shape == (100_000,) and keep.dtype == bool
    seg = g.segments(p1, margin=2.0).take(pairs[:, 0])
    np.testing.assert_array_equal(keep, seg.distance(p2[pairs[:, 1]]) <= 2.0)
    matches = [cv2.DMatch(int(i), int(j), 0, 0.0) for i, j in pairs]
    out = SegmentMatcher(g).filter(matches, kp1, kp2)
    assert len(out) == int(keep.sum())
    labels, counts = explain_pairs(pairs, p1, p2, g)
    assert sum(counts.values()) == 100_000
    np.testing.assert_array_equal(labels == Rejection.ON_SEGMENT, keep)


# ---------------------------------------------------------------------------------
# empty input: correctly typed empty results, never an exception
# ---------------------------------------------------------------------------------
EMPTY_FLOAT = [None, np.zeros((0, 128), np.float32)]


def assert_empty_pairs(pairs, dist):
    assert isinstance(pairs, np.ndarray) and pairs.shape == (0, 2) and pairs.dtype == np.intp
    assert isinstance(dist, np.ndarray) and dist.shape == (0,) and dist.dtype == np.float32


@pytest.mark.parametrize("empty_desc", EMPTY_FLOAT, ids=["None", "0xD"])
@pytest.mark.parametrize("empty_kp", [[], np.zeros((0, 2))], ids=["list", "array"])
@pytest.mark.parametrize("constraint", ["segment", "line", "none"])
@pytest.mark.parametrize("cross_check", [False, True])
def test_empty_keypoint_sets(empty_desc, empty_kp, constraint, cross_check):
    kp1, d1, kp2, d2, p1, p2 = features("sift")
    m = SegmentMatcher(default_pair().geometry, cv2.NORM_L2, cross_check, constraint=constraint)
    # no queries
    assert m.match(empty_desc, d2, empty_kp, kp2) == []
    assert m.knnMatch(empty_desc, d2, empty_kp, kp2, 1) == []
    # no train keypoints
    assert m.match(d1, empty_desc, kp1, empty_kp) == []
    assert m.knnMatch(d1, empty_desc, kp1, empty_kp, 1) == [[] for _ in kp1]
    assert m.filter([], kp1, empty_kp) == []
    if not cross_check:
        assert m.knnMatch(empty_desc, d2, empty_kp, kp2, 2) == []
        assert m.knnMatch(d1, empty_desc, kp1, empty_kp, 2) == [[] for _ in kp1]
        assert m.radiusMatch(empty_desc, d2, empty_kp, kp2, 100.0) == []
        assert m.radiusMatch(d1, empty_desc, kp1, empty_kp, 100.0) == [[] for _ in kp1]
        # both empty
        assert m.match(empty_desc, empty_desc, empty_kp, empty_kp) == []
        assert m.knnMatch(empty_desc, empty_desc, empty_kp, empty_kp, 2) == []


@pytest.mark.parametrize("norm, dtype, width", [("l2", np.float32, 128), ("hamming", np.uint8, 32)])
@pytest.mark.parametrize("empty_desc", ["None", "0xD"])
@pytest.mark.parametrize("side", ["query", "train", "both"])
def test_empty_array_api(norm, dtype, width, empty_desc, side):
    g = geometry_100()
    rng = np.random.default_rng(0)
    full = rng.integers(0, 255, (6, width)).astype(dtype)
    pts_full = rng.uniform(0, 99, (6, 2))
    empty = None if empty_desc == "None" else np.zeros((0, width), dtype)
    d1, p1 = (empty, np.zeros((0, 2))) if side in ("query", "both") else (full, pts_full)
    d2, p2 = (empty, np.zeros((0, 2))) if side in ("train", "both") else (full, pts_full)
    n1 = len(p1)
    for kw in (dict(), dict(cross_check=True), dict(mutual=False, pad=0)):
        assert_empty_pairs(*match_descriptors(d1, d2, p1, p2, g, norm=norm, **kw))
    assert_empty_pairs(*radius_descriptors(d1, d2, p1, p2, g, max_distance=1e9, norm=norm))
    res = knn_descriptors(d1, d2, p1, p2, g, k=2, norm=norm)
    assert res.indices.shape == (n1, 2) and res.indices.dtype == np.intp and (res.indices == -1).all()
    assert res.distances.shape == (n1, 2) and np.isinf(res.distances).all()
    assert res.counts.shape == (n1,) and not res.counts.any()
    keep = filter_pairs(np.zeros((0, 2), np.intp), p1, p2, g)
    assert keep.shape == (0,) and keep.dtype == bool
    labels, counts = explain_pairs(np.zeros((0, 2), np.intp), p1, p2, g)
    assert labels.shape == (0,) and set(counts.values()) == {0}


@pytest.mark.parametrize("empty", [[], ()], ids=["list", "tuple"])
def test_empty_pair_list_is_accepted(empty):
    """An empty list of pairs has no dtype to check: it is the empty result, not an error."""
    g = geometry_100()
    p = np.random.default_rng(0).uniform(0, 99, (4, 2))
    keep = filter_pairs(empty, p, p, g)
    assert keep.shape == (0,) and keep.dtype == bool
    labels, counts = explain_pairs(empty, p, p, g)
    assert labels.shape == (0,) and sum(counts.values()) == 0


@pytest.mark.parametrize("constraint", ["segment", "line"])
def test_empty_segments_give_empty_results(constraint):
    """Camera 2 faces away: every query's segment (and, with `line`, every candidate set) is empty."""
    g = facing_away()
    rng = np.random.default_rng(1)
    p1, p2 = rng.uniform(0, 99, (20, 2)), rng.uniform(0, 99, (30, 2))
    d1, d2 = rng.random((20, 64)).astype(np.float32), rng.random((30, 64)).astype(np.float32)
    assert not g.segments(p1).valid.any()
    m = SegmentMatcher(g, constraint="segment")
    assert m.match(d1, d2, p1, p2) == []
    assert m.knnMatch(d1, d2, p1, p2, 2) == [[] for _ in range(20)]
    assert m.radiusMatch(d1, d2, p1, p2, 1e9) == [[] for _ in range(20)]
    assert SegmentMatcher(g, crossCheck=True).match(d1, d2, p1, p2) == []
    assert_empty_pairs(*match_descriptors(d1, d2, p1, p2, g, constraint="segment"))
    assert_empty_pairs(*radius_descriptors(d1, d2, p1, p2, g, max_distance=1e9))
    matches = [cv2.DMatch(i, i, 0, 0.0) for i in range(20)]
    assert m.filter(matches, p1, p2) == []
    labels, counts = m.explain(matches, p1, p2)
    assert sum(counts.values()) == 20
    assert set(labels.tolist()) <= {Rejection.EMPTY_SEGMENT, Rejection.OFF_LINE}
    assert counts["empty_segment"] == int((labels == Rejection.EMPTY_SEGMENT).sum())


def test_empty_segment_among_valid_ones():
    """A query whose ray is behind camera 2 gets an empty list; the others are unaffected."""
    g, kp1, kp2, d1, d2 = small_problem()
    # (60, 20) with depth range (0, 1e-9): a segment at the epipole (x = -inf), outside image 2
    m = SegmentMatcher(g, depth_range=(0.0, 1e-3))
    assert m.knnMatch(d1, d2, kp1, kp2, 2) == [[], [], []]
    assert m.match(d1, d2, kp1, kp2) == []


# ---------------------------------------------------------------------------------
# bad input: ValueError / TypeError naming the argument
# ---------------------------------------------------------------------------------
@pytest.fixture
def small():
    g, kp1, kp2, d1, d2 = small_problem()
    return g, kp1, kp2, d1, d2


METHODS = {
    "match": lambda m, d1, d2, k1, k2: m.match(d1, d2, k1, k2),
    "knnMatch": lambda m, d1, d2, k1, k2: m.knnMatch(d1, d2, k1, k2, 2),
    "radiusMatch": lambda m, d1, d2, k1, k2: m.radiusMatch(d1, d2, k1, k2, 10.0),
}


@pytest.mark.parametrize("method", sorted(METHODS))
@pytest.mark.parametrize("constraint", ["segment", "line", "none"])
def test_bad_descriptors(small, method, constraint):
    g, kp1, kp2, d1, d2 = small
    call = functools.partial(METHODS[method], SegmentMatcher(g, constraint=constraint))
    with pytest.raises(TypeError, match="dtype"):
        call(d1, (d2 * 255).astype(np.uint8), kp1, kp2)
    with pytest.raises(ValueError, match="width"):
        call(d1, d2[:, :16], kp1, kp2)
    with pytest.raises(ValueError, match="queryKeypoints"):
        call(d1, d2, kp1[:2], kp2)
    with pytest.raises(ValueError, match="trainKeypoints"):
        call(d1, d2, kp1, kp2 + [cv2.KeyPoint(1, 1, 1)])
    with pytest.raises(ValueError, match="trainKeypoints"):
        call(d1, d2, kp1, pts(kp2)[:3])
    nan_d = d1.copy()
    nan_d[0, 0] = np.nan
    with pytest.raises(ValueError, match="queryDescriptors"):
        call(nan_d, d2, kp1, kp2)
    with pytest.raises(ValueError, match="queryDescriptors"):
        call(d1[:, :, None], d2, kp1, kp2)


@pytest.mark.parametrize("method", sorted(METHODS))
@pytest.mark.parametrize("constraint", ["segment", "line", "none"])
def test_nan_keypoints(small, method, constraint):
    g, kp1, kp2, d1, d2 = small
    call = functools.partial(METHODS[method], SegmentMatcher(g, constraint=constraint))
    bad_kp = list(kp1)
    bad_kp[1] = cv2.KeyPoint(float("nan"), 3.0, 5.0)
    with pytest.raises(ValueError, match="queryKeypoints"):
        call(d1, d2, bad_kp, kp2)
    bad_arr = pts(kp2)
    bad_arr[2, 1] = np.nan
    with pytest.raises(ValueError, match="trainKeypoints"):
        call(d1, d2, kp1, bad_arr)
    bad_arr[2, 1] = np.inf
    with pytest.raises(ValueError, match="trainKeypoints"):
        call(d1, d2, kp1, bad_arr)
    with pytest.raises((ValueError, TypeError), match="queryKeypoints"):
        call(d1, d2, [kp1[0], (1.0, 2.0), kp1[2]], kp2)


@pytest.mark.parametrize("constraint", ["segment", "line", "none"])
def test_nan_keypoints_in_filter(small, constraint):
    g, kp1, kp2, d1, d2 = small
    m = SegmentMatcher(g, constraint=constraint)
    bad = list(kp1)
    bad[0] = cv2.KeyPoint(1.0, float("nan"), 5.0)
    with pytest.raises(ValueError, match="queryKeypoints"):
        m.filter([cv2.DMatch(1, 0, 0, 0.0)], bad, kp2)
    arr = pts(kp2)
    arr[0, 0] = np.nan
    with pytest.raises(ValueError, match="trainKeypoints"):
        m.filter([cv2.DMatch(1, 1, 0, 0.0)], kp1, arr)


@pytest.mark.parametrize("constraint", ["segment", "line", "none"])
def test_bad_k_tol_maxdistance(small, constraint):
    g, kp1, kp2, d1, d2 = small
    m = SegmentMatcher(g, constraint=constraint)
    for k in (0, -1):
        with pytest.raises(ValueError, match="k"):
            m.knnMatch(d1, d2, kp1, kp2, k)
    for k in (1.5, "2", None, True):
        with pytest.raises(TypeError, match="k"):
            m.knnMatch(d1, d2, kp1, kp2, k)
    with pytest.raises(ValueError, match="maxDistance"):
        m.radiusMatch(d1, d2, kp1, kp2, -1.0)
    with pytest.raises(ValueError, match="tol"):
        SegmentMatcher(g, tol=-0.5, constraint=constraint)
    with pytest.raises(ValueError, match="tol"):
        SegmentMatcher(g, tol=np.nan, constraint=constraint)
    with pytest.raises(ValueError, match="k"):
        SegmentMatcher(g, crossCheck=True, constraint=constraint).knnMatch(d1, d2, kp1, kp2, 2)


def test_bad_k_and_tol_array_api(small):
    g, kp1, kp2, d1, d2 = small
    p1, p2 = pts(kp1), pts(kp2)
    with pytest.raises(ValueError, match="k"):
        knn_descriptors(d1, d2, p1, p2, g, k=0)
    for fn in (match_descriptors, knn_descriptors):
        with pytest.raises(ValueError, match="tol"):
            fn(d1, d2, p1, p2, g, tol=-1.0)
    with pytest.raises(ValueError, match="tol"):
        radius_descriptors(d1, d2, p1, p2, g, max_distance=1.0, tol=-1.0)
    with pytest.raises(ValueError, match="tol"):
        filter_pairs([[0, 0]], p1, p2, g, tol=-1.0)
    with pytest.raises(ValueError, match="tol"):
        explain_pairs([[0, 0]], p1, p2, g, tol=-1.0)


@pytest.mark.parametrize("bad", ["segments", "Segment", "epipolar", "", None, 1])
def test_unknown_constraint(small, bad):
    g, kp1, kp2, d1, d2 = small
    p1, p2 = pts(kp1), pts(kp2)
    with pytest.raises(ValueError, match="constraint"):
        SegmentMatcher(g, constraint=bad)
    with pytest.raises(ValueError, match="constraint"):
        match_descriptors(d1, d2, p1, p2, g, constraint=bad)
    with pytest.raises(ValueError, match="constraint"):
        knn_descriptors(d1, d2, p1, p2, g, constraint=bad)
    with pytest.raises(ValueError, match="constraint"):
        filter_pairs([[0, 0]], p1, p2, g, constraint=bad)


@pytest.mark.parametrize("constraint", ["segment", "line", "none"])
def test_norm_must_fit_dtype(small, constraint):
    g, kp1, kp2, d1, d2 = small
    m = SegmentMatcher(g, cv2.NORM_HAMMING, constraint=constraint)
    for call in (lambda: m.match(d1, d2, kp1, kp2), lambda: m.knnMatch(d1, d2, kp1, kp2, 1),
                 lambda: m.radiusMatch(d1, d2, kp1, kp2, 5.0)):
        with pytest.raises(TypeError, match="Descriptors"):
            call()
    with pytest.raises(TypeError, match="descriptors1"):
        match_descriptors(d1, d2, pts(kp1), pts(kp2), g, norm="hamming")
    with pytest.raises(ValueError, match="normType"):
        SegmentMatcher(g, cv2.NORM_INF, constraint=constraint)
    with pytest.raises(ValueError, match="normType"):
        SegmentMatcher(g, "l3", constraint=constraint)


def test_float64_descriptors_are_accepted_or_refused_by_name(small):
    """float64 passes the descriptor check, so every path must handle it: no bare cv2.error."""
    g, kp1, kp2, d1, d2 = small
    d1, d2 = d1.astype(np.float64), d2.astype(np.float64)
    for constraint in ("segment", "none"):
        m = SegmentMatcher(g, constraint=constraint)
        for call in (lambda: m.match(d1, d2, kp1, kp2), lambda: m.knnMatch(d1, d2, kp1, kp2, 2),
                     lambda: m.radiusMatch(d1, d2, kp1, kp2, 5.0)):
            try:
                call()
            except (TypeError, ValueError) as exc:
                assert "Descriptors" in str(exc)


@pytest.mark.parametrize("constraint", ["segment", "line", "none"])
def test_filter_index_out_of_range(small, constraint):
    g, kp1, kp2, d1, d2 = small
    m = SegmentMatcher(g, constraint=constraint)
    for bad in ([cv2.DMatch(3, 0, 0, 0.0)], [cv2.DMatch(0, 5, 0, 0.0)], [cv2.DMatch(-1, 0, 0, 0.0)],
                [[cv2.DMatch(0, 0, 0, 0.0)], [cv2.DMatch(1, 99, 0, 0.0)]]):
        with pytest.raises(ValueError, match="out of range"):
            m.filter(bad, kp1, kp2)
        with pytest.raises(ValueError, match="out of range"):
            m.explain(bad, kp1, kp2)
    with pytest.raises(ValueError, match="out of range"):
        m.filter([cv2.DMatch(0, 0, 0, 0.0)], kp1, [])
    with pytest.raises(ValueError, match="out of range"):
        filter_pairs([[0, 7]], pts(kp1), pts(kp2), g, constraint=constraint)
    with pytest.raises(TypeError, match="matches"):
        m.filter([(0, 0)], kp1, kp2)
    with pytest.raises(TypeError, match="matches"):
        m.filter(None, kp1, kp2)


GEOMETRY_USERS = {
    "SegmentMatcher": lambda g, d1, d2, p1, p2: SegmentMatcher(g),
    "CandidateIndex": lambda g, d1, d2, p1, p2: CandidateIndex(g, p1, p2),
    "match_descriptors": lambda g, d1, d2, p1, p2: match_descriptors(d1, d2, p1, p2, g),
    "knn_descriptors": lambda g, d1, d2, p1, p2: knn_descriptors(d1, d2, p1, p2, g),
    "radius_descriptors": lambda g, d1, d2, p1, p2: radius_descriptors(d1, d2, p1, p2, g, max_distance=1.0),
    "filter_pairs": lambda g, d1, d2, p1, p2: filter_pairs([[0, 0]], p1, p2, g),
    "explain_pairs": lambda g, d1, d2, p1, p2: explain_pairs([[0, 0]], p1, p2, g),
}


@pytest.mark.parametrize("user", sorted(GEOMETRY_USERS))
@pytest.mark.parametrize("bad", [None, "geometry", np.eye(3)], ids=["None", "str", "array"])
def test_geometry_must_be_a_two_view_geometry(small, user, bad):
    g, kp1, kp2, d1, d2 = small
    with pytest.raises(TypeError, match="geometry"):
        GEOMETRY_USERS[user](bad, d1, d2, pts(kp1), pts(kp2))
