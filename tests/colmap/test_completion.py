"""Track completion (issue 14): consensus groups of two views extended by projection with the known poses."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import episeg_cv
from episeg_cv import scenes
from episeg_cv.colmap import TrackConsensus, View, verify_tracks
from episeg_cv.colmap import _completion_kernel
from episeg_cv.colmap.consensus import _normalised, verify_and_complete

K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])


def _line(n):
    """n cameras on the x axis, one unit apart, looking down +z (100 x 100 images)."""
    return [View(f"{k}", k + 1, 1, K, np.eye(3), [-k, 0, 0], (100, 100)) for k in range(n)]


def _at(views, X):
    """The projections of the point X, one row per view."""
    return np.array([(K @ (v.R @ X + v.t))[:2] / (v.R @ X + v.t)[2] for v in views])


def _pairs(n, items=()):
    """Every pair of n views, with the given candidates ``{(i, j): (pairs, ratios)}`` and none elsewhere."""
    items = dict(items)
    return [(i, j, *items.get((i, j), (np.zeros((0, 2), np.int64), np.zeros(0)))) for i in range(n)
            for j in range(i + 1, n)]


def _added(cands, added):
    return {(c[0], c[1]): a.tolist() for c, a in zip(cands, added) if len(a)}


X0 = np.array([0.0, 0.0, 20.0])  # seen by every camera of _line (they are 5 px apart in its images)
D = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], np.float32)  # three descriptors


# --------------------------------------------------------------------------------------
# Hand-made cases
# --------------------------------------------------------------------------------------
def test_a_two_view_match_gains_the_view_where_its_point_lands():
    views = _line(3)
    kp = [x[None] for x in _at(views, X0)]
    cands = _pairs(3, {(0, 1): (np.array([[0, 0]]), np.array([0.5]))})
    keep, added, stats = verify_and_complete(views, cands, lambda k: kp[k], lambda k: D[:1], 0.68, 1.0)
    assert [k.tolist() for k in keep] == [[True], [], []]
    assert _added(cands, added) == {(0, 2): [[0, 0]], (1, 2): [[0, 0]]}
    assert stats["added"] == 1 and stats["merged"] == 0 and stats["new_edges"] == 2
    # without the completion: the same keep, nothing added
    assert [k.tolist() for k in verify_tracks(views, cands, lambda k: kp[k], 0.68, 1.0)[0]] == [[True], [], []]


def test_nothing_is_added_when_no_keypoint_is_near_the_projection():
    views = _line(3)
    kp = [x[None] for x in _at(views, X0)]
    kp[2] = kp[2] + [1.5, 0.0]  # beyond tau = 1 px
    cands = _pairs(3, {(0, 1): (np.array([[0, 0]]), np.array([0.5]))})
    _, added, stats = verify_and_complete(views, cands, lambda k: kp[k], lambda k: D[:1], 0.68, 1.0)
    assert _added(cands, added) == {} and stats["added"] == 0
    _, added, _ = verify_and_complete(views, cands, lambda k: kp[k], lambda k: D[:1], 0.68, 2.0)  # within 2 px
    assert _added(cands, added) == {(0, 2): [[0, 0]], (1, 2): [[0, 0]]}


def test_a_loose_match_needs_two_views_found():
    views = _line(4)
    kp = [x[None] for x in _at(views, X0)]
    cands = _pairs(4, {(0, 1): (np.array([[0, 0]]), np.array([0.8]))})  # above the pair rule's 0.68
    far = [kp[0], kp[1], kp[2], kp[3] + [0.0, 30.0]]  # only view 2 holds the point
    keep, added, _ = verify_and_complete(views, cands, lambda k: far[k], lambda k: D[:1], 0.68, 1.0)
    assert not keep[0].any() and _added(cands, added) == {}
    keep, added, stats = verify_and_complete(views, cands, lambda k: kp[k], lambda k: D[:1], 0.68, 1.0)
    assert keep[0].all() and stats["added"] == 2
    assert _added(cands, added) == {(0, 2): [[0, 0]], (0, 3): [[0, 0]], (1, 2): [[0, 0]], (1, 3): [[0, 0]],
                                    (2, 3): [[0, 0]]}


def test_two_groups_of_one_point_merge():
    """Views 0-1 and 2-3 matched the same point, with no match between the two: one track of four views."""
    views = _line(4)
    kp = [x[None] for x in _at(views, X0)]
    one = (np.array([[0, 0]]), np.array([0.5]))
    cands = _pairs(4, {(0, 1): one, (2, 3): one})
    keep, added, stats = verify_and_complete(views, cands, lambda k: kp[k], lambda k: D[:1], 0.68, 1.0)
    assert stats["merged"] == 1 and stats["added"] == 0
    assert _added(cands, added) == {(0, 2): [[0, 0]], (0, 3): [[0, 0]], (1, 2): [[0, 0]], (1, 3): [[0, 0]]}
    assert keep[0].all() and keep[-1].all()


def test_a_keypoint_of_another_point_on_the_same_ray_is_not_taken():
    """View 2's keypoint lies where the point of views 0-1 projects, but it belongs to another group (views
    2-3) whose point is elsewhere on that ray: no point explains the four, so nothing changes."""
    views = _line(4)
    x2 = _at(views, X0)[2]
    Y = np.array([(x2[0] - 50) / 100 * 10 + 2, 0.0, 10.0])  # camera 2's ray through x2, at depth 10
    assert np.allclose(_at(views, Y)[2], x2)
    kp = [_at(views, X0)[0][None], _at(views, X0)[1][None], x2[None], _at(views, Y)[3][None]]
    one = (np.array([[0, 0]]), np.array([0.5]))
    cands = _pairs(4, {(0, 1): one, (2, 3): one})
    _, added, stats = verify_and_complete(views, cands, lambda k: kp[k], lambda k: D[:1], 0.68, 1.0)
    assert _added(cands, added) == {} and stats["merged"] == 0 and stats["added"] == 0


def test_the_nearest_descriptor_in_the_disc_is_taken():
    views = _line(3)
    x = _at(views, X0)
    kp = [x[0][None], x[1][None], np.array([x[2], x[2] + [0.6, 0.0]])]  # both within 1 px of the projection
    des = [D[:1], D[:1], np.array([D[1], D[0] * 0.9 + D[1] * 0.1])]  # the second resembles the track
    cands = _pairs(3, {(0, 1): (np.array([[0, 0]]), np.array([0.5]))})
    _, added, _ = verify_and_complete(views, cands, lambda k: kp[k], lambda k: des[k], 0.68, 1.0)
    assert _added(cands, added) == {(0, 2): [[0, 1]], (1, 2): [[0, 1]]}


def test_a_keypoint_goes_to_the_track_it_resembles_most():
    """Two groups of views 0-1 project within tau of one keypoint of view 2: the nearer by descriptor takes it."""
    views = _line(3)
    X1 = X0 + [0.05, 0.0, 0.0]  # 0.25 px beside X0 in every image
    a, b = _at(views, X0), _at(views, X1)
    kp = [np.array([a[0], b[0]]), np.array([a[1], b[1]]), a[2][None]]
    for g, seen in ((0, [D[0], D[1]]), (1, [D[1], D[0]])):  # the keypoint of view 2 has descriptor D[0]
        des = [np.array(seen), np.array(seen), D[:1]]
        cands = _pairs(3, {(0, 1): (np.array([[0, 0], [1, 1]]), np.array([0.5, 0.5]))})
        _, added, stats = verify_and_complete(views, cands, lambda k: kp[k], lambda k: des[k], 0.68, 1.0)
        assert stats["added"] == 1 and _added(cands, added) == {(0, 2): [[g, 0]], (1, 2): [[g, 0]]}


def test_hamming_and_l1_descriptors():
    views = _line(3)
    x = _at(views, X0)
    kp = [x[0][None], x[1][None], np.array([x[2], x[2] + [0.5, 0.0]])]
    bits = [np.array([[0b1111, 0]], np.uint8)] * 2 + [np.array([[0, 0b1111], [0b0111, 0]], np.uint8)]
    cands = _pairs(3, {(0, 1): (np.array([[0, 0]]), np.array([0.5]))})
    for norm, des in (("hamming", bits), ("l1", [b.astype(np.float32) for b in bits])):
        _, added, _ = verify_and_complete(views, cands, lambda k: kp[k], lambda k: des[k], 0.68, 1.0, norm=norm)
        assert _added(cands, added) == {(0, 2): [[0, 1]], (1, 2): [[0, 1]]}, norm
    # [0, 0b1111] against [0b1111, 0]: four bits differ in each byte
    assert _completion_kernel._distance(bits[2][0], bits[0][0], _completion_kernel.HAMMING) == 8


def test_views_from_one_place_do_not_complete_a_track():
    """A third camera at (nearly) the same place as camera 1 adds no view that counts (min_angle)."""
    views = _line(2) + [View("2", 3, 1, K, np.eye(3), [-1.001, 0, 0], (100, 100))]
    kp = [x[None] for x in _at(views, X0)]
    cands = _pairs(3, {(0, 1): (np.array([[0, 0]]), np.array([0.5]))})
    _, added, _ = verify_and_complete(views, cands, lambda k: kp[k], lambda k: D[:1], 0.68, 1.0)
    assert _added(cands, added) == {}
    _, added, _ = verify_and_complete(views, cands, lambda k: kp[k], lambda k: D[:1], 0.68, 1.0,
                                      TrackConsensus(min_angle=0))
    assert _added(cands, added) == {(0, 2): [[0, 0]], (1, 2): [[0, 0]]}


def test_empty_candidates():
    views = _line(3)
    keep, added, stats = verify_and_complete(views, _pairs(3), lambda k: np.zeros((0, 2)),
                                             lambda k: np.zeros((0, 3), np.float32), 0.68, 1.0)
    assert [len(k) for k in keep] == [0, 0, 0] and [a.shape for a in added] == [(0, 2)] * 3 and stats["kept"] == 0


def test_bad_input_is_refused():
    views = _line(3)
    kp = [x[None] for x in _at(views, X0)]
    cands = _pairs(3, {(0, 1): (np.array([[0, 0]]), np.array([0.5]))})
    with pytest.raises(ValueError, match="descriptors of view 0 must be one row"):
        verify_and_complete(views, cands, lambda k: kp[k], lambda k: D, 0.68, 1.0)
    with pytest.raises(ValueError, match="descriptors of view 2 must be one row of 3"):
        verify_and_complete(views, cands, lambda k: kp[k], lambda k: D[:1, :2] if k == 2 else D[:1], 0.68, 1.0)
    with pytest.raises(ValueError, match="norm must be one of"):
        verify_and_complete(views, cands, lambda k: kp[k], lambda k: D[:1], 0.68, 1.0, norm="cosine")
    with pytest.raises(TypeError, match="complete must be a bool"):
        TrackConsensus(complete="yes")
    assert TrackConsensus(complete=True).complete and not TrackConsensus().complete


# --------------------------------------------------------------------------------------
# Synthetic scenes and properties
# --------------------------------------------------------------------------------------
def _scene(n_views, n_points, seed, noise=0.2, distractors=0):
    """Cameras on a quarter circle round random points; keypoint p of each view is point p (with ``noise``
    pixels of error), with a random unit descriptor per point; then ``distractors`` random keypoints."""
    rng = np.random.default_rng(seed)
    Kr = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    views = []
    for k in range(n_views):
        a = 2 * np.pi * k / n_views * 0.25
        R, t = scenes.look_at([4 * np.sin(a), 0.3 * k, -4 * np.cos(a)], [0, 0, 0])
        views.append(View(f"v{k}.png", k + 1, 1, Kr, R, t, (640, 480)))
    X = rng.uniform(-0.5, 0.5, (n_points, 3))
    des = rng.normal(size=(n_points + distractors, 32)).astype(np.float32)
    des /= np.linalg.norm(des, axis=1, keepdims=True)
    kp, ds = [], []
    for v in views:
        Xc = X @ v.R.T + v.t
        x = (Xc @ Kr.T)[:, :2] / Xc[:, 2:] + rng.uniform(-noise, noise, (n_points, 2))
        kp.append(np.vstack([x, rng.uniform([0, 0], [640, 480], (distractors, 2))]))
        ds.append(des + rng.normal(scale=0.05, size=des.shape).astype(np.float32))
    return views, kp, ds


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), n_views=st.integers(3, 6), noise=st.sampled_from([0.0, 0.3]))
def test_two_view_matches_are_completed_with_their_true_keypoints(seed, n_views, noise):
    """Only views 0 and 1 matched (strict). Without noise every added match joins keypoints of one point,
    and a point whose keypoint in a view has no other keypoint within 2 tau gets that view. With 0.3 px of
    noise a two-view point can project more than tau from its own keypoint and next to another point's,
    which then joins (nothing checks the descriptor's distance, only that it is the nearest in the disc):
    at most 5 % of the added matches (hypothesis found seed 8476 with one; the worst of 210 scenes, 2.2 %)."""
    n = 40
    views, kp, des = _scene(n_views, n, seed, noise=noise, distractors=60)
    idx = np.arange(n)
    cands = _pairs(n_views, {(0, 1): (np.column_stack([idx, idx]), np.full(n, 0.5))})
    keep, added, _ = verify_and_complete(views, cands, lambda k: kp[k], lambda k: des[k], 0.68, 1.0)
    assert keep[0].all()
    pairs = [(i, j, a) for (i, j, _, _), a in zip(cands, added)]
    wrong = sum(int((a[:, 0] != a[:, 1]).sum()) for _, _, a in pairs)  # keypoint p with keypoint q != p
    total = sum(len(a) for _, _, a in pairs)
    if noise == 0:
        assert wrong == 0
    else:
        assert wrong <= 0.05 * total, (wrong, total)
    got = {(j, int(p)) for (i, j, _, _), a in zip(cands, added) if i == 0 for p in a[:, 0]}
    for k in range(2, n_views if noise == 0 else 2):
        d = np.linalg.norm(kp[k][:n, None] - kp[k][None], axis=2)
        alone = (d <= 2.0).sum(1) == 1  # no other keypoint within 2 tau: the nearest in its disc is itself
        for p in np.flatnonzero(alone):
            assert (k, p) in got, (k, p)


@pytest.mark.skipif(__import__("numba").config.NUMBA_NUM_THREADS < 2, reason="needs two numba threads")
def test_threads_give_the_serial_result():
    """Thousands of groups: the projections run on threads (blocks of groups); the result is one thread's."""
    n = 2500
    views, kp, des = _scene(5, n, seed=4, noise=0.3, distractors=500)
    idx = np.arange(n)
    rng = np.random.default_rng(2)
    ratio = np.round(rng.uniform(0.3, 0.9, n), 2)  # loose ones need two views found, ties in ratio
    cands = _pairs(5, {(0, 1): (np.column_stack([idx, idx]), ratio),
                       (2, 3): (np.column_stack([idx[::3], idx[::3]]), ratio[::3])})  # merges
    assert n >= episeg_cv.threads.MIN_PARALLEL_ITEMS
    calls = []
    real = _completion_kernel.nearby_parallel

    def spy(*args):
        calls.append(1)
        return real(*args)

    results = []
    for threads in (1, 2):
        episeg_cv.set_num_threads(threads)
        try:
            _completion_kernel.nearby_parallel = spy
            results.append(verify_and_complete(views, cands, lambda k: kp[k], lambda k: des[k], 0.68, 1.0))
        finally:
            _completion_kernel.nearby_parallel = real
            episeg_cv.set_num_threads(None)
    assert len(calls) == 1  # the second run was parallel
    (k1, a1, s1), (k2, a2, s2) = results
    assert s1 == s2 and s1["added"] > 1000 and s1["merged"] > 100
    for x, y in zip(k1 + a1, k2 + a2):
        np.testing.assert_array_equal(x, y)


def test_the_kernel_twins_agree():
    views, kp, des = _scene(4, 300, seed=9, distractors=200)
    from numba import typed
    from episeg_cv.colmap.consensus import _normalised
    P, _ = _normalised(views)
    kp_xy = np.vstack(kp)
    kp_ptr = np.array([0, 500, 1000, 1500, 2000])
    sizes = np.full((4, 2), [640.0, 480.0])
    grid = _completion_kernel.build_grid(kp_xy, kp_ptr, sizes, 1.0)
    grp_ptr = np.arange(0, 601, 2)
    grp_nodes = np.arange(600)
    node_image = np.tile([0, 1], 300)
    node_kp = np.repeat(np.arange(300), 2)
    node_xy = np.array([kp[i][p] for i, p in zip(node_image, node_kp)])
    args = (P, grp_ptr, grp_nodes, node_image, node_kp, node_xy, kp_xy, kp_ptr, typed.List(des), 0, sizes, 1.0,
            *grid)
    a = _completion_kernel.nearby(*args)
    b = _completion_kernel.nearby_parallel(*args, 7)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert (a[0][:, 2:] >= 0).mean() > 0.8 and (a[0][:, :2] == -1).all()


# --------------------------------------------------------------------------------------
# In the pipeline
# --------------------------------------------------------------------------------------
def test_match_model_with_completion_keeps_more_and_triangulates_more(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    pycolmap.logging.minloglevel = 2
    from episeg_cv import colmap
    c = scenes.make_collection(4, image_size=(480, 360))
    paths = colmap.save_collection(c, tmp_path / "set")
    runs = {}
    for label, verify in (("off", "tracks"), ("on", TrackConsensus(complete=True))):
        db = tmp_path / f"{label}.db"
        report = colmap.match_model(paths["model"], paths["images"], db, verify=verify,
                                    cache_dir=tmp_path / "features")
        rec = colmap.triangulate(db, paths["model"], paths["images"], tmp_path / f"tri_{label}")
        runs[label] = report, colmap.read_database_matches(db), rec
    (r_off, m_off, rec_off), (r_on, m_on, rec_on) = runs["off"], runs["on"]
    assert "added" not in r_off.verify and r_on.verify["added"] + r_on.verify["merged"] > 0
    assert r_on.n_inliers > r_off.n_inliers
    for pair, (_, inl) in m_off.items():  # the completion only adds
        have = {tuple(r) for r in m_on[pair][1]}
        assert all(tuple(r) in have for r in inl)
    assert rec_on.num_points3D() > rec_off.num_points3D()
    assert rec_on.compute_mean_reprojection_error() < 1.0


# --------------------------------------------------------------------------------------
# The photometric check
# --------------------------------------------------------------------------------------
def _plane_images(views, seed=0, size=100):
    """Images of the textured plane z = 20 (the depth of X0) seen by the cameras of _line: camera k is k units
    to the right, so its image is the texture shifted 5 k pixels left (100 / 20 per unit)."""
    import cv2
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (size, size + 40)).astype(np.float32), (0, 0), 1.5)
    return [np.ascontiguousarray(tex[:, 5 * k: 5 * k + size]) for k in range(len(views))]


def test_a_proposal_whose_patch_does_not_match_is_refused():
    """Hand-made: the third view's keypoint lies where X0 projects (within tau), but its image shows another
    texture there: the NCC is about 0, below MIN_NCC, and nothing is added. With the true image it is."""
    from episeg_cv.colmap import completion
    views = _line(3)
    kp = [x[None] for x in _at(views, X0)]
    cands = _pairs(3, {(0, 1): (np.array([[0, 0]]), np.array([0.5]))})
    ims = _plane_images(views)
    _, added, _ = verify_and_complete(views, cands, lambda k: kp[k], lambda k: D[:1], 0.68, 1.0,
                                      images=lambda k: ims[k])
    assert _added(cands, added) == {(0, 2): [[0, 0]], (1, 2): [[0, 0]]}
    other = _plane_images(views, seed=1)
    mixed = [ims[0], ims[1], other[2]]
    _, added, stats = verify_and_complete(views, cands, lambda k: kp[k], lambda k: D[:1], 0.68, 1.0,
                                          images=lambda k: mixed[k])
    assert _added(cands, added) == {} and stats["added"] == 0
    # the scores themselves: the true patch correlates (the plane is the true surface), the other does not
    P, centers = _normalised(views)  # camera centres (-1, 0, 0), (0, 0, 0), (1, 0, 0): X0 becomes (0, 0, 20)
    Xn = X0 - [1.0, 0.0, 0.0]
    args = (P, centers, Xn[None], np.array([2]), kp[2], np.array([[0, 1]]))
    assert completion.photo_consistency(*args, lambda k: ims[k])[0] > 0.95
    assert abs(completion.photo_consistency(*args, lambda k: mixed[k])[0]) < completion.MIN_NCC


def test_views_beyond_max_angle_are_not_checked_and_refused():
    from episeg_cv.colmap import completion
    views = _line(3)
    ims = _plane_images(views)
    P, centers = _normalised(views)
    X = np.array([[0.0, 0.0, 0.3]])  # near the cameras: view 2 sees it at a wide angle from view 0
    x2 = P[2] @ np.append(X[0], 1)
    nc = completion.photo_consistency(P, centers, X, np.array([2]), (x2[:2] / x2[2])[None], np.array([[0]]),
                                      lambda k: ims[k], max_angle=1.0)
    assert np.isnan(nc[0])


@pytest.mark.skipif(__import__("numba").config.NUMBA_NUM_THREADS < 2, reason="needs two numba threads")
def test_threads_give_the_serial_result_with_the_photometric_check():
    """The scene of test_threads_give_the_serial_result on noise images: many proposals are refused, and
    one thread and two agree."""
    n = 2500
    views, kp, des = _scene(5, n, seed=4, noise=0.3, distractors=500)
    rng = np.random.default_rng(5)
    ims = [rng.uniform(0, 255, (480, 640)).astype(np.float32) for _ in views]
    idx = np.arange(n)
    cands = _pairs(5, {(0, 1): (np.column_stack([idx, idx]), np.full(n, 0.5))})
    results = []
    for threads in (1, 2):
        episeg_cv.set_num_threads(threads)
        try:
            results.append(verify_and_complete(views, cands, lambda k: kp[k], lambda k: des[k], 0.68, 1.0,
                                               images=lambda k: ims[k]))
        finally:
            episeg_cv.set_num_threads(None)
    (k1, a1, s1), (k2, a2, s2) = results
    base = verify_and_complete(views, cands, lambda k: kp[k], lambda k: des[k], 0.68, 1.0)[2]
    assert s1 == s2 and s1["added"] < base["added"] / 2  # noise images: unrelated patches
    for x, y in zip(k1 + a1, k2 + a2):
        np.testing.assert_array_equal(x, y)
