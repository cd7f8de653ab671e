"""The track consensus (issue 14): candidate matches of a collection verified with the known poses.

Needs no pycolmap: views, candidates and keypoints are built here.
"""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from episeg_cv import scenes
from episeg_cv.colmap import TrackConsensus, View, verify_tracks
from episeg_cv.colmap.consensus import MIN_VIEW_CANDIDATES, SUSPECT_FRACTION, projection_matrices, suspect_views

K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
SIZE = (640, 480)


def _ring(n, radius=4.0):
    """n cameras on a circle around the origin, all looking at it."""
    views = []
    for k in range(n):
        a = 2 * np.pi * k / n * 0.25  # a quarter circle: every camera sees the centre
        R, t = scenes.look_at([radius * np.sin(a), 0.3 * k, -radius * np.cos(a)], [0, 0, 0])
        views.append(View(f"v{k}.png", k + 1, 1, K, R, t, SIZE))
    return views


def _project(views, X):
    """(n_views, n_points, 2) pixels."""
    return np.stack([(X @ v.R.T + v.t) @ K.T for v in views])[..., :2] / \
        np.stack([(X @ v.R.T + v.t)[:, 2:] for v in views])


def _scene(n_views=4, n_points=30, seed=0):
    rng = np.random.default_rng(seed)
    views = _ring(n_views)
    X = rng.uniform(-0.5, 0.5, (n_points, 3))
    kp = _project(views, X)  # keypoint p of view k is the projection of point p
    return views, X, kp


def _all_pairs(n_views, n_points, ratio=0.5, drop=()):
    """Every true match of every pair, ratio ``ratio``."""
    out = []
    for i in range(n_views):
        for j in range(i + 1, n_views):
            idx = np.array([p for p in range(n_points) if (i, j, p) not in drop], dtype=np.int64)
            out.append((i, j, np.column_stack([idx, idx]), np.full(len(idx), ratio)))
    return out


# --------------------------------------------------------------------------------------
# Hand-made cases
# --------------------------------------------------------------------------------------
def test_true_tracks_are_kept_at_any_ratio_with_three_views():
    views, _, kp = _scene()
    cands = _all_pairs(4, 30, ratio=0.85)  # loose, but every track spans 4 views
    keep, stats = verify_tracks(views, cands, lambda k: kp[k], strict=0.68, tau=2.0)
    assert all(k.all() for k in keep)
    assert stats["groups"] == 30 and stats["components"] == 30 and stats["kept"] == stats["edges"] == 6 * 30


def test_loose_edges_of_two_views_need_a_third():
    views, _, kp = _scene(n_views=2)
    strict = (0, 1, np.array([[0, 0], [1, 1]]), np.array([0.5, 0.6]))
    keep, _ = verify_tracks(views, [strict], lambda k: kp[k], strict=0.68, tau=2.0)
    assert keep[0].tolist() == [True, True]
    loose = (0, 1, np.array([[0, 0], [1, 1]]), np.array([0.7, 0.89]))
    keep, _ = verify_tracks(views, [loose], lambda k: kp[k], strict=0.68, tau=2.0)
    assert keep[0].tolist() == [False, False]
    keep, _ = verify_tracks(views, [loose], lambda k: kp[k], strict=0.68, tau=2.0,
                            config=TrackConsensus(min_views=2))
    assert keep[0].tolist() == [True, True]


def test_a_false_edge_between_two_tracks_is_dropped_and_the_tracks_survive():
    views, _, kp = _scene(n_views=4, n_points=2)
    cands = _all_pairs(4, 2, ratio=0.5)
    # one false, even strict, match: point 0 in view 0 with point 1 in view 3
    i, j, p, r = cands[2]  # the pair (0, 3)
    assert (i, j) == (0, 3)
    cands[2] = (i, j, np.vstack([p, [[0, 1]]]), np.append(r, 0.3))
    keep, stats = verify_tracks(views, cands, lambda k: kp[k], strict=0.68, tau=2.0)
    assert keep[2].tolist() == [True, True, False]  # the lowest ratio of all, still contradicted by the tracks
    assert all(k.all() for q, k in enumerate(keep) if q != 2)
    assert stats["components"] == 1 and stats["groups"] == 2


def test_a_keypoint_off_its_track_is_left_out():
    views, _, kp = _scene(n_views=4, n_points=1)
    kp = kp.copy()
    kp[3, 0] += [6.0, -4.0]  # view 3 observes the point 7 px off: beyond tau
    keep, _ = verify_tracks(views, _all_pairs(4, 1, ratio=0.8), lambda k: kp[k], strict=0.68, tau=2.0)
    pairs = [(i, j) for i in range(4) for j in range(i + 1, 4)]
    assert {pq: bool(k[0]) for pq, k in zip(pairs, keep)} == {
        (0, 1): True, (0, 2): True, (1, 2): True, (0, 3): False, (1, 3): False, (2, 3): False}
    keep, _ = verify_tracks(views, _all_pairs(4, 1, ratio=0.8), lambda k: kp[k], strict=0.68, tau=8.0)
    assert all(k.all() for k in keep)


def test_points_behind_a_camera_do_not_count():
    views, _, kp = _scene(n_views=3, n_points=1)
    behind = views[2].R.T @ (np.array([0, 0, -2.0]) - views[2].t)  # 2 m behind camera 2, on its axis
    kp = kp.copy()
    for k in range(2):
        Xc = views[k].R @ behind + views[k].t
        kp[k, 0] = (K @ Xc)[:2] / Xc[2]
    kp[2, 0] = K[:2, 2]  # where the point's mirror image would project
    keep, _ = verify_tracks(views, _all_pairs(3, 1, ratio=0.8), lambda k: kp[k], strict=0.68, tau=2.0)
    assert keep[0].tolist() == [False] and not keep[1].any() and not keep[2].any()


def test_empty_candidates_and_empty_pairs():
    views, _, kp = _scene(n_views=3)
    keep, stats = verify_tracks(views, [], lambda k: kp[k], strict=0.68, tau=2.0)
    assert keep == [] and stats["edges"] == 0
    empty = (0, 1, np.zeros((0, 2), np.int64), np.zeros(0))
    keep, stats = verify_tracks(views, [empty, _all_pairs(3, 30)[2]], lambda k: kp[k], strict=0.68, tau=2.0)
    assert keep[0].shape == (0,) and keep[1].all() and stats["edges"] == 30


def test_tracks_chained_into_one_component_are_each_verified():
    """False loose edges chain 40 tracks into one component of 200 observations: each track is still found
    (the seeds of a round are the edges around its lowest-ratio edge), with a neighbourhood of any size."""
    views, _, kp = _scene(n_views=5, n_points=40, seed=3)
    cands = _all_pairs(5, 40, ratio=0.5)
    i, j, p, r = cands[0]
    chain = np.column_stack([np.arange(39), np.arange(1, 40)])
    cands[0] = (i, j, np.vstack([p, chain]), np.append(r, np.full(39, 0.85)))
    for config in (TrackConsensus(), TrackConsensus(neighbourhood=4, hops=1)):
        keep, stats = verify_tracks(views, cands, lambda k: kp[k], strict=0.68, tau=2.0, config=config)
        assert stats["components"] == 1 and stats["groups"] == 40
        assert keep[0][:40].all() and not keep[0][40:].any()  # the true matches, not the chain
        assert all(k.all() for k in keep[1:])


def test_the_tightest_of_two_equally_supported_seeds_wins():
    """MSAC's score: a wrong keypoint b* (1 px along the epipolar line from b) makes a seed a-b* whose
    point still lands within tau of c, as many observations as the true seed a-b; its lower ratio does not
    let it win, the tighter fit does."""
    from episeg_cv.colmap.consensus import _normalised

    views, X, kp = _scene(n_views=3, n_points=1, seed=1)
    kp = kp.copy()
    e = _epipolar_direction(views[0], views[1], X[0])
    kp1 = np.vstack([kp[1], kp[1, 0] + 1.0 * e])  # keypoint 1 of view 1: b*
    pts = {0: kp[0], 1: kp1, 2: kp[2]}
    cands = [(0, 1, np.array([[0, 1], [0, 0]]), np.array([0.3, 0.4])),  # a-b* (lower ratio), a-b
             (0, 2, np.array([[0, 0]]), np.array([0.5])), (1, 2, np.array([[0, 0], [1, 0]]), np.array([0.5, 0.6]))]
    # the premise: seen from a-b*, c is within tau too (so counting alone would take a-b*, the first seed)
    P, _ = _normalised(views)
    Xs = _two_view_point(P[0], P[1], pts[0][0], pts[1][1])
    h = P[2] @ np.append(Xs, 1.0)
    assert 0.5 < np.hypot(*(h[:2] / h[2] - pts[2][0])) <= 2.0
    keep, stats = verify_tracks(views, cands, lambda k: pts[k], strict=0.68, tau=2.0,
                                config=TrackConsensus(min_views=3))
    assert [k.tolist() for k in keep] == [[False, True], [True], [True, False]]
    assert stats["groups"] == 1


def test_support_grows_along_the_edges_only():
    """An observation that lands on the track's point but is linked to it only through an observation that
    does not (a false match) is not part of the track's group."""
    from episeg_cv.colmap import _consensus_kernel
    from episeg_cv.colmap.consensus import _normalised

    views, _, kp = _scene(n_views=4, n_points=2, seed=4)
    # nodes: a, b, c (point 0 in views 0-2), e (point 1 in view 1, far from point 0), d (point 0 in view 3)
    node_image = np.array([0, 1, 2, 1, 3])
    node_xy = np.array([kp[0, 0], kp[1, 0], kp[2, 0], kp[1, 1], kp[3, 0]])
    assert np.hypot(*(kp[1, 1] - kp[1, 0])) > 20
    eu, ev = np.array([0, 1, 0, 3]), np.array([1, 2, 3, 4])  # a-b, b-c, a-e (false), e-d (false)
    er = np.array([0.3, 0.5, 0.7, 0.9])
    P, centers = _normalised(views)
    group, group_views, stats = _consensus_kernel.consensus(P, centers, node_image, node_xy, eu, ev, er, 4, 2.0,
                                                            np.cos(np.radians(1.5)), 24, 1000, 2)
    assert group[0] == group[1] == group[2] >= 0 and group[4] != group[0]
    assert group_views[group[0]] == 3 and stats[0] == 1


def test_views_from_one_place_count_once():
    """Two images taken from the same place (a rotation apart) and a third: a loose track over the three
    spans two distinct views, so its loose edges need another view; its strict edge is kept."""
    views = _ring(3)
    R, t = scenes.look_at(views[0].center, [0.4, 0.2, 0.0])  # the same centre as view 0, turned
    views[1] = View("v1.png", 2, 1, K, R, t, SIZE)
    X = np.array([[0.05, -0.1, 0.1]])
    kp = _project(views, X)
    assert np.all((kp > 0) & (kp < SIZE))
    cands = [(0, 1, np.array([[0, 0]]), np.array([0.5])), (0, 2, np.array([[0, 0]]), np.array([0.8])),
             (1, 2, np.array([[0, 0]]), np.array([0.8]))]
    keep, _ = verify_tracks(views, cands, lambda k: kp[k], strict=0.68, tau=2.0)
    assert [k.tolist() for k in keep] == [[True], [False], [False]]
    keep, _ = verify_tracks(views, cands, lambda k: kp[k], strict=0.68, tau=2.0, config=TrackConsensus(min_angle=0))
    assert all(k.all() for k in keep)


def test_a_synthetic_collection_with_false_matches_and_a_repeated_viewpoint():
    """Six views (one taken again from the place of another), 80 points seen with 0.3 px noise, every true
    match at a loose ratio, 8 % of the matches replaced by a wrong keypoint (chaining the tracks into a few
    big components): no false match is kept, and almost every true one is."""
    rng = np.random.default_rng(11)
    views = _ring(5)
    R, t = scenes.look_at(views[2].center, [0.3, -0.2, 0.1])
    views.append(View("v5.png", 6, 1, K, R, t, SIZE))  # view 5: from the place of view 2
    X = rng.uniform(-0.4, 0.4, (80, 3))
    kp = _project(views, X) + rng.uniform(-0.3, 0.3, (6, 80, 2))
    cands, truth = [], []
    for i in range(6):
        for j in range(i + 1, 6):
            p = np.column_stack([np.arange(80), np.arange(80)])
            false = rng.random(80) < 0.08
            p[false, 1] = (p[false, 1] + rng.integers(1, 80, int(false.sum()))) % 80
            cands.append((i, j, p, rng.uniform(0.7, 0.99, 80)))
            truth.append(~false)
    keep, stats = verify_tracks(views, cands, lambda k: kp[k], strict=0.68, tau=1.5)
    kept = np.concatenate(keep)
    true = np.concatenate(truth)
    assert stats["components"] < 20 and not (kept & ~true).any()
    assert kept[true].mean() > 0.95 and stats["groups"] >= 80


def _epipolar_direction(v1, v2, X):
    """Unit direction, in view 2, of the epipolar line of X's projection in view 1, at X's projection."""
    C1 = v1.center
    p = [(K @ (v2.R @ Y + v2.t)) for Y in (X, X + 0.1 * (X - C1))]
    d = p[1][:2] / p[1][2] - p[0][:2] / p[0][2]
    return d / np.linalg.norm(d)


def _two_view_point(P1, P2, x1, x2):
    A = np.array([x1[0] * P1[2] - P1[0], x1[1] * P1[2] - P1[1], x2[0] * P2[2] - P2[0], x2[1] * P2[2] - P2[1]])
    A /= np.linalg.norm(A, axis=1, keepdims=True)
    return np.linalg.solve(A[:, :3].T @ A[:, :3], -A[:, :3].T @ A[:, 3])


@pytest.mark.parametrize("cands, error, match", [
    ([(0, 0, [[0, 0]], [0.5])], ValueError, "i = j"),
    ([(0, 3, [[0, 0]], [0.5])], ValueError, "view index j"),
    ([(-1, 1, [[0, 0]], [0.5])], ValueError, "view index i"),
    ([(0.0, 1, [[0, 0]], [0.5])], ValueError, "view index i"),
    ([(0, 1, [0, 0], [0.5])], ValueError, "pairs"),
    ([(0, 1, [[0, -1]], [0.5])], ValueError, ">= 0"),
    ([(0, 1, [[0, 0]], [0.5, 0.6])], ValueError, "ratio"),
    ([(0, 1, [[0, 0]], [np.nan])], ValueError, "NaN"),
    ([(0, 1, [[0, 0]], ["x"])], TypeError, "ratio"),
    ([(0, 1, [[0, 0]])], TypeError, "tuple"),
    ([(0, 1, [[0, 0]], [0.5], [True])], TypeError, "tuple"),
    ([(0, 1, [[0, 99]], [0.5])], ValueError, "keypoint 99 of view 1 is beyond its 5"),
    ([(0, 1, [[0, 0]], [0.5]), (2, 0, [[1, 0], [7, 2]], [0.5, 0.5])], ValueError, "keypoint 7 of view 2 is beyond"),
])
def test_bad_candidates_are_refused(cands, error, match):
    views, _, kp = _scene(n_views=3, n_points=5)
    with pytest.raises(error, match=match):
        verify_tracks(views, cands, lambda k: kp[k], strict=0.68, tau=2.0)


@pytest.mark.parametrize("bad, match", [
    ((np.array([[0, 0], [1, 1]], np.int64), np.array([0.5, np.nan])), r"candidates\[1\] ratio must not be NaN"),
    ((np.array([[0, 0], [1, -3]], np.int64), np.array([0.5, 0.5])), r"candidates\[1\] pairs .* got -3"),
    ((np.array([[0, 0], [1, 1]], np.int64), np.array([0.5])), r"candidates\[1\] ratio must have shape"),
    ((np.array([[0, 0, 0]], np.int64), np.array([0.5])), r"candidates\[1\] pairs must have shape"),
])
def test_bad_candidate_arrays_are_refused_by_index(bad, match):
    """Arrays (as the pipeline passes them) are checked once, concatenated: the error still names the
    candidate; a wrong shape or ratio length takes the one-by-one checks."""
    views, _, kp = _scene(n_views=3, n_points=5)
    good = (0, 1, np.array([[0, 0], [2, 2]], np.uint32), np.array([0.5, 0.6]))
    cands = [good, (1, 2, *bad), good]
    with pytest.raises(ValueError, match=match):
        verify_tracks(views, cands, lambda k: kp[k], strict=0.68, tau=2.0)


def test_candidate_arrays_and_lists_give_the_same_result():
    """uint32 pairs and float32 ratios (arrays, taken as they are) and plain lists of the same values (checked
    one by one) are the same candidates."""
    views, _, kp = _scene(n_views=4, n_points=30)
    rng = np.random.default_rng(3)
    arrays = [(np.int64(i), j, np.repeat(np.arange(30, dtype=np.uint32)[:, None], 2, axis=1),
               rng.uniform(0.1, 0.9, 30).astype(np.float32)) for i in range(4) for j in range(i + 1, 4)]
    lists = [(int(i), j, p.tolist(), r.tolist()) for i, j, p, r in arrays]
    a = verify_tracks(views, lists, lambda k: kp[k], strict=0.68, tau=2.0)
    b = verify_tracks(views, arrays, lambda k: kp[k], strict=0.68, tau=2.0)
    assert len(a[0]) == len(b[0]) == len(lists)
    assert all(np.array_equal(x, y) for x, y in zip(a[0], b[0])) and a[1] == b[1]


@pytest.mark.parametrize("seed", range(4))
def test_observations_are_numbered_as_np_unique(seed):
    """Property: the compiled dense numbering of the candidates' ends is ``np.unique``'s of the
    (image, keypoint) keys, with repeated ends, views without candidates and empty input."""
    from episeg_cv.colmap import _consensus_kernel as kernel

    rng = np.random.default_rng(seed)
    counts = rng.integers(0, 30, 6)
    counts[seed % 6] = 0
    start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    live = np.flatnonzero(counts)
    m = int(rng.integers(0, 200)) if seed else 0
    img_a, img_b = rng.choice(live, m), rng.choice(live, m)
    pairs = np.column_stack([rng.integers(0, counts[img_a]), rng.integers(0, counts[img_b])]).astype(np.int64)
    eu, ev, node_image, node_kp = kernel.number_observations(img_a.astype(np.int64), img_b.astype(np.int64),
                                                             pairs.reshape(-1, 2), start)
    keys = np.concatenate([start[img_a] + pairs[:, 0], start[img_b] + pairs[:, 1]]).astype(np.int64)
    uniq, inv = np.unique(keys, return_inverse=True)
    assert np.array_equal(np.concatenate([eu, ev]), inv) and eu.dtype == np.int64
    img = np.searchsorted(start, uniq, side="right") - 1
    assert np.array_equal(node_image, img) and np.array_equal(node_kp, uniq - start[img])


@pytest.mark.parametrize("tau", [0.0, -1.0, float("inf"), float("nan"), "2"])
def test_bad_tau_is_refused(tau):
    views, _, kp = _scene(n_views=3, n_points=5)
    with pytest.raises(ValueError, match="tau"):
        verify_tracks(views, _all_pairs(3, 5), lambda k: kp[k], strict=0.68, tau=tau)


def test_projection_matrices_are_normalised():
    views = _ring(4, radius=1000.0)
    P = projection_matrices(views)
    X = np.array([[0.3, -0.2, 0.1]])
    centers = np.array([v.center for v in views])
    c0, s = centers.mean(0), np.median(np.linalg.norm(centers - centers.mean(0), axis=1))
    Y = (X - c0) / s
    for v, Pk in zip(views, P):
        h = Pk @ np.append(Y[0], 1.0)
        Xc = v.R @ X[0] + v.t
        np.testing.assert_allclose(h[:2] / h[2], (K @ Xc)[:2] / Xc[2], rtol=1e-9)


@pytest.mark.parametrize("kwargs, match", [
    ({"loose": 1.5}, "loose"), ({"loose": 0}, "loose"), ({"min_views": 1}, "min_views"),
    ({"tau": -1.0}, "tau"), ({"tau": float("nan")}, "tau"), ({"max_seeds": 0}, "max_seeds"),
    ({"neighbourhood": 1}, "neighbourhood"), ({"hops": 0}, "hops"), ({"min_views": 2.5}, "min_views"),
    ({"min_angle": -1.0}, "min_angle"), ({"min_angle": 90}, "min_angle"), ({"min_angle": "1"}, "min_angle"),
    ({"tau": True}, "tau"),
])
def test_config_is_checked(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TrackConsensus(**kwargs)


# --------------------------------------------------------------------------------------
# Properties
# --------------------------------------------------------------------------------------
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n_views=st.integers(3, 6), noise=st.floats(0.0, 0.8))
def test_consistent_tracks_are_kept_and_the_order_of_pairs_does_not_matter(seed, n_views, noise):
    """Keypoints up to ``noise`` px (a disc) from their projections, at most 0.4 tau. Not tau / 2: the
    triangulated point's error in one view can exceed every keypoint's offset (a least-squares point), and
    with offsets up to 1 px hypothesis found seed 300 (4 views) where one reprojects beyond tau; a sweep of
    900 scenes found 6 such at a 1.0 px radius and none at 0.8."""
    views, _, kp = _scene(n_views=n_views, n_points=12, seed=seed)
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0.0, 2.0 * np.pi, kp.shape[:-1])
    radius = noise * np.sqrt(rng.uniform(0.0, 1.0, kp.shape[:-1]))
    kp = kp + np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=-1)
    cands = _all_pairs(n_views, 12, ratio=0.85)
    cands = [(i, j, p, r + rng.uniform(-0.1, 0.04, len(r))) for i, j, p, r in cands]  # distinct ratios
    keep, _ = verify_tracks(views, cands, lambda k: kp[k], strict=0.68, tau=2.0)
    assert all(k.all() for k in keep)
    order = rng.permutation(len(cands))
    shuffled, _ = verify_tracks(views, [cands[q] for q in order], lambda k: kp[k], strict=0.68, tau=2.0)
    for q, k in zip(order, shuffled):
        np.testing.assert_array_equal(k, keep[q])


@pytest.mark.parametrize("wrong, neighbourhood", [(0.002, 1000), (0.15, 3)])  # 3: seeds from tiny neighbourhoods
def test_components_on_threads_give_the_serial_result(wrong, neighbourhood):
    """Thousands of edges: the kernel runs its parallel twin (blocks of components); the kept matches,
    the groups (numbered in component order) and the counts must be those of one thread, with false
    edges, tied ratios and components of every size among them."""
    import episeg_cv
    from episeg_cv.colmap import _consensus_kernel
    from episeg_cv.colmap.consensus import _normalised

    views, _, kp = _scene(n_views=6, n_points=400, seed=3)
    rng = np.random.default_rng(8)
    kp = kp + rng.uniform(-0.5, 0.5, kp.shape)
    cands = []
    for i, j, p, r in _all_pairs(6, 400, ratio=0.5):
        false = rng.random(len(p)) < wrong  # false edges: to a random keypoint, merging tracks
        p = p.copy()
        p[false, 1] = rng.integers(0, 400, int(false.sum()))
        cands.append((i, j, p, np.round(rng.uniform(0.3, 0.89, len(p)), 2)))  # rounded: many ties
    assert sum(len(p) for _, _, p, _ in cands) >= episeg_cv.threads.MIN_PARALLEL_ITEMS
    config = TrackConsensus(neighbourhood=neighbourhood)
    calls = []
    real = _consensus_kernel.consensus_parallel

    def spy(*args):
        calls.append(args[-1])
        return real(*args)

    runs = {}
    for n in (1, 2):
        episeg_cv.set_num_threads(n)
        try:
            _consensus_kernel.consensus_parallel = spy
            runs[n] = verify_tracks(views, cands, lambda k: kp[k], strict=0.68, tau=2.0, config=config)
        finally:
            _consensus_kernel.consensus_parallel = real
            episeg_cv.set_num_threads(None)
    if episeg_cv.threads.get_num_threads() > 1:
        assert calls, "the parallel twin did not run"
    (k1, s1), (k2, s2) = runs[1], runs[2]
    assert s1 == s2 and s1["groups"] > 100
    assert s1["components"] < 50 if wrong > 0.1 else s1["components"] > 100
    for a, b in zip(k1, k2):
        np.testing.assert_array_equal(a, b)
    # and the kernel's own outputs, group by group
    P, centers = _normalised(views)
    node_image = np.repeat(np.arange(6), 400)
    node_xy = kp.reshape(-1, 2)
    eu = np.concatenate([i * 400 + p[:, 0] for i, _, p, _ in cands])
    ev = np.concatenate([j * 400 + p[:, 1] for _, j, p, _ in cands])
    er = np.concatenate([r for _, _, _, r in cands])
    args = (P, centers, node_image, node_xy, eu, ev, er, 6, 2.0, np.cos(np.radians(1.5)), 24, neighbourhood, 2)
    serial = _consensus_kernel.consensus(*args)
    for blocks in (1, 3, 16, 64):
        par = _consensus_kernel.consensus_parallel(*args, blocks)
        for a, b in zip(serial, par):
            np.testing.assert_array_equal(a, b)


def _reference_groups(P, centers, node_image, node_xy, eu, ev, er, n_images, tau, cos_min_angle, max_seeds,
                      neighbourhood, hops):
    """The consensus of the module docstring, plainly: every seed of a round scored (no support bounds),
    every edge scanned each round. ``(group per node, -1 where none; local numbering, views per group)``."""
    n, m = len(node_image), len(eu)
    parent = list(range(n))

    def find(x):
        while parent[x] != x:
            x = parent[x]
        return x

    for a, b in zip(eu, ev):
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[ra] = rb
    adj = [[] for _ in range(n)]  # (edge, other end), in edge order
    for k, (a, b) in enumerate(zip(eu, ev)):
        adj[a].append((k, b))
        adj[b].append((k, a))
    alive, dead, group, views, gid = np.ones(n, bool), np.zeros(m, bool), np.full(n, -1), [], 0

    def triangulate(nodes):
        A = []
        for v in nodes:
            Pk = P[node_image[v]]
            for r in range(2):
                a = node_xy[v, r] * Pk[2] - Pk[r]
                if np.linalg.norm(a) > 0:
                    A.append(a / np.linalg.norm(a))
        A = np.array(A)
        N = A[:, :3].T @ A[:, :3]
        if not abs(np.linalg.det(N)) > 1e-12 * (np.trace(N) / 3) ** 3:
            return None
        return np.linalg.solve(N, -A[:, :3].T @ A[:, 3])

    def support(X, a, b):  # breadth first along the edges, through alive observations within tau
        queue, seen, best = [], set(), {}
        for s in (a, b):
            if s not in seen:
                seen.add(s)
                queue.append(s)
        for v in queue:
            h = P[node_image[v]] @ np.append(X, 1.0)
            if not h[2] > 0:
                continue
            err = np.hypot(h[0] / h[2] - node_xy[v, 0], h[1] / h[2] - node_xy[v, 1])
            if not err <= tau:
                continue
            k = node_image[v]
            if k not in best or err < best[k][0]:
                best[k] = (err, v)
            for _, w in adj[v]:
                if w not in seen and alive[w]:
                    seen.add(w)
                    queue.append(w)
        return [v for _, v in best.values()], sum(1 - (e / tau) ** 2 for e, _ in best.values())

    def window(e0):
        queue, depth, seen = [], [], set()
        for s in (eu[e0], ev[e0]):
            if s not in seen:
                seen.add(s)
                queue.append(s)
                depth.append(0)
        head = 0
        while head < len(queue) < neighbourhood:
            v, d = queue[head], depth[head]
            head += 1
            for _, w in adj[v] if d < hops else ():
                if w not in seen and alive[w]:
                    seen.add(w)
                    queue.append(w)
                    depth.append(d + 1)
                    if len(queue) >= neighbourhood:
                        break
        return seen

    def distinct(X, nodes):
        dirs = []
        for v in nodes:
            d = centers[node_image[v]] - X
            d = d / np.linalg.norm(d)
            if all(d @ e <= cos_min_angle for e in dirs):
                dirs.append(d)
        return len(dirs)

    order = sorted(range(m), key=lambda k: (er[k], k))
    for root in sorted({find(v) for v in range(n)}):
        edges = [k for k in order if find(eu[k]) == root]
        while True:
            live = [k for k in edges if alive[eu[k]] and alive[ev[k]] and not dead[k]]
            if not live:
                break
            near = window(live[0])
            seeds = [live[0]] + [k for k in live[1:] if eu[k] in near and ev[k] in near][:max_seeds - 1]
            best, best_score, best_seed = [], 0.0, None
            for k in seeds:
                X = triangulate([eu[k], ev[k]])
                if X is None:
                    continue
                got, score = support(X, eu[k], ev[k])
                if len(got) >= 2 and score > best_score:
                    best, best_score, best_seed = got, score, k
            if best_seed is None:
                dead[seeds] = True
                continue
            X = triangulate(best)
            if X is not None:
                again, _ = support(X, eu[best_seed], ev[best_seed])
                if len(again) >= 2:
                    best = again
                    X = triangulate(best)
            else:
                X = triangulate([eu[best_seed], ev[best_seed]])
            group[best] = gid
            alive[best] = False
            views.append(distinct(X, best))
            gid += 1
    return group, views


@pytest.mark.parametrize("wrong, neighbourhood, min_angle", [(0.3, 1000, 1.5), (0.3, 4, 1.5), (0.1, 1000, 30.0)])
def test_the_kernel_is_the_plain_algorithm(wrong, neighbourhood, min_angle):
    """The kernel's shortcuts (support bounds kept across rounds, scanned edges dropped, seeds ranked on the
    fly) change no group: the same partition of the observations, and the same views per group, as scoring
    every seed of every round."""
    from episeg_cv.colmap import _consensus_kernel
    from episeg_cv.colmap.consensus import _normalised

    views, _, kp = _scene(n_views=5, n_points=25, seed=5)
    rng = np.random.default_rng(2)
    node_image, node_xy, eu, ev = [], [], [], []
    nid = {}
    for k in range(5):
        for p in range(25):
            nid[k, p] = len(node_image)
            node_image.append(k)
            node_xy.append(kp[k, p] + rng.uniform(-0.6, 0.6, 2))
    for i in range(5):
        for j in range(i + 1, 5):
            for p in range(25):
                q = int(rng.integers(0, 25)) if rng.random() < wrong else p
                eu.append(nid[i, p])
                ev.append(nid[j, q])
    P, centers = _normalised(views)
    args = (P, centers, np.array(node_image), np.array(node_xy), np.array(eu), np.array(ev),
            np.round(rng.uniform(0.3, 0.9, len(eu)), 1), 5, 2.0, np.cos(np.radians(min_angle)), 6, neighbourhood, 2)
    got, got_views, _ = _consensus_kernel.consensus(*args)
    want, want_views = _reference_groups(*args)
    assert (got >= 0).sum() > 40
    # the same partition (the kernel numbers its groups by component; compare the node sets) and views
    as_sets = lambda g, vs: {(tuple(np.flatnonzero(g == q)), int(vs[q])) for q in set(g[g >= 0])}  # noqa: E731
    assert as_sets(got, got_views) == as_sets(want, want_views)
    if min_angle > 10:  # a quarter circle of 5 cameras: 30 degrees merges some of them
        assert any(len(np.flatnonzero(got == q)) > got_views[q] for q in set(got[got >= 0]))


def _chained_graph(wrong, seed=3):
    """A 6-view scene of 400 points whose false edges (a share ``wrong``) chain tracks into big components,
    with tied ratios: the kernel's arguments."""
    from episeg_cv.colmap.consensus import _normalised

    views, _, kp = _scene(n_views=6, n_points=400, seed=seed)
    rng = np.random.default_rng(8)
    kp = kp + rng.uniform(-0.5, 0.5, kp.shape)
    eu, ev, er = [], [], []
    for i, j, p, _ in _all_pairs(6, 400, ratio=0.5):
        q = p[:, 1].copy()
        false = rng.random(len(p)) < wrong
        q[false] = rng.integers(0, 400, int(false.sum()))
        eu.append(i * 400 + p[:, 0])
        ev.append(j * 400 + q)
        er.append(np.round(rng.uniform(0.3, 0.89, len(p)), 2))
    P, centers = _normalised(views)
    return (P, centers, np.repeat(np.arange(6), 400), kp.reshape(-1, 2), np.concatenate(eu), np.concatenate(ev),
            np.concatenate(er), 6, 2.0, np.cos(np.radians(1.5)), 24, 1000, 2)


@pytest.mark.skipif(__import__("numba").config.NUMBA_NUM_THREADS < 2, reason="needs two numba threads")
@pytest.mark.parametrize("wrong, big, read_cap, per_slot, chain", [
    (0.15, 4096, 8192, 16, 4),  # the defaults: the chained component runs on both threads
    (0.15, 1, 8192, 4, 4),      # every component above its thread's share of the edges
    (0.15, 1, 24, 4, 4),        # room for few reads: most chains run again in the apply phase
    (0.6, 1, 8192, 64, 4),      # many false edges (seeds set aside too), big batches: many clashes
    (0.3, 1, 8192, 1, 1),       # batches of one chain per slot, chains of one round: the rest runs in the apply phase
    (0.3, 1, 8192, 8, 64),      # chains as long as an edge has rounds
])
def test_big_components_in_speculative_batches_give_the_serial_result(monkeypatch, wrong, big, read_cap, per_slot,
                                                                       chain):
    """A big component's rounds run in speculative batches of chains on every thread (``_big_component``: an
    edge's rounds on the graph less what the chain took, applied in ratio order unless something a chain read
    was taken by one applied before it, and then run again): the groups, their views and the counts must be
    those of the serial loop, whatever the batch, the chain, the room for reads and the graph."""
    import numba

    from episeg_cv.colmap import _consensus_kernel as kernel

    args = _chained_graph(wrong)
    serial = kernel.consensus(*args)
    runs = []
    real = kernel._big_component
    monkeypatch.setattr(kernel, "_big_component", lambda *a: (runs.append(a[0]), real(*a))[1])
    monkeypatch.setattr(kernel, "BIG_COMPONENT", big)
    monkeypatch.setattr(kernel, "READ_CAP", read_cap)
    monkeypatch.setattr(kernel, "ROUNDS_PER_SLOT", per_slot)
    monkeypatch.setattr(kernel, "MAX_CHAIN", chain)
    before = numba.get_num_threads()
    numba.set_num_threads(2)
    try:
        par = kernel.consensus_parallel(*args, 8)
    finally:
        numba.set_num_threads(before)
    assert runs, "no component ran in speculative batches"
    assert serial[1].size > 100 and (serial[2][2] > 0 or wrong < 0.5)  # groups (and seeds set aside) compared
    for a, b in zip(serial, par):
        np.testing.assert_array_equal(a, b)


def test_ratio_order_is_a_stable_sort():
    """The edges' order (``_by_ratio``, a radix sort of the ratios' bits): numpy's stable argsort, ties in input
    order, zeros of both signs equal, negative and infinite values in place."""
    from episeg_cv.colmap import _consensus_kernel as kernel

    rng = np.random.default_rng(4)
    special = np.array([0.0, -0.0, 0.25, 0.5, 1e-300, 5e-324, 0.9999, 1.0, 3.5, -2.0, np.inf, -np.inf])
    for _ in range(300):
        x = np.concatenate([rng.choice(special, rng.integers(0, 40)), rng.random(rng.integers(0, 40)),
                            np.round(rng.random(rng.integers(0, 40)), 1)])
        rng.shuffle(x)
        np.testing.assert_array_equal(kernel._by_ratio(x), np.argsort(x, kind="stable"))
    assert kernel._by_ratio(np.zeros(0)).shape == (0,)
    # a collection's size: every digit of the mantissa differs somewhere, and many ties (rounded values)
    x = np.concatenate([rng.random(60_000), np.round(rng.random(60_000), 3), rng.choice(special, 1000)])
    rng.shuffle(x)
    np.testing.assert_array_equal(kernel._by_ratio(x), np.argsort(x, kind="stable"))


# -- views whose pose looks off (suspect_views) -----------------------------------------------------------------
def _counts(kept_per_pair, n=100):
    """Candidates of a triangle of pairs (0, 1), (1, 2), (0, 2), ``n`` each, the first ``kept`` of each kept."""
    pairs = [(0, 1), (1, 2), (0, 2)]
    cands = [(i, j, np.zeros((n, 2), np.intp), np.zeros(n)) for i, j in pairs]
    return cands, [np.arange(n) < k for k in kept_per_pair]


def test_suspect_views_by_hand():
    # shares: view 0 (80 + 80) / 200 = 0.8, view 1 (80 + 10) / 200 = 0.45, view 2 (10 + 80) / 200 = 0.45
    assert suspect_views(3, *_counts([80, 10, 80])) == []
    # view 2 keeps (2 + 2) / 200 = 0.02 against a median of 0.41: below a quarter of it
    assert suspect_views(3, *_counts([80, 2, 2])) == [(2, 0.02, pytest.approx(0.41))]
    # just above the threshold is not named; views with too few candidates are not judged
    share = SUSPECT_FRACTION * 0.45 + 0.01
    assert suspect_views(3, *_counts([80, round(200 * share / 2), round(200 * share / 2)])) == []
    assert suspect_views(3, *_counts([0, 0, 0], n=MIN_VIEW_CANDIDATES // 2 - 1)) == []
    assert suspect_views(0, [], []) == []


@settings(max_examples=30, deadline=None)
@given(st.integers(3, 8), st.floats(0.5, 1.0), st.integers(0, 2**31 - 1))
def test_a_uniform_collection_names_no_view(n_views, share, seed):
    """Property: when every pair keeps about the same share of its candidates, no view is named."""
    rng = np.random.default_rng(seed)
    cands, keep = [], []
    for i in range(n_views):
        for j in range(i + 1, n_views):
            n = int(rng.integers(50, 200))  # (binomial noise: at least 7 sigma from the threshold)
            cands.append((i, j, np.zeros((n, 2), np.intp), np.zeros(n)))
            keep.append(rng.random(n) < share)
    assert suspect_views(n_views, cands, keep) == []
