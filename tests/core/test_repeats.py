"""Repeated structure: matches whose keypoints have a twin inside the same band (matching/repeats.py)."""

import numpy as np
import pytest

from episeg_cv import SearchConfig, TwoViewGeometry, match_descriptors
from episeg_cv.matching import MatchInputs
from episeg_cv.matching.repeats import ambiguous, twin_distances

K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
G = TwoViewGeometry(K, K, np.eye(3), [-1, 0, 0], image_size1=(100, 100), image_size2=(100, 100))  # rows


def _inputs(d1, d2, p1, p2):
    return MatchInputs.check(np.asarray(d1, np.float32), np.asarray(d2, np.float32), np.asarray(p1, float),
                             np.asarray(p2, float), "l2")


def test_twins_by_hand():
    """Query (60, 50) matched to (40, 50) at distance 1; image 2 has a keypoint 1.8 away in descriptor space
    on the same row (the band), one 0.5 away off the row, one 0.3 away 1 px from the match (the same point);
    image 1 has a keypoint 2.5 away on the row of the match (its reverse band)."""
    d1 = [[0, 0], [0, 2.5], [9, 9]]
    p1 = [[60.0, 50.0], [90.0, 50.0], [20.0, 20.0]]
    d2 = [[1, 0], [0, 1.5], [1, 0.5], [1.3, 0]]
    p2 = [[40.0, 50.0], [20.0, 50.0], [30.0, 80.0], [41.0, 50.0]]
    inputs = _inputs(d1, d2, p1, p2)
    pairs = np.array([[0, 0]])
    tw = twin_distances(inputs, pairs, G, SearchConfig(tol=2.0))
    assert tw[0] == pytest.approx(np.hypot(1, 1.5))  # not the 0.5 off the band, not the 0.3 at the same place
    assert not ambiguous(inputs, pairs, G, SearchConfig(tol=2.0), 0.8)[0]  # 1 < 0.8 * 1.80
    assert ambiguous(inputs, pairs, G, SearchConfig(tol=2.0), 0.5)[0]  # 1 >= 0.5 * 1.80
    # a closer twin in image 1, on the reverse band of the match (row 50, right of x = 40)
    inputs = _inputs([[0, 0], [0, 1.1], [9, 9]], d2, p1, p2)
    assert twin_distances(inputs, pairs, G, SearchConfig(tol=2.0))[0] == pytest.approx(1.1)
    assert ambiguous(inputs, pairs, G, SearchConfig(tol=2.0), 0.8)[0]


def test_edge_cases():
    inputs = _inputs([[0, 0]], [[1, 0]], [[60.0, 50.0]], [[40.0, 50.0]])
    empty = np.zeros((0, 2), np.intp)
    assert ambiguous(inputs, empty, G, SearchConfig(), 0.8).shape == (0,)
    assert twin_distances(inputs, np.array([[0, 0]]), G, SearchConfig())[0] == np.inf  # nothing else: no twin
    assert not ambiguous(inputs, np.array([[0, 0]]), G, SearchConfig(), 0.8)[0]


def test_a_periodic_wall_is_ambiguous_and_unique_points_are_not():
    """A wall at depth 5 tiled with one motif every 0.5 m (20 px) along the rows, seen by a sideways move:
    every copy of the motif lies on the row of every other. Each view adds its own descriptor noise (the
    viewpoint) that is larger than the copies' differences: the wall's matches are ambiguous, those of
    unique points scattered at other depths are not."""
    rng = np.random.default_rng(0)
    xs, ys = np.meshgrid(np.arange(-2.0, 2.01, 0.2), np.arange(-1.5, 1.51, 0.5))
    wall = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, 5.0)])
    unique = np.column_stack([rng.uniform(-2, 2, 40), rng.uniform(-1.5, 1.5, 40), rng.uniform(3, 8, 40)])
    X = np.vstack([wall, unique])
    motif = rng.normal(0, 1, 64)
    base = np.vstack([motif + rng.normal(0, 0.05, (len(wall), 64)), rng.normal(0, 1, (len(unique), 64))])
    p1 = X[:, :2] / X[:, 2:] * 100 + 50
    p2 = (X[:, :2] - [1, 0]) / X[:, 2:] * 100 + 50
    ok = np.all((p1 > 0) & (p1 < 99) & (p2 > 0) & (p2 < 99), axis=1)
    d1 = base + rng.normal(0, 0.2, base.shape)
    d2 = base + rng.normal(0, 0.2, base.shape)
    d1, d2, p1, p2 = d1[ok], d2[ok], p1[ok], p2[ok]
    n_wall = int(ok[:len(wall)].sum())
    pairs = np.column_stack([np.arange(len(p1)), np.arange(len(p1))])  # the true matches
    amb = ambiguous(_inputs(d1, d2, p1, p2), pairs, G, SearchConfig(), 0.8)
    assert amb[:n_wall].all() and not amb[n_wall:].any()
    # what the matcher returns on the wall is largely wrong; what survives the test is right
    found, _ = match_descriptors(d1.astype(np.float32), d2.astype(np.float32), p1, p2, G, ratio=1.0)
    keep = ~ambiguous(_inputs(d1, d2, p1, p2), found, G, SearchConfig(), 0.8)
    right = found[:, 0] == found[:, 1]
    assert right[found[:, 0] < n_wall].mean() < 0.5 and right[keep].all() and keep.sum() >= 0.9 * (len(p1) - n_wall)
