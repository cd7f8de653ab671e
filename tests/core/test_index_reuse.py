"""An index built once and passed to several calls on the same pair gives the same results, and is checked."""

import cv2
import numpy as np
import pytest

from episeg_cv import (CandidateIndex, SearchConfig, SegmentMatcher, TwoViewGeometry, guided_matches, knn_descriptors,
                       match_descriptors, radius_descriptors)

K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
G = TwoViewGeometry(K, K, cv2.Rodrigues(np.array([[0.0], [0.2], [0.02]]))[0], [-1.0, 0.05, 0.3],
                    image_size1=(320, 240), image_size2=(320, 240))


def problem(n1=600, n2=650, seed=0):
    rng = np.random.default_rng(seed)
    p1 = rng.uniform(0, 239, (n1, 2))
    p2 = rng.uniform(0, 239, (n2, 2))
    d1, d2 = (rng.integers(0, 4, (n, 8)).astype(np.float32) for n in (n1, n2))
    return p1, p2, d1, d2


@pytest.mark.parametrize("constraint", ["segment", "line"])
def test_reused_index_gives_the_same_results(constraint):
    p1, p2, d1, d2 = problem()
    kw = dict(constraint=constraint, tol=3.0)
    index = CandidateIndex(G, p1, p2, search=SearchConfig(**kw))
    for k in (1, 2, 3):
        a = knn_descriptors(d1, d2, p1, p2, G, k=k, **kw)
        b = knn_descriptors(d1, d2, p1, p2, G, k=k, index=index, **kw)
        for x, y in ((a.indices, b.indices), (a.distances, b.distances), (a.counts, b.counts),
                     (a.column_best, b.column_best)):
            np.testing.assert_array_equal(x, y)
    for cc in (False, True):
        for x, y in zip(match_descriptors(d1, d2, p1, p2, G, cross_check=cc, **kw),
                        match_descriptors(d1, d2, p1, p2, G, cross_check=cc, index=index, **kw)):
            np.testing.assert_array_equal(x, y)
    for x, y in zip(radius_descriptors(d1, d2, p1, p2, G, max_distance=2.0, **kw),
                    radius_descriptors(d1, d2, p1, p2, G, max_distance=2.0, index=index, **kw)):
        np.testing.assert_array_equal(x, y)
    a, b = guided_matches(d1, d2, p1, p2, G, **kw), guided_matches(d1, d2, p1, p2, G, index=index, **kw)
    np.testing.assert_array_equal(a.pairs, b.pairs)
    np.testing.assert_array_equal(a.ratio, b.ratio)


def test_an_index_that_does_not_fit_is_refused():
    p1, p2, d1, d2 = problem()
    index = CandidateIndex(G, p1, p2, tol=2.0)
    with pytest.raises(ValueError, match="other points1"):
        knn_descriptors(d1[:-1], d2, p1[:-1], p2, G, index=index)
    moved = p2.copy()
    moved[3, 0] += 1
    with pytest.raises(ValueError, match="other points2"):
        match_descriptors(d1, d2, p1, moved, G, index=index)
    with pytest.raises(ValueError, match="built for SearchConfig"):
        match_descriptors(d1, d2, p1, p2, G, index=index, tol=3.0)
    with pytest.raises(ValueError, match="another geometry"):
        match_descriptors(d1, d2, p1, p2, G.inverse(), index=index)
    with pytest.raises(TypeError, match="index must be a CandidateIndex or None"):
        knn_descriptors(d1, d2, p1, p2, G, index="index")
    # an equal geometry built again is the same geometry
    same = TwoViewGeometry(G.K1, G.K2, G.R, G.t, image_size1=G.image_size1, image_size2=G.image_size2)
    assert len(knn_descriptors(d1, d2, p1, p2, same, index=index).indices) == len(p1)


def test_segment_matcher_index():
    p1, p2, d1, d2 = problem(seed=1)
    kp1 = [cv2.KeyPoint(float(x), float(y), 3) for x, y in p1]
    kp2 = [cv2.KeyPoint(float(x), float(y), 3) for x, y in p2]
    m = SegmentMatcher(G, cv2.NORM_L2, ratio=0.9)
    index = m.index(kp1, kp2)
    assert isinstance(index, CandidateIndex)

    def key(matches):
        return [(d.queryIdx, d.trainIdx, d.distance) for d in matches]

    assert key(m.match(d1, d2, kp1, kp2, index=index)) == key(m.match(d1, d2, kp1, kp2))
    assert [key(r) for r in m.knnMatch(d1, d2, kp1, kp2, k=2, index=index)] == \
        [key(r) for r in m.knnMatch(d1, d2, kp1, kp2, k=2)]
    assert [key(r) for r in m.radiusMatch(d1, d2, kp1, kp2, 2.0, index=index)] == \
        [key(r) for r in m.radiusMatch(d1, d2, kp1, kp2, 2.0)]
    with pytest.raises(ValueError, match="built for SearchConfig"):
        SegmentMatcher(G, cv2.NORM_L2, tol=5).match(d1, d2, kp1, kp2, index=index)
    none = SegmentMatcher(G, cv2.NORM_L2, constraint="none")
    with pytest.raises(ValueError, match="no candidate index"):
        none.index(kp1, kp2)
    with pytest.raises(ValueError, match="index must be None"):
        none.match(d1, d2, kp1, kp2, index=index)
