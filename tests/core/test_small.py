"""The small-pair path (:mod:`episeg_cv.matching.small`): one compiled call, the index path's results."""

import cv2
import numpy as np
import pytest

from episeg_cv import FundamentalGeometry, TwoViewGeometry
from episeg_cv.geometry import point_segment_distance
from episeg_cv.matching import _small_kernels, guided, small
from episeg_cv.matching.config import AcceptRule, SearchConfig
from episeg_cv.matching.filtering import keep_mask

K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
SIZE = (320, 240)


def _both_paths(monkeypatch, inputs, g, search, rule, prefilter):
    calls = []
    real = small.nearest
    monkeypatch.setattr(small, "nearest", lambda *a: calls.append(1) or real(*a))
    a = guided.nearest(inputs, g, search, rule, rng=3, prefilter=prefilter)
    monkeypatch.setattr(small, "SMALL_PAIRS", -1)  # the index path
    b = guided.nearest(inputs, g, search, rule, rng=3, prefilter=prefilter)
    assert calls == [1]  # the first call took the small path, the second did not
    return a, b


def _case(rng, n1, n2, t, norm):
    g = TwoViewGeometry(K, K, cv2.Rodrigues(rng.normal(0, 0.3, 3))[0], t, image_size1=SIZE, image_size2=SIZE)
    p1 = rng.uniform(-5, 325, (n1, 2))
    p2 = rng.uniform(-5, 325, (n2, 2)) * [1, 0.75]
    if norm == "hamming":
        d1, d2 = (rng.integers(0, 256, (n, 32)).astype(np.uint8) for n in (n1, n2))
    else:  # few distinct values: many ties, which both paths must break the same way
        d1, d2 = (rng.integers(0, 4, (n, 16)).astype(np.float32) for n in (n1, n2))
    return g, guided.MatchInputs.check(d1, d2, p1, p2, norm)


@pytest.mark.parametrize("seed", range(24))
def test_small_path_equals_the_index_path(monkeypatch, seed):
    """Property: same indices, ratios, mutual flags and counts, bit for bit, dtypes included."""
    rng = np.random.default_rng(seed)
    t = rng.normal(0, 1, 3) * ([1, 1, 1] if seed % 3 else [1, 0, 0])  # every third: epipole at infinity
    norm = ("l2", "l2sqr", "l1", "hamming")[seed % 4]
    n1, n2 = (int(v) for v in rng.integers(1, 300, 2))
    g, inputs = _case(rng, n1, n2, t, norm)
    depth = [(0.0, np.inf), (0.5, 3.0), (rng.uniform(0, 1, n1), rng.uniform(1, 5, n1))][seed % 3]
    search = SearchConfig(tol=float(rng.choice([0.5, 2.0, 8.0, 30.0])), depth_range=depth)
    rule = AcceptRule(ratio=float(rng.choice([0.68, 0.9, 1.0])), mutual=bool(seed % 2),
                      pad=int(rng.choice([0, 5, 128])))
    for prefilter in (False, True):
        a, b = _both_paths(monkeypatch, inputs, g, search, rule, prefilter)
        monkeypatch.undo()
        for x, y in zip(a, b):
            assert x.dtype == y.dtype and np.array_equal(x, y)


@pytest.mark.parametrize("t, n1, n2", [([0, 0, 0], 20, 30),  # pure rotation: point segments
                                       ([1, 0, 0], 0, 10), ([1, 0, 0], 10, 0), ([1, 0, 0], 0, 0)])
def test_small_path_edge_cases(monkeypatch, t, n1, n2):
    rng = np.random.default_rng(5)
    g, inputs = _case(rng, n1, n2, t, "l2")
    a, b = _both_paths(monkeypatch, inputs, g, SearchConfig(tol=3.0), AcceptRule(), True)
    for x, y in zip(a, b):
        assert x.dtype == y.dtype and np.array_equal(x, y)
    assert len(a[4]) == n1


def test_ray_behind_camera_2_has_no_candidates():
    """Hand-computed: camera 2 one unit ahead, a query whose depth range ends before it: empty segment."""
    g = TwoViewGeometry(K, K, np.eye(3), [0, 0, -1.0], image_size1=SIZE, image_size2=SIZE)
    inputs = guided.MatchInputs.check(np.ones((1, 4), np.float32), np.ones((2, 4), np.float32),
                                      [[160.0, 120.0]], [[160.0, 120.0], [100.0, 100.0]], "l2")
    i, j, r, mu, counts = guided.nearest(inputs, g, SearchConfig(depth_range=(0.1, 0.9)), AcceptRule())
    assert i.dtype == np.intp and len(i) == 0 and counts.tolist() == [0]
    i, j, r, mu, counts = guided.nearest(inputs, g, SearchConfig(depth_range=(1.5, 9.0)), AcceptRule(pad=0))
    assert i.tolist() == [0] and j.tolist() == [0] and counts.tolist() == [1]  # the centre maps to the centre


def test_small_path_is_not_taken_where_it_does_not_apply():
    s, r = SearchConfig(), AcceptRule()
    g = TwoViewGeometry(K, K, np.eye(3), [1.0, 0, 0], image_size1=SIZE, image_size2=SIZE)
    assert small.fits(300, 300, s, r, g)
    assert not small.fits(2000, 2000, s, r, g)  # large: the index
    assert not small.fits(300, 300, s.replace(constraint="line"), r, g)
    assert not small.fits(300, 300, s, r.replace(cross_check=True), g)
    assert not small.fits(300, 300, SearchConfig(tol="auto"), r, g)
    assert not small.fits(300, 300, s, r, g.with_covariance(np.eye(6) * 1e-6))
    F = FundamentalGeometry(np.array([[0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]), image_size1=SIZE, image_size2=SIZE)
    assert not small.fits(300, 300, s, r, F)


@pytest.mark.parametrize("seed", range(6))
def test_segment_keep_is_the_distance_to_the_segment(seed):
    """cv2-free reference: ``point_segment_distance`` on the segments, applied pair by pair."""
    rng = np.random.default_rng(seed)
    g = TwoViewGeometry(K, K, cv2.Rodrigues(rng.normal(0, 0.3, 3))[0], rng.normal(0, 1, 3), image_size1=SIZE,
                        image_size2=SIZE)
    p1, p2 = rng.uniform(0, 320, (80, 2)), rng.uniform(0, 320, (90, 2)) * [1, 0.75]
    pairs = np.column_stack([rng.integers(0, 80, 400), rng.integers(0, 90, 400)]).astype(np.intp)
    kept = []
    for tol in (1.0, 10.0, 60.0):
        seg = g.segments(p1, margin=tol)
        d = point_segment_distance(p2[pairs[:, 1]], np.nan_to_num(seg.start[pairs[:, 0]]),
                                   np.nan_to_num(seg.end[pairs[:, 0]]))
        want = seg.valid[pairs[:, 0]] & (d <= tol)
        got = keep_mask(pairs, p1, p2, g, SearchConfig(tol=tol))
        assert got.dtype == bool and np.array_equal(got, want)
        kept.append(want.mean())
    assert max(kept) > 0 and min(kept) < 1  # the check can fail both ways
    empty = _small_kernels.segment_keep(seg.line, seg.start, seg.end, seg.valid, np.zeros(0, np.int64), p2,
                                        np.zeros(0, np.int64), 1.0)
    assert empty.dtype == bool and empty.shape == (0,)


def test_many_pairs_in_one_call_equal_nearest_and_keep_mask():
    """small.many on pairs that share arrays, with different depth ranges and bands: each pair's
    nearest candidates (ratio and mutual rule), and the reverse test of keep_mask, as one by one."""
    rng = np.random.default_rng(11)
    g1, inputs = _case(rng, 150, 170, [1.0, 0.1, 0.2], "l2")
    g2 = TwoViewGeometry(K, K, cv2.Rodrigues(np.array([0.1, -0.2, 0.05]))[0], [0.2, 1.0, -0.1], image_size1=SIZE,
                         image_size2=SIZE)
    x1, x2, a, b = inputs.points1, inputs.points2, inputs.distances.a, inputs.distances.b
    rule = AcceptRule(ratio=1.0)
    cases = [(g1, 2.0, (0.0, np.inf), (0.0, np.inf)), (g1, 2.0, (0.5, 3.0), (0.2, 2.0)),
             (g2, 6.0, (0.5, 3.0), (1.5, 1.8))]
    items = [small.SmallPair(x1, a, x2, b, g, tol, d1, d2) for g, tol, d1, d2 in cases]
    found = small.many(items, rule, 1.0, "l2", lambda n2, n_pad: guided.padding_references(3, n2, n_pad))
    assert len(found) == 3
    for (g, tol, d1, d2), (i, j, r, inlier) in zip(cases, found):
        ii, jj, rr, mu, _ = guided.nearest(inputs, g, SearchConfig(tol=tol, depth_range=d1), rule, rng=3,
                                           prefilter=True)
        keep = (rr < 1.0) & mu
        assert np.array_equal(i, ii[keep]) and np.array_equal(j, jj[keep]) and np.array_equal(r, rr[keep])
        pairs = np.column_stack([j, i]).astype(np.intp)
        want = keep_mask(pairs, x2, x1, g.inverse(), SearchConfig(tol=tol, depth_range=d2))
        assert inlier.dtype == bool and np.array_equal(inlier, want)
    assert len(found[0][0]) != len(found[1][0])  # the depth ranges mattered
    assert any(f[3].any() for f in found) and any((~f[3]).any() for f in found)  # the reverse test can fail
    assert small.many([], rule, 1.0, "l2", None) == []


@pytest.mark.parametrize("seed", range(8))
def test_bucket_slices_equal_searchsorted(seed):
    """Property: the bucket table's ``[start, stop)`` is ``np.searchsorted``'s (left, right), with ties,
    one distinct key, bounds outside the keys' range and empty slices."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 60))
    pts = rng.integers(0, 5, (n, 2)).astype(float) if seed % 2 else rng.uniform(-50, 400, (n, 2))
    if seed == 6:
        pts[:] = 7.0  # every key equal: a zero span
    a0, a1 = np.cos(seed), np.sin(seed)
    keys, order, ys, table = np.empty(n), np.empty(n, np.int64), np.empty((n, 2)), np.empty(n + 1, np.int64)
    kmin, scale = _small_kernels._axis(pts, a0, a1, keys, order, ys, table)
    v = pts[:, 0] * a0 + pts[:, 1] * a1
    assert np.array_equal(keys, v[order]) and np.array_equal(ys, pts[order]) and np.all(np.diff(keys) >= 0)
    bounds = rng.uniform(-500, 500, (40, 2))
    if n:
        bounds = np.vstack([bounds, np.repeat(keys[:, None], 2, 1), keys[rng.integers(0, n, (40, 2))]])
    for lo, hi in bounds:
        got = _small_kernels._slices(lo, hi, keys, table, kmin, scale)
        want = np.searchsorted(keys, lo, "left"), np.searchsorted(keys, hi, "right")
        assert got == (want[0], max(want[0], want[1]))


@pytest.mark.parametrize("parallel", [False, True])
def test_many_pairs_of_distinct_images(monkeypatch, parallel):
    """small.many over images of different sizes (one empty, one of a single keypoint), each sorted once
    for all its pairs, serial and on threads: every pair as guided.nearest finds it alone."""
    rng = np.random.default_rng(4)
    sizes = [120, 0, 1, 200, 75]
    pts = [rng.uniform(0, 320, (n, 2)) * [1, 0.75] for n in sizes]
    desc = [rng.integers(0, 4, (n, 16)).astype(np.float32) for n in sizes]
    rows = [guided.MatchInputs.check(d, d, p, p, "l2").distances.a for d, p in zip(desc, pts)]
    pairs = [(0, 3), (3, 0), (0, 1), (1, 4), (2, 3), (4, 3), (4, 0)]
    geos = [TwoViewGeometry(K, K, cv2.Rodrigues(rng.normal(0, 0.2, 3))[0], rng.normal(0, 1, 3), image_size1=SIZE,
                            image_size2=SIZE) for _ in pairs]
    rule = AcceptRule(ratio=1.0, pad=0)
    items = [small.SmallPair(pts[u], rows[u], pts[v], rows[v], g, 8.0, (0.0, np.inf), (0.0, np.inf))
             for (u, v), g in zip(pairs, geos)]
    monkeypatch.setattr(small.threads, "use_parallel", lambda items: parallel)
    found = small.many(items, rule, 1.0, "l2", None)
    for (u, v), g, (i, j, r, inlier) in zip(pairs, geos, found):
        inputs = guided.MatchInputs.check(desc[u], desc[v], pts[u], pts[v], "l2")
        ii, jj, rr, mu, _ = guided.nearest(inputs, g, SearchConfig(tol=8.0), rule, prefilter=True)
        keep = (rr < 1.0) & mu
        assert np.array_equal(i, ii[keep]) and np.array_equal(j, jj[keep]) and np.array_equal(r, rr[keep])
        assert inlier.shape == i.shape
    assert sum(len(f[0]) for f in found) > 50  # the pairs of the large images found matches
