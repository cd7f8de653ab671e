"""CandidateIndex against a brute-force search over all pairs.

The reference is the definition: ``(i, j)`` is a candidate when
``EpipolarSegments.take(i).distance(points2[j]) <= tol`` (segment) or
``line_distance <= tol`` (line), with the segments of
``geometry.segments(points1, depth_range, margin=tol)``. Pairs whose distance
is within ``BOUNDARY_RTOL`` of ``tol`` may go either way (rounding).
"""

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from episeg_cv import CandidateIndex, TwoViewGeometry

#: Pixel distances within this (relative to 1 + tol) of ``tol`` are on the boundary.
BOUNDARY_RTOL = 1e-6


def K_of(f, size, shift=(0.0, 0.0)):
    w, h = size
    return np.array([[f, 0.0, (w - 1) / 2 + shift[0]], [0.0, f, (h - 1) / 2 + shift[1]], [0.0, 0.0, 1.0]])


def rotation(rotvec):
    return cv2.Rodrigues(np.asarray(rotvec, dtype=np.float64).reshape(3, 1))[0]


def pair_distances(geometry, points1, points2, tol, depth_range, constraint):
    """(N1, N2) pixel distance of every point of image 2 to every query's segment (or line)."""
    seg = geometry.segments(points1, depth_range, margin=tol)
    n1, n2 = len(points1), len(points2)
    ii, jj = np.meshgrid(np.arange(n1), np.arange(n2), indexing="ij")
    ii, jj = ii.ravel(), jj.ravel()
    sub = seg.take(ii)
    y = np.asarray(points2, dtype=np.float64).reshape(-1, 2)[jj]
    if constraint == "segment":
        d = sub.distance(y)
    else:
        d = np.where(np.all(np.isfinite(sub.line_start), axis=1), sub.line_distance(y), np.inf)
    return d.reshape(n1, n2)


def brute_force(geometry, points1, points2, tol, depth_range, constraint):
    """(strict, loose) candidate sets: strict must be found, nothing outside loose may be."""
    d = pair_distances(geometry, points1, points2, tol, depth_range, constraint)
    slack = BOUNDARY_RTOL * (1.0 + tol)
    strict = {tuple(p) for p in np.argwhere(d <= tol - slack).tolist()}
    loose = {tuple(p) for p in np.argwhere(d <= tol + slack).tolist()}
    return strict, loose


def check_against_brute_force(geometry, p1, p2, tol, depth_range, constraint, bucket_size):
    index = CandidateIndex(geometry, p1, p2, tol=tol, depth_range=depth_range, constraint=constraint,
                           bucket_size=bucket_size)
    pairs = index.pairs()
    assert pairs.dtype == np.intp and pairs.ndim == 2 and pairs.shape[1] == 2
    # sorted by query then train, no duplicates
    if len(pairs) > 1:
        key = pairs[:, 0] * (len(p2) + 1) + pairs[:, 1]
        assert np.all(np.diff(key) > 0)
    got = {tuple(p) for p in pairs.tolist()}
    strict, loose = brute_force(geometry, p1, p2, tol, depth_range, constraint)
    missing, extra = strict - got, got - loose
    assert not missing, f"{len(missing)} candidates missed, e.g. {sorted(missing)[:5]}"
    assert not extra, f"{len(extra)} false candidates, e.g. {sorted(extra)[:5]}"
    counts = index.candidate_counts()
    assert counts.shape == (len(p1),)
    np.testing.assert_array_equal(counts, np.bincount(pairs[:, 0], minlength=len(p1)) if len(pairs) else 0)
    return got, strict, loose


def assert_segment_within_line(seg, line, defined=None):
    """Segment candidates are line candidates, up to pairs on the line's tolerance boundary (only for the
    queries ``defined`` marks, those with an epipolar line, when given)."""
    (seg_got, _, _), (line_got, line_strict, line_loose) = seg, line
    outside = {p for p in seg_got - line_got if defined is None or defined[p[0]]}
    assert outside <= line_loose - line_strict, f"segment candidates off the line: {sorted(outside)[:5]}"


def planted_points2(geometry, p1, tol, depth_range, size, rng, n_random):
    """Keypoints of image 2: random ones, plus ones near the segments and lines (on both sides of them)."""
    w, h = size
    pts = [rng.uniform([-0.5, -0.5], [w - 0.5, h - 0.5], size=(n_random, 2))]
    seg = geometry.segments(p1, depth_range, margin=tol)
    ok = np.flatnonzero(seg.valid)
    if ok.size:
        s = rng.uniform(-0.3, 1.3, size=ok.size)
        base = seg.start[ok] + s[:, None] * (seg.end[ok] - seg.start[ok])
        line = seg.line[ok]
        normal = np.where(np.isfinite(line[:, :2]), line[:, :2], 0.0)
        off = rng.uniform(-1.5, 1.5, size=ok.size) * max(tol, 0.5)
        pts.append(base + off[:, None] * normal)
        pts.append(seg.start[ok])  # exactly on the segment's ends
        pts.append(seg.end[ok])
    lok = np.flatnonzero(np.all(np.isfinite(seg.line_start), axis=1))
    if lok.size:
        s = rng.uniform(0, 1, size=lok.size)
        pts.append(seg.line_start[lok] + s[:, None] * (seg.line_end[lok] - seg.line_start[lok]))
    p2 = np.concatenate(pts)
    inside = (p2[:, 0] >= -0.5) & (p2[:, 0] <= w - 0.5) & (p2[:, 1] >= -0.5) & (p2[:, 1] <= h - 0.5)
    return p2[np.all(np.isfinite(p2), axis=1) & inside]


# ---------------------------------------------------------------------------------
# hypothesis: random poses, including the degenerate ones
# ---------------------------------------------------------------------------------
POSE_KINDS = ["general", "t3_zero", "pure_rotation", "tiny_t3", "facing_away", "forward", "epipole_inside"]


@st.composite
def problems(draw):
    kind = draw(st.sampled_from(POSE_KINDS))
    size = draw(st.sampled_from([(160, 120), (320, 240), (97, 131)]))
    f1 = draw(st.floats(60, 600))
    f2 = draw(st.floats(60, 600))
    shift = (draw(st.floats(-20, 20)), draw(st.floats(-20, 20)))
    rv = np.array([draw(st.floats(-0.4, 0.4)) for _ in range(3)])
    t = np.array([draw(st.floats(-1, 1)) for _ in range(3)])
    if kind == "t3_zero":
        t[2] = 0.0
        if not t[:2].any():
            t[0] = 1.0
    elif kind == "pure_rotation":
        t[:] = 0.0
    elif kind == "tiny_t3":
        t[2] = 1e-12
        if not t[:2].any():
            t[0] = 1.0
    elif kind == "facing_away":
        rv = np.array([0.0, np.pi, 0.0]) + 0.1 * rv
    elif kind == "forward":
        t = np.array([0.05 * t[0], 0.05 * t[1], -1.0 if t[2] < 0 else 1.0])
    elif kind == "epipole_inside":
        t = np.array([0.1 * t[0], 0.1 * t[1], 1.0])
    g = TwoViewGeometry(K_of(f1, size), K_of(f2, size, shift), rotation(rv), t, image_size1=size, image_size2=size)
    tol = draw(st.sampled_from([0.0, 0.5, 2.0, 7.5]))
    dr = draw(st.sampled_from(["all", "band", "near", "per_point"]))
    seed = draw(st.integers(0, 2**32 - 1))
    n1 = draw(st.integers(0, 60))
    rng = np.random.default_rng(seed)
    w, h = size
    p1 = rng.uniform([-0.5, -0.5], [w - 0.5, h - 0.5], size=(n1, 2))
    if dr == "all":
        depth_range = (0.0, np.inf)
    elif dr == "band":
        depth_range = (0.5, 4.0)
    elif dr == "near":
        depth_range = (0.0, 0.3)
    else:
        zmin = rng.uniform(0, 2, n1)
        depth_range = (zmin, zmin + rng.uniform(0.01, 10, n1))
    p2 = planted_points2(g, p1, tol, depth_range, size, rng, draw(st.integers(0, 80)))
    bucket_size = draw(st.sampled_from([1, 3, 32]))
    return g, p1, p2, tol, depth_range, bucket_size, kind


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(problems())
def test_pairs_equal_brute_force_on_random_poses(problem):
    g, p1, p2, tol, depth_range, bucket_size, kind = problem
    seg_pairs = check_against_brute_force(g, p1, p2, tol, depth_range, "segment", bucket_size)
    line_pairs = check_against_brute_force(g, p1, p2, tol, depth_range, "line", bucket_size)
    # with t = 0 the line is undefined (F = 0), and so it is when t is so small that F underflows (t = 1e-300)
    defined = np.all(np.isfinite(g.segments(p1, depth_range, margin=tol).line), axis=1)
    assert_segment_within_line(seg_pairs, line_pairs, defined)


# ---------------------------------------------------------------------------------
# fixed cases
# ---------------------------------------------------------------------------------
SIZE = (320, 240)
K = K_of(300.0, SIZE)

FIXED_POSES = {
    "general": (rotation([0.05, -0.2, 0.03]), [0.6, -0.1, 0.3]),
    "t3_zero": (rotation([0.0, 0.07, 0.0]), [-0.6, 0.05, 0.0]),
    "pure_rotation": (rotation([0.02, 0.1, -0.05]), [0.0, 0.0, 0.0]),
    "tiny_t3": (rotation([0.0, 0.05, 0.0]), [-1.0, 0.0, 1e-12]),
    "forward": (rotation([0.0, 0.0, 0.03]), [0.1, 0.05, -1.0]),
    "backward": (np.eye(3), [0.0, 0.0, 1.0]),
    "facing_away": (rotation([0.0, np.pi, 0.0]), [0.3, 0.0, -2.0]),
}


def fixed_problem(name, n1=200, n2=400, seed=0, tol=2.0, depth_range=(0.0, np.inf)):
    R, t = FIXED_POSES[name]
    g = TwoViewGeometry(K, K, R, t, image_size1=SIZE, image_size2=SIZE)
    rng = np.random.default_rng(seed)
    p1 = rng.uniform(-0.5, np.array(SIZE) - 0.5, size=(n1, 2))
    p2 = planted_points2(g, p1, tol, depth_range, SIZE, rng, n2)
    return g, p1, p2


@pytest.mark.parametrize("name", sorted(FIXED_POSES))
@pytest.mark.parametrize("bucket_size", [1, 7, 64])
def test_pairs_equal_brute_force_fixed_poses(name, bucket_size):
    g, p1, p2 = fixed_problem(name)
    seg = check_against_brute_force(g, p1, p2, 2.0, (0.0, np.inf), "segment", bucket_size)
    line = check_against_brute_force(g, p1, p2, 2.0, (0.0, np.inf), "line", bucket_size)
    if name != "pure_rotation":
        assert_segment_within_line(seg, line)
    if name in ("general", "forward", "t3_zero"):
        assert len(line[0]) > len(seg[0]) > 0  # the segment removes candidates


@pytest.mark.parametrize("name", ["general", "forward", "tiny_t3"])
@pytest.mark.parametrize("depth_range", [(0.5, 3.0), (0.0, 0.2), (2.0, np.inf)])
def test_pairs_with_depth_range(name, depth_range):
    g, p1, p2 = fixed_problem(name, n1=150, n2=300, depth_range=depth_range)
    narrow = check_against_brute_force(g, p1, p2, 2.0, depth_range, "segment", 16)[0]
    full = check_against_brute_force(g, p1, p2, 2.0, (0.0, np.inf), "segment", 16)[0]
    assert narrow <= full


def test_pairs_with_per_point_depth_range():
    g, p1, p2 = fixed_problem("general", n1=100, n2=300)
    rng = np.random.default_rng(1)
    zmin = rng.uniform(0, 2, len(p1))
    dr = (zmin, zmin + rng.uniform(0.1, 5, len(p1)))
    check_against_brute_force(g, p1, p2, 2.0, dr, "segment", 8)


@pytest.mark.parametrize("name", ["general", "pure_rotation", "forward"])
def test_tol_zero(name):
    g, p1, p2 = fixed_problem(name, n1=80, n2=100, tol=0.0)
    check_against_brute_force(g, p1, p2, 0.0, (0.0, np.inf), "segment", 8)
    check_against_brute_force(g, p1, p2, 0.0, (0.0, np.inf), "line", 8)
    # the planted segment ends are at distance 0, so they are found with tol = 0
    s = g.segments(p1, margin=0.0)
    ok = np.flatnonzero(s.valid)
    idx = CandidateIndex(g, p1, s.start[ok], tol=0.0).pairs()
    assert {(int(i), k) for k, i in enumerate(ok)} <= {tuple(p) for p in idx.tolist()}


def test_facing_away_gives_empty_segments_and_no_candidates():
    R, t = FIXED_POSES["facing_away"]
    g = TwoViewGeometry(K, K, R, [0.0, 0.0, -2.0], image_size1=SIZE, image_size2=SIZE)
    rng = np.random.default_rng(3)
    p1 = rng.uniform(-0.5, np.array(SIZE) - 0.5, size=(50, 2))
    p2 = rng.uniform(-0.5, np.array(SIZE) - 0.5, size=(200, 2))
    index = CandidateIndex(g, p1, p2, tol=2.0)
    assert not index.segments.valid.any()
    assert index.pairs().shape == (0, 2) and index.pairs().dtype == np.intp
    np.testing.assert_array_equal(index.candidate_counts(), np.zeros(50))


def test_doc_example_by_hand():
    # segment of (50, 50) for t = (-1, 0, 0): the row y = 50, from the epipole at x = -inf to p_inf (50, 50)
    g = TwoViewGeometry([[100, 0, 50], [0, 100, 50], [0, 0, 1]], [[100, 0, 50], [0, 100, 50], [0, 0, 1]],
                        np.eye(3), [-1, 0, 0], image_size1=(100, 100), image_size2=(100, 100))
    p2 = [[30.0, 50.5], [70.0, 50.0], [30.0, 60.0], [50.0, 52.0], [52.0, 50.0], [52.01, 50.0]]
    assert CandidateIndex(g, [[50.0, 50.0]], p2, tol=2.0).pairs().tolist() == [[0, 0], [0, 3], [0, 4]]
    assert CandidateIndex(g, [[50.0, 50.0]], p2, tol=2.0, constraint="line").pairs().tolist() == \
        [[0, 0], [0, 1], [0, 3], [0, 4], [0, 5]]


# ---------------------------------------------------------------------------------
# empty input
# ---------------------------------------------------------------------------------
@pytest.mark.parametrize("constraint", ["segment", "line"])
@pytest.mark.parametrize("n1, n2", [(0, 0), (0, 10), (10, 0)])
def test_empty_sides(constraint, n1, n2):
    g, p1, p2 = fixed_problem("general", n1=10, n2=10)
    p1, p2 = p1[:n1], p2[:n2]
    index = CandidateIndex(g, p1, p2, tol=2.0, constraint=constraint)
    pairs = index.pairs()
    assert pairs.shape == (0, 2) and pairs.dtype == np.intp
    counts = index.candidate_counts()
    assert counts.shape == (n1,) and not counts.any()


def test_empty_lists_are_accepted():
    g, _, _ = fixed_problem("general", n1=1, n2=1)
    assert CandidateIndex(g, [], []).pairs().shape == (0, 2)


# ---------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------
def test_bad_input():
    g, p1, p2 = fixed_problem("general", n1=5, n2=5)
    with pytest.raises(TypeError, match="geometry"):
        CandidateIndex(object(), p1, p2)
    with pytest.raises(ValueError, match="constraint"):
        CandidateIndex(g, p1, p2, constraint="segments")
    with pytest.raises(ValueError, match="constraint"):
        CandidateIndex(g, p1, p2, constraint="none")
    with pytest.raises(ValueError, match="tol"):
        CandidateIndex(g, p1, p2, tol=-1.0)
    bad = p1.copy()
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match="points1"):
        CandidateIndex(g, bad, p2)
    with pytest.raises(ValueError, match="points2"):
        CandidateIndex(g, p1, p2[:, :1])


def test_pseudo_angles_keep_the_order_of_angles_mod_pi():
    """The index compares pencil pseudo-angles instead of arctan2(b, a) % pi: same order, period 2."""
    from episeg_cv.matching._index_kernels import PERIOD, _pseudo_angle

    rng = np.random.default_rng(0)
    theta = np.sort(np.concatenate([rng.uniform(0, np.pi, 2000), [0.0, np.pi / 2, np.pi / 4, 3 * np.pi / 4]]))
    scale = rng.uniform(1e-6, 1e6, theta.size)
    sign = rng.choice([-1.0, 1.0], theta.size)  # a line's direction either way: the same angle mod pi
    p = np.array([_pseudo_angle(s * r * np.sin(t), s * r * np.cos(t)) for t, r, s in zip(theta, scale, sign)])
    assert np.all((p >= 0) & (p < PERIOD)) and np.all(np.diff(p) > 0)
    assert _pseudo_angle(0.0, 1.0) == 0.0 and _pseudo_angle(1.0, 0.0) == 1.0 and _pseudo_angle(0.0, -1.0) == 0.0
    assert _pseudo_angle(0.0, 0.0) == 0.0 and np.isnan(_pseudo_angle(np.nan, 1.0))


def _reference_ranges(lo, width, edges):
    """The buckets of each keypoint's angle interval, by ``np.searchsorted`` (the index's definition)."""
    from episeg_cv.matching._index_kernels import PERIOD

    n_b = len(edges) - 1
    h = np.minimum(lo + width, lo + PERIOD)
    bucket = lambda x: np.clip(np.searchsorted(edges, x, side="right") - 1, 0, n_b - 1)  # noqa: E731
    k0, k1 = bucket(lo), bucket(np.minimum(h, PERIOD))
    w1 = np.where(h > PERIOD, np.minimum(bucket(np.maximum(h - PERIOD, 0.0)), k0 - 1), -1)
    return np.column_stack([k0, k1, w1])


@pytest.mark.parametrize("n_b", [1, 2, 7, 156])
def test_bucket_ranges_are_searchsorted(n_b):
    """The grid-accelerated bucket search of the index gives np.searchsorted's buckets, edges and ties included."""
    from episeg_cv.matching._index_kernels import PERIOD, _grid, _ranges

    rng = np.random.default_rng(n_b)
    inner = np.sort(rng.choice(np.concatenate([rng.uniform(0, PERIOD, n_b), [0.5, 0.5, 1.0]]), n_b - 1))
    edges = np.concatenate([[0.0], inner, [PERIOD]])
    grid_values = np.arange(4 * n_b + 1) * (PERIOD / (4 * n_b))  # values on the grid's cell bounds
    lo = np.concatenate([rng.uniform(0, PERIOD, 3000), edges[:-1], grid_values[:-1], np.nextafter(edges[1:], 0)])
    width = np.concatenate([rng.choice([0.0, 1e-3, 0.3, PERIOD], 3000, p=[0.1, 0.6, 0.2, 0.1]),
                            rng.uniform(0, PERIOD, lo.size - 3000)])
    got = np.empty((lo.size, 3), dtype=np.int64)
    _ranges(0, lo.size, lo, width, edges, _grid(edges), got)
    np.testing.assert_array_equal(got, _reference_ranges(lo, width, edges))


@pytest.mark.parametrize("n_b", [1, 3, 40])
def test_bucket_sort_is_a_stable_sort_by_bucket_then_key(n_b):
    """The index's counting sort by (bucket, cell) and its per-cell sorts give a stable sort of the entries
    by bucket, then key (ties in keypoint order): keys spread out, bunched into one cell (the merge-sort
    branch), repeated, and at the ends of a bucket."""
    from episeg_cv.matching._index_kernels import INSERTION_MAX, _by_cell, _sort_cells

    rng = np.random.default_rng(n_b)
    n = 6000
    counts = rng.integers(0, 4, n)
    first = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    total = int(first[-1])
    bucket = rng.integers(0, n_b, total).astype(np.int64)
    frac = rng.uniform(0, 1, total)
    kind = rng.random(total)
    frac[kind < 0.1] = rng.choice([0.0, 0.5, np.nextafter(1.0, 0)], (kind < 0.1).sum())  # repeated, the ends
    bunched = kind > 0.7
    frac[bunched] = 0.25 + rng.uniform(0, 1e-6, bunched.sum())
    key = bucket + frac
    t, k, cstart, per = _by_cell(first, bucket, key, n_b)
    assert np.diff(cstart).max() > INSERTION_MAX  # both branches of _sort_cells run
    cells = len(cstart) - 1
    _sort_cells(0, cells // 3, cstart, t, k)  # in pieces, as the threads do
    _sort_cells(cells // 3, cells, cstart, t, k)
    owner = np.repeat(np.arange(n), counts)
    o = np.lexsort((key, bucket))  # stable: ties keep the keypoint-major order
    np.testing.assert_array_equal(t, owner[o])
    np.testing.assert_array_equal(k, key[o])
    np.testing.assert_array_equal(cstart[::per], np.searchsorted(bucket[o], np.arange(n_b + 1)))


def test_slice_bounds_are_searchsorted():
    """Each query's slice: np.searchsorted of its key interval in its bucket's sorted keys."""
    from episeg_cv.matching._index_kernels import slice_bounds

    rng = np.random.default_rng(3)
    sizes = rng.integers(0, 40, 30)
    bstart = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    key_t = np.concatenate([b + np.sort(rng.choice(np.linspace(0, 1, 25), s)) for b, s in enumerate(sizes)])
    qb = rng.integers(0, len(sizes), 500).astype(np.int64)
    klo = qb + rng.choice(np.linspace(-0.1, 1.1, 37), 500)
    khi = klo + rng.choice([0.0, 0.05, 0.5, 2.0], 500)
    start, stop = slice_bounds(key_t, bstart, qb, klo, khi)
    for r in range(500):
        a, z = bstart[qb[r]], bstart[qb[r] + 1]
        assert start[r] == a + np.searchsorted(key_t[a:z], klo[r], side="left")
        assert stop[r] == a + np.searchsorted(key_t[a:z], khi[r], side="right")
