"""The shortcuts taken for speed give the same results as the plain computation.

- ``match_descriptors`` scores the random padding references only for the pairs
  the rule could keep, and computes exact distances only for the kept pairs: it
  must equal ``guided_matches(...).accept(...)``, which does neither.
- ``Distances.exact`` (paired distances in chunks with reused buffers) against a direct
  row-by-row computation, across chunk boundaries and every norm and dtype.
- ``Distances.nearest_excluding`` (BLAS row chunks and searchsorted exclusion
  for L2, a compiled loop otherwise) against the dense score matrix from the
  definition, with the excluded entries masked.
- The compiled scores (``Distances.paired``) against ``cv2.norm``.
- ``filter_pairs`` computes the segment distance only for pairs near the line:
  it must equal the definition also on pairs planted at the tolerance boundary
  and on undefined lines (pure rotation).
- ``as_descriptor_pair`` tests finiteness by the minimum and maximum; huge finite
  entries (whose sum would overflow) must not be mistaken for NaN or inf.
"""

import cv2
import numpy as np
import pytest

import episeg_cv
from episeg_cv import (SegmentMatcher, TwoViewGeometry, filter_pairs, guided_matches, knn_descriptors,
                       match_descriptors)
from episeg_cv._validation import as_descriptor_pair
from episeg_cv.matching.distances import Distances


def geometry(t=(-1.0, 0.1, 0.2), size=(200, 150)):
    K = np.array([[150.0, 0, (size[0] - 1) / 2], [0, 150.0, (size[1] - 1) / 2], [0, 0, 1]])
    R = cv2.Rodrigues(np.array([[0.02], [-0.03], [0.01]]))[0]
    return TwoViewGeometry(K, K, R, t, image_size1=size, image_size2=size)


def random_problem(n1=300, n2=350, dim=32, dtype=np.float32, seed=0, size=(200, 150)):
    rng = np.random.default_rng(seed)
    p1 = rng.uniform([0, 0], [size[0] - 1, size[1] - 1], (n1, 2))
    p2 = rng.uniform([0, 0], [size[0] - 1, size[1] - 1], (n2, 2))
    if dtype == np.uint8:
        d1 = rng.integers(0, 256, (n1, dim), dtype=np.uint8)
        d2 = rng.integers(0, 256, (n2, dim), dtype=np.uint8)
    else:
        d1 = rng.integers(0, 40, (n1, dim)).astype(dtype)  # integer-valued, as SIFT's: exact ties occur
        d2 = rng.integers(0, 40, (n2, dim)).astype(dtype)
    return d1, d2, p1, p2


@pytest.mark.parametrize("constraint", ["segment", "line"])
@pytest.mark.parametrize("norm,dtype", [("l2", np.float32), ("l1", np.float32), ("hamming", np.uint8)])
@pytest.mark.parametrize("ratio,mutual,pad,cross_check", [
    (0.68, True, 128, False), (0.9, False, 128, False), (1.0, True, 128, False), (0.8, True, 0, False),
    (0.8, True, 64, True), (0.75, False, 500, False)])
def test_match_descriptors_equals_guided_accept(constraint, norm, dtype, ratio, mutual, pad, cross_check):
    d1, d2, p1, p2 = random_problem(dtype=dtype, seed=3)
    g = geometry()
    kw = dict(norm=norm, tol=4.0, constraint=constraint, pad=pad, cross_check=cross_check)
    gm = guided_matches(d1, d2, p1, p2, g, **kw)
    pairs, dist = match_descriptors(d1, d2, p1, p2, g, ratio=ratio, mutual=mutual, **kw)
    ref_pairs, ref_dist = gm.accept(ratio, mutual or cross_check)
    np.testing.assert_array_equal(pairs, ref_pairs)
    np.testing.assert_array_equal(dist, ref_dist)
    assert pairs.dtype == np.intp and dist.dtype == np.float32


@pytest.mark.parametrize("norm,dtype", [("l2", np.float32), ("l2sqr", np.float32), ("l1", np.float32),
                                        ("l2", np.float64), ("l1", np.uint8), ("l2", np.uint8),
                                        ("hamming", np.uint8)])
@pytest.mark.parametrize("n", [0, 1, 7, 50, 5000])
def test_exact_equals_direct(norm, dtype, n):
    d1, d2, _, _ = random_problem(n1=20, n2=25, dim=16, dtype=dtype, seed=1)
    rng = np.random.default_rng(2)
    i, j = rng.integers(0, 20, n), rng.integers(0, 25, n)
    got = Distances(d1, d2, norm).exact(i, j)
    assert got.dtype == np.float32 and got.shape == (n,)
    if norm == "hamming":
        want = np.unpackbits(d1[i] ^ d2[j], axis=1).sum(1).astype(np.float32)
    else:
        diff = d1[i].astype(np.float32) - d2[j].astype(np.float32)
        want = np.abs(diff).sum(1, dtype=np.float32) if norm == "l1" else np.einsum("ij,ij->i", diff, diff)
        want = np.sqrt(want) if norm == "l2" else want
    np.testing.assert_array_equal(got, want)
    for (a, b), d in zip(zip(i, j), got):  # and what cv2 reports, pair by pair
        if norm != "l2sqr":
            ref = cv2.norm(d1[a].astype(np.float32) if dtype == np.float64 else d1[a],
                           d2[b].astype(np.float32) if dtype == np.float64 else d2[b],
                           {"l1": cv2.NORM_L1, "l2": cv2.NORM_L2, "hamming": cv2.NORM_HAMMING}[norm])
            assert d == pytest.approx(ref, rel=1e-5, abs=1e-6)


def dense_scores(d1, d2, norm):
    """(N1, N2) scores by the definition: squared L2, L1, or Hamming on packed bits."""
    if norm == "hamming":
        return np.unpackbits(d1[:, None, :] ^ d2[None, :, :], axis=2).sum(2).astype(np.float32)
    diff = d1[:, None, :].astype(np.float64) - d2[None, :, :]
    return (np.abs(diff).sum(2) if norm == "l1" else (diff**2).sum(2)).astype(np.float32)


@pytest.mark.parametrize("norm,dtype", [("l2", np.float32), ("l2sqr", np.float32), ("l1", np.float32),
                                        ("hamming", np.uint8)])
@pytest.mark.parametrize("n_queries", [25, 1300])  # 1300: three padding chunks, the last one partial
def test_nearest_excluding_equals_dense(norm, dtype, n_queries):
    from episeg_cv.matching.distances import PAD_CHUNK

    assert n_queries < PAD_CHUNK or n_queries % PAD_CHUNK
    d1, d2, _, _ = random_problem(n1=max(40, n_queries), n2=60, dim=16, dtype=dtype, seed=4)
    dist = Distances(d1, d2, norm)
    rng = np.random.default_rng(5)
    qi = np.sort(rng.choice(len(d1), n_queries, replace=False))
    tj = np.sort(rng.choice(60, 12, replace=False))
    exclude = np.where(rng.random(n_queries) < 0.5, rng.choice(tj, n_queries), rng.integers(0, 60, n_queries))
    dense = dense_scores(d1[qi], d2[tj], norm)
    dense[tj[None, :] == exclude[:, None]] = np.inf
    got = dist.nearest_excluding(qi, tj, exclude)
    np.testing.assert_allclose(got, dense.min(axis=1), rtol=1e-5)
    # one reference keypoint, excluded: nothing left
    one = dist.nearest_excluding(qi[:1], tj[:1], tj[:1])
    assert one.tolist() == [np.inf]
    # the padding's arithmetic per row does not depend on the thread count (fixed chunks)
    try:
        episeg_cv.set_num_threads(1)
        serial = dist.nearest_excluding(qi, tj, exclude)
    finally:
        episeg_cv.set_num_threads(None)
    np.testing.assert_array_equal(got, serial)
    # non-integer descriptors: exact ties are rare, rounding differs from the dense float64 reference
    f1, f2 = (rng.random((len(d1), 16)).astype(np.float32), rng.random((60, 16)).astype(np.float32))
    if norm != "hamming":
        got = Distances(f1, f2, norm).nearest_excluding(qi, tj, exclude)
        want = dense_scores(f1[qi], f2[tj], norm)
        want[tj[None, :] == exclude[:, None]] = np.inf
        np.testing.assert_allclose(got, want.min(axis=1), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("norm,dtype,dim", [("l2", np.float32, 128), ("l2sqr", np.float32, 7), ("l1", np.float32, 33),
                                            ("l2", np.uint8, 32), ("hamming", np.uint8, 61), ("hamming", np.uint8, 1)])
def test_compiled_scores_equal_cv2_norm(norm, dtype, dim):
    rng = np.random.default_rng(6)
    if dtype == np.uint8:
        d1, d2 = (rng.integers(0, 256, (20, dim), dtype=np.uint8) for _ in range(2))
    else:
        d1, d2 = (rng.normal(size=(20, dim)).astype(np.float32) for _ in range(2))
    i, j = rng.integers(0, 20, 50), rng.integers(0, 20, 50)
    got = Distances(d1, d2, norm).paired(i, j)
    code = {"l2": cv2.NORM_L2SQR, "l2sqr": cv2.NORM_L2SQR, "l1": cv2.NORM_L1, "hamming": cv2.NORM_HAMMING}[norm]
    ref = [cv2.norm(d1[a].astype(np.float32) if norm != "hamming" else d1[a],
                    d2[b].astype(np.float32) if norm != "hamming" else d2[b], code) for a, b in zip(i, j)]
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-6)


def planted_pairs(g, p1, tol, rng, n):
    """Pairs whose keypoint of image 2 sits at a distance from the segment close to ``tol``, both sides."""
    seg = g.segments(p1, margin=tol)
    ok = np.flatnonzero(seg.valid)
    i = rng.choice(ok, n)
    s = rng.uniform(-0.2, 1.2, n)
    base = seg.start[i] + s[:, None] * (seg.end[i] - seg.start[i])
    normal = seg.line[i, :2]
    off = tol * (1 + rng.choice([-1e-7, -1e-10, 0.0, 1e-10, 1e-7, 0.5, -0.5], n))
    return i, base + off[:, None] * normal


@pytest.mark.parametrize("constraint", ["segment", "line"])
@pytest.mark.parametrize("t", [(-1.0, 0.1, 0.2), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 0.0, 0.0)],
                         ids=["general", "forward", "t3_zero", "pure_rotation"])
def test_filter_pairs_equals_definition_near_the_boundary(constraint, t):
    g = geometry(t=t)
    rng = np.random.default_rng(6)
    p1 = rng.uniform([0, 0], [199, 149], (200, 2))
    p1[0] = g.epipole if np.all(np.isfinite(g.epipole)) and 0 <= g.epipole[0] < 199 and 0 <= g.epipole[1] < 149 \
        else p1[0]  # a query at the epipole of image 1 has an undefined line
    tol = 2.0
    if np.any(g.segments(p1, margin=tol).valid) and np.any(t):
        i, y = planted_pairs(g, p1, tol, rng, 400)
    else:
        i, y = np.zeros(0, dtype=np.intp), np.zeros((0, 2))
    y = np.vstack([y, rng.uniform([0, 0], [199, 149], (400, 2))])
    i = np.r_[i, rng.integers(0, len(p1), 400)]
    pairs = np.column_stack([i, np.arange(len(y))])
    keep = filter_pairs(pairs, p1, y, g, tol=tol, constraint=constraint)
    seg = g.segments(p1, margin=tol).take(i)
    want = seg.distance(y) <= tol if constraint == "segment" else seg.line_distance(y) <= tol
    np.testing.assert_array_equal(keep, want)


@pytest.mark.parametrize("n_pairs", [5, 199, 200, 600], ids=["few", "one_fewer", "as_many", "more"])
def test_filter_pairs_is_the_same_for_few_and_many_pairs(n_pairs):
    """With fewer pairs than queries only the pairs' segments are computed (per-point depth bounds taken
    along); the mask must not depend on that choice."""
    g = geometry()
    rng = np.random.default_rng(11)
    p1 = rng.uniform([0, 0], [199, 149], (200, 2))
    i, y = planted_pairs(g, p1, 2.0, rng, n_pairs)
    zmin, zmax = rng.uniform(0.5, 2.0, len(p1)), rng.uniform(3.0, 50.0, len(p1))
    pairs = np.column_stack([i, np.arange(n_pairs)])
    for depth_range in ((0.0, np.inf), (1.0, 20.0), (zmin, zmax)):
        keep = filter_pairs(pairs, p1, y, g, tol=2.0, depth_range=depth_range)
        zr = tuple(z if np.ndim(z) == 0 else z[i] for z in depth_range)
        want = g.segments(p1[i], zr, margin=2.0).distance(y) <= 2.0
        np.testing.assert_array_equal(keep, want)
        assert keep.any() and not keep.all()


def test_filter_lists_keep_objects_and_rows():
    g = geometry()
    d1, d2, p1, p2 = random_problem(seed=7)
    kp1 = [cv2.KeyPoint(float(x), float(y), 3) for x, y in p1]
    kp2 = [cv2.KeyPoint(float(x), float(y), 3) for x, y in p2]
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=3)  # a tuple of tuples
    m = SegmentMatcher(g, tol=4.0)
    rows = m.filter(knn, kp1, kp2) + m.filter(list(knn[:5]) + [(), []], kp1, kp2)
    flat = [x for r in knn for x in r]
    keep = filter_pairs([(x.queryIdx, x.trainIdx) for x in flat], p1, p2, g, tol=4.0)
    kept = [x for x, k in zip(flat, keep) if k]
    assert [x for r in rows[:len(knn)] for x in r] == kept  # the same objects, in order
    assert all(isinstance(r, list) for r in rows) and rows[-2:] == [[], []]
    with pytest.raises(TypeError, match="cv2.DMatch"):
        m.filter([list(knn[0]), [1, 2]], kp1, kp2)
    with pytest.raises(TypeError, match="cv2.DMatch"):
        m.filter([knn[0][0], "x"], kp1, kp2)


def test_match_returns_dmatch_with_img_idx_zero():
    g = geometry()
    d1, d2, p1, p2 = random_problem(seed=8)
    kp1 = [cv2.KeyPoint(float(x), float(y), 3) for x, y in p1]
    kp2 = [cv2.KeyPoint(float(x), float(y), 3) for x, y in p2]
    m = SegmentMatcher(g, tol=4.0, pad=0)
    out = m.match(d1, d2, kp1, kp2) + [x for r in m.knnMatch(d1, d2, kp1, kp2, k=2) for x in r]
    assert out and all(isinstance(x, cv2.DMatch) and x.imgIdx == 0 for x in out)


def test_finiteness_check_on_huge_finite_values():
    big = np.full((3, 4), 3e38, np.float32)  # finite, but its sum overflows
    d1, d2 = as_descriptor_pair(big, big, "l2")
    assert d1 is not None and d2.shape == (3, 4)
    for bad in (np.nan, np.inf, -np.inf):
        x = big.copy()
        x[1, 2] = bad
        with pytest.raises(ValueError, match="finite"):
            as_descriptor_pair(x, big, "l2")
        y = np.zeros((3, 4), np.float32)
        y[2, 3] = bad
        with pytest.raises(ValueError, match="descriptors2"):
            as_descriptor_pair(np.zeros((3, 4), np.float32), y, "l2")


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("parallel", [False, True])
def test_largest_magnitude_is_numpys_abs_max(dtype, parallel, monkeypatch):
    """The one-pass check (sign bit off, integer maximum) against ``np.abs(a).max()``: random signs and
    magnitudes, signed zeros, subnormals, a strided view, and NaN or inf anywhere, serial and parallel."""
    from episeg_cv import threads
    from episeg_cv._finite_kernels import largest_magnitude
    if parallel:
        monkeypatch.setattr(threads, "MIN_PARALLEL_ITEMS", 1)
    rng = np.random.default_rng(3)
    tiny = np.finfo(dtype).smallest_subnormal
    for trial in range(40):
        n, d = int(rng.integers(1, 40)), int(rng.integers(1, 9))
        a = (rng.standard_normal((n, d)) * 10.0 ** rng.integers(-30, 30, (n, d))).astype(dtype)
        a.flat[rng.integers(0, a.size)] = rng.choice([0.0, -0.0, tiny, -tiny])
        if trial % 3 == 0:
            a = a[:, ::2]  # not contiguous
        assert largest_magnitude(a) == float(np.abs(a).max())
        for bad in (np.inf, -np.inf, np.nan):
            b = a.copy()
            b.flat[rng.integers(0, b.size)] = bad
            got = largest_magnitude(b)
            assert (np.isnan(got) if np.isnan(bad) else got == np.inf), (bad, got)
        c = a.copy()
        c.flat[rng.integers(0, c.size)], c.flat[rng.integers(0, c.size)] = np.inf, np.nan
        assert np.isnan(largest_magnitude(c))  # a NaN wins over an infinity, as in min() and max()
    assert largest_magnitude(np.array([[-0.0]], dtype)) == 0.0


def test_float64_descriptors_beyond_float32_are_refused():
    """Distances are computed in float32 (as cv2 does): 1e308 would silently give no match at all."""
    with pytest.raises(ValueError, match="descriptors1 must fit in float32"):
        as_descriptor_pair(np.full((3, 4), 1e308), np.ones((3, 4)), "l2")
    d1, _ = as_descriptor_pair(np.full((3, 4), 1e6), np.ones((3, 4)), "l2")  # large but fine
    assert d1.dtype == np.float64


@pytest.mark.parametrize("constraint", ["segment", "line"])
def test_bucket_size_changes_speed_only(constraint):
    d1, d2, p1, p2 = random_problem(n1=400, n2=450, seed=8)
    g = geometry()
    ref = guided_matches(d1, d2, p1, p2, g, constraint=constraint)
    for bucket_size in (1, 7, 1000):
        got = guided_matches(d1, d2, p1, p2, g, constraint=constraint, bucket_size=bucket_size)
        np.testing.assert_array_equal(got.pairs, ref.pairs)
        np.testing.assert_array_equal(got.ratio, ref.ratio)
        np.testing.assert_array_equal(got.mutual, ref.mutual)
        np.testing.assert_array_equal(got.candidates, ref.candidates)


def test_knn_ties_go_to_the_smaller_index():
    """Two keypoints of image 2 with the same descriptor, both candidates: the smaller index comes first,
    as in cv2.BFMatcher; and a keypoint's nearest query on a tie is the smaller query index."""
    K = [[100, 0, 50], [0, 100, 50], [0, 0, 1]]
    g = TwoViewGeometry(K, K, np.eye(3), [-1, 0, 0], image_size1=(100, 100), image_size2=(100, 100))
    p1 = np.array([[60.0, 50.0], [60.0, 50.5]])
    p2 = np.array([[10.0, 50.0], [40.0, 50.0], [20.0, 50.0]])  # all on both segments (row y = 50, x < 60)
    d1 = np.array([[1, 0, 0, 0], [1, 0, 0, 0]], dtype=np.float32)
    d2 = np.array([[0, 0, 0, 0], [1, 0, 0, 1], [1, 0, 0, 1]], dtype=np.float32)  # 1 and 2 tie for both queries
    res = knn_descriptors(d1, d2, p1, p2, g, k=3)
    assert res.indices.tolist() == [[0, 1, 2], [0, 1, 2]]
    assert res.column_best.tolist() == [0, 0, 0]


def test_padding_references_are_the_seeded_draw_and_not_shared():
    """The padding references of an int seed are kept between calls: the same draw as a fresh generator, as
    a new array each time (a caller changing it cannot change the next call's)."""
    from episeg_cv.matching.guided import padding_references

    want = np.sort(np.random.default_rng(7).choice(500, 128, replace=False))
    a = padding_references(7, 500, 128)
    np.testing.assert_array_equal(a, want)
    a[:] = -1
    np.testing.assert_array_equal(padding_references(7, 500, 128), want)
    np.testing.assert_array_equal(padding_references(np.int64(7), 500, 128), want)
    assert not np.array_equal(padding_references(8, 500, 128), want)
    gen = padding_references(np.random.default_rng(7), 500, 128)  # a Generator: drawn from it, not kept
    np.testing.assert_array_equal(gen, want)
    assert padding_references(0, 5, 5).tolist() == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError):
        padding_references(-1, 10, 3)
