"""Renderer, pose suite and ground truth of ``episeg_cv.scenes``."""

import numpy as np
import pytest

from episeg_cv.geometry import TwoViewGeometry
from episeg_cv.scenes import (
    GroundTruth,
    Quad,
    Scene,
    box_quads,
    disparity_ground_truth,
    ground_truth_matches,
    load_texture,
    look_at,
    make_pair,
    make_room_scene,
    pose_suite,
    render,
)
from episeg_cv.evaluation import nearest_within

ROOM = (8.0, 3.0, 10.0)  # make_room_scene's default room
SMALL = (160, 120)


def K_of(f, size):
    w, h = size
    return np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])


def rotation_angle_deg(R):
    return np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))


def flat_texture(value):
    return np.full((8, 8), float(value))


def project(K, R, t, X):
    Xc = np.atleast_2d(X) @ R.T + t
    x = Xc @ K.T
    return x[:, :2] / x[:, 2:3], Xc[:, 2]


# ---------------------------------------------------------------------------------
# renderer
# ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def room():
    return make_room_scene(rng=7, keep_clear=[[0.0, 0.0, -3.0]])


def test_depth_is_consistent_with_geometry(room):
    # an oblique, rolled camera; the back wall (z = +5) is seen at the centre
    K = K_of(90.0, SMALL)
    R, t = look_at([0.3, -0.2, -3.0], [1.0, 0.4, 5.0], roll=0.1)
    image, depth = render(room, K, R, t, SMALL)
    assert image.shape == depth.shape == (120, 160) and image.dtype == np.uint8
    assert np.isfinite(depth).all()  # a closed room: every ray meets a surface

    # every pixel's back-projected point lies on some quad's plane
    ys, xs = np.mgrid[0:120, 0:160]
    rays = np.column_stack([xs.ravel(), ys.ravel(), np.ones(xs.size)]) @ np.linalg.inv(K).T
    Xw = (rays * depth.reshape(-1, 1) - t) @ R  # R^T (X_cam - t)
    on_plane = np.zeros(len(Xw), dtype=bool)
    for q in room.quads:
        n = np.cross(q.edge_u, q.edge_v)
        n /= np.linalg.norm(n)
        on_plane |= np.abs((Xw - q.corner) @ n) < 1e-9 * (1 + np.abs(Xw).max())
    assert on_plane.all()

    # a point on the back wall (z = 5): the depth at its pixel is the exact ray-plane
    # intersection, and the back-projected point reprojects onto the pixel centre
    P = np.array([0.7, 0.1, 5.0])
    x, _ = project(K, R, t, P)
    ix, iy = np.rint(x[0]).astype(int)
    C = -R.T @ t
    ray_w = R.T @ np.linalg.inv(K) @ [ix, iy, 1.0]  # camera z-component 1: the ray parameter is the depth
    assert depth[iy, ix] == pytest.approx((5.0 - C[2]) / ray_w[2], rel=1e-12)
    Xw = R.T @ (depth[iy, ix] * np.linalg.inv(K) @ [ix, iy, 1.0] - t)
    assert Xw[2] == pytest.approx(5.0, abs=1e-9)
    x_back, z_back = project(K, R, t, Xw)
    np.testing.assert_allclose(x_back[0], [ix, iy], atol=0.01)
    assert z_back[0] == pytest.approx(depth[iy, ix], rel=1e-12)


def test_flat_quad_shading_and_antialiasing():
    K = K_of(40.0, (64, 48))
    bright = Quad([-1.05, -2, 4], [2.1, 0, 0], [0, 4, 0], texture=0, gain=0.5)
    wall = Quad([-10, -10, 8], [20, 0, 0], [0, 20, 0], texture=1)
    scene = Scene([bright, wall], [flat_texture(200), flat_texture(20)])
    image, depth = render(scene, K, np.eye(3), np.zeros(3), (64, 48))
    assert image[24, 31] == 100 and depth[24, 31] == pytest.approx(4.0)
    assert image[24, 2] == 20 and depth[24, 2] == pytest.approx(8.0)
    # the quad's left edge x = -1.05 at z = 4 is at x = 31.5 - 10.5 = 21.0, the centre of
    # pixel 21: two of its four samples see the quad, two the wall
    assert image[24, 21] == 60 and image[24, 20] == 20 and image[24, 22] == 100
    assert np.all(image[:, :20] == 20)


def test_occlusion_box_in_front_of_wall():
    K = K_of(50.0, (80, 60))
    wall = Quad([-5, -5, 6], [10, 0, 0], [0, 10, 0], texture=0)
    box = box_quads([0.0, 0.0, 3.0], [1.0, 1.0, 1.0], 0.0, 1, rng=0)
    for quads in ([wall, *box], [*box, wall]):  # the drawing order does not matter
        scene = Scene(quads, [flat_texture(50), flat_texture(220)])
        image, depth = render(scene, K, np.eye(3), np.zeros(3), (80, 60))
        assert depth[30, 40] == pytest.approx(2.5)  # the box's front face, z = 3 - 0.5
        assert depth[30, 2] == pytest.approx(6.0)  # the wall
        assert image[30, 40] > 150 and image[30, 2] < 60
        # the front face spans x in [-0.5, 0.5] at z = 2.5: 20 px wide around the centre
        box_px = np.isclose(depth, 2.5)
        assert box_px[30].sum() in (20, 21)


def test_behind_camera_is_not_drawn():
    K = K_of(50.0, (40, 30))
    behind = Quad([-5, -5, -2], [10, 0, 0], [0, 10, 0])
    image, depth = render(Scene([behind], [flat_texture(100)]), K, np.eye(3), np.zeros(3), (40, 30))
    assert np.isinf(depth).all() and (image == 0).all()


def test_same_seed_same_image():
    K = K_of(60.0, (96, 72))
    R, t = look_at([0.0, 0.0, -3.0], [0.2, 0.1, 5.0])
    a = render(make_room_scene(rng=3), K, R, t, (96, 72))
    b = render(make_room_scene(rng=3), K, R, t, (96, 72))
    c = render(make_room_scene(rng=4), K, R, t, (96, 72))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])
    p, q = make_pair("forward", (64, 48)), make_pair("forward", (64, 48))
    np.testing.assert_array_equal(p.image2, q.image2)


def test_render_rejects_bad_input(room):
    K = K_of(50.0, (40, 30))
    with pytest.raises(ValueError, match="K"):
        render(room, np.eye(4), np.eye(3), np.zeros(3), (40, 30))
    with pytest.raises(ValueError, match="supersample"):
        render(room, K, np.eye(3), np.zeros(3), (40, 30), supersample=0)
    with pytest.raises(TypeError, match="scene"):
        render([], K, np.eye(3), np.zeros(3), (40, 30))
    with pytest.raises(ValueError, match="parallel"):
        Quad([0, 0, 0], [1, 0, 0], [2, 0, 0])
    with pytest.raises(ValueError, match="texture"):
        Scene([Quad([0, 0, 1], [1, 0, 0], [0, 1, 0], texture=1)], [flat_texture(1)])
    with pytest.raises(ValueError, match="name"):
        load_texture("nope")


# ---------------------------------------------------------------------------------
# pose suite
# ---------------------------------------------------------------------------------
SUITE = pose_suite()


def image_grid(size, step=8):
    w, h = size
    ys, xs = np.mgrid[0:h:step, 0:w:step]
    return np.column_stack([xs.ravel(), ys.ravel()]).astype(float)


def inside(p, size):
    w, h = size
    return -0.5 <= p[0] <= w - 0.5 and -0.5 <= p[1] <= h - 0.5


def a3_over_image1(case):
    g = case.geometry()
    x = image_grid(case.image_size, 4)
    return (np.column_stack([x, np.ones(len(x))]) @ g.infinity_homography.T)[:, 2]


def test_suite_names():
    assert list(SUITE) == ["forward", "backward", "lateral", "converging", "face_to_face",
                           "near_pure_rotation", "partial_behind", "noisy_pose"]
    assert len({c.seed for c in SUITE.values()}) == len(SUITE)


@pytest.mark.parametrize("name", list(SUITE))
def test_case_is_consistent(name):
    c = SUITE[name]
    # the relative pose agrees with the world poses
    np.testing.assert_allclose(c.R2, c.R @ c.R1, atol=1e-12)
    np.testing.assert_allclose(c.t2, c.R @ c.t1 + c.t, atol=1e-12)
    # both cameras are inside the room
    for C in c.centers:
        assert np.all(np.abs(C) < np.array(ROOM) / 2 - 0.2)
    if name != "noisy_pose":
        assert c.R_given is c.R and c.t_given is c.t


def test_forward():
    c = SUITE["forward"]
    assert c.t[2] < 0 and inside(c.geometry().epipole, c.image_size)


def test_backward():
    c = SUITE["backward"]
    assert c.t[2] > 0 and inside(c.geometry().epipole, c.image_size)


def test_lateral():
    c = SUITE["lateral"]
    assert c.t[2] == 0.0 and np.linalg.norm(c.t) > 0.3
    assert not np.all(np.isfinite(c.geometry().epipole))


def test_converging():
    c = SUITE["converging"]
    C1, C2 = c.centers
    assert np.linalg.norm(C1 - C2) > 4.0  # wide baseline
    axes = c.R1[2], c.R2[2]
    assert np.degrees(np.arccos(axes[0] @ axes[1])) > 20  # converging optical axes
    assert inside(c.geometry().epipole, c.image_size)


def test_face_to_face():
    c = SUITE["face_to_face"]
    C1, C2 = c.centers
    assert (c.R1 @ C2 + c.t1)[2] > 0 and (c.R2 @ C1 + c.t2)[2] > 0  # each is in front of the other
    assert rotation_angle_deg(c.R) > 150
    assert np.all(a3_over_image1(c) < 0)  # every ray of camera 1 points towards camera 2
    assert inside(c.geometry().epipole, c.image_size) and inside(c.geometry().inverse().epipole, c.image_size)


def test_face_to_face_sees_the_wall_behind_the_other_camera():
    c = SUITE["face_to_face"]
    pair = make_pair("face_to_face", SMALL)
    for g, depth in ((pair.geometry_true, pair.depth2), (pair.geometry_true.inverse(), pair.depth1)):
        e = np.rint(g.epipole).astype(int)  # where the other camera is
        assert depth[e[1], e[0]] > g.t[2] + 0.3  # the surface seen there is behind it
    assert c.t[2] > 5


def test_near_pure_rotation():
    c = SUITE["near_pure_rotation"]
    assert 0 < np.linalg.norm(c.t) <= 0.03
    assert rotation_angle_deg(c.R) > 5


def test_partial_behind():
    a3 = a3_over_image1(SUITE["partial_behind"])
    assert 0.05 < np.mean(a3 < 0) < 0.5


def test_noisy_pose():
    c = SUITE["noisy_pose"]
    assert 0.4 < rotation_angle_deg(c.R_given @ c.R.T) < 0.6
    assert np.linalg.norm(c.t_given) == pytest.approx(np.linalg.norm(c.t))
    u, v = c.t / np.linalg.norm(c.t), c.t_given / np.linalg.norm(c.t_given)
    assert 0.015 < np.linalg.norm(u - v) < 0.025
    pair = make_pair("noisy_pose", (64, 48))
    assert pair.geometry is not pair.geometry_true
    np.testing.assert_allclose(pair.geometry.R, c.R_given)
    np.testing.assert_allclose(pair.R, c.R)


@pytest.mark.parametrize("name", list(SUITE))
def test_views_see_texture_and_overlap(name):
    pair = make_pair(name, SMALL)
    g = pair.geometry_true
    for img, depth in ((pair.image1, pair.depth1), (pair.image2, pair.depth2)):
        assert np.isfinite(depth).mean() > 0.99
        assert img.std() > 20  # textured, not blank
    grid = image_grid(SMALL, 4)
    vis12 = ground_truth_matches(grid, grid, pair.depth1, pair.depth2, g).visible.mean()
    vis21 = ground_truth_matches(grid, grid, pair.depth2, pair.depth1, g.inverse()).visible.mean()
    assert min(vis12, vis21) > 0.15, (vis12, vis21)


def test_make_pair_scales_intrinsics():
    c = SUITE["forward"]
    K1, _ = c.intrinsics((320, 240))
    np.testing.assert_allclose(K1, [[250, 0, 159.5], [0, 250, 119.5], [0, 0, 1]])
    with pytest.raises(ValueError, match="name"):
        make_pair("sideways")


# ---------------------------------------------------------------------------------
# ground truth
# ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def two_planes():
    """A wall at z = 6 and a 1 x 2 m panel at z = 3 covering world x in [-1, 0].

    Camera 1 at the origin, camera 2 at x = +0.5 (``t = (-0.5, 0, 0)``), f = 100,
    100 x 80 px. Disparity: 100 * 0.5 / 6 = 8.333 px on the wall, 16.667 px on the panel.
    In image 1 the panel covers x in [16.17, 49.5]; in image 2 x in [-0.5, 32.83].
    """
    size = (100, 80)
    K = np.array([[100.0, 0, 49.5], [0, 100.0, 39.5], [0, 0, 1]])
    wall = Quad([-10, -10, 6], [20, 0, 0], [0, 20, 0], texture=0)
    panel = Quad([-1, -1, 3], [1, 0, 0], [0, 2, 0], texture=1)
    scene = Scene([wall, panel], [load_texture("gravel"), load_texture("brick")])
    t = np.array([-0.5, 0.0, 0.0])
    _, depth1 = render(scene, K, np.eye(3), np.zeros(3), size)
    _, depth2 = render(scene, K, np.eye(3), t, size)
    g = TwoViewGeometry(K, K, np.eye(3), t, image_size1=size, image_size2=size)
    return g, depth1, depth2


def test_ground_truth_two_planes(two_planes):
    g, depth1, depth2 = two_planes
    d_wall, d_panel = 100 * 0.5 / 6, 100 * 0.5 / 3
    points1 = np.array([
        [70.0, 40.0],  # wall, visible
        [30.25, 20.5],  # panel, visible (sub-pixel: exact by inverse-depth interpolation)
        [12.0, 40.0],  # wall, hidden behind the panel in view 2 (lands at 3.67)
        [5.0, 40.0],  # wall, leaves image 2 (lands at -3.33)
        [80.0, 10.0],  # wall, visible, but no keypoint within 3 px
    ])
    points2 = np.array([
        [65.0, 40.0],  # 3.33 px from the first's projection: too far
        [62.5, 40.5],  # 0.96 px: the true match of point 0
        [30.25 - d_panel, 20.5],  # exactly on point 1's projection
        [12.0 - d_wall, 40.0],  # where point 2 would be: must not match (occluded)
        [-3.0, 40.0],
    ])
    gt = ground_truth_matches(points1, points2, depth1, depth2, g)
    assert isinstance(gt, GroundTruth)
    assert gt.match.tolist() == [1, 2, -1, -1, -1]
    assert gt.visible.tolist() == [True, True, False, False, True]
    expected = points1 - [[d_wall, 0], [d_panel, 0], [d_wall, 0], [d_wall, 0], [d_wall, 0]]
    np.testing.assert_allclose(gt.projected, expected, atol=1e-9)
    assert gt.distance[0] == pytest.approx(np.hypot(62.5 - (70 - d_wall), 0.5))
    assert gt.distance[1] < 1e-9 and np.isinf(gt.distance[[2, 3, 4]]).all()
    assert gt.num_matchable == 2 and gt.matchable.tolist() == [True, True, False, False, False]
    # correct = visible and within 3 px of the projection (keypoint 3 sits on point 2's
    # projection, but point 2 is occluded)
    assert gt.is_correct([[0, 1], [0, 0], [1, 2], [2, 3]]).tolist() == [True, False, True, False]
    np.testing.assert_allclose(gt.error([[0, 1]]), [gt.distance[0]])
    # a duplicate keypoint (same position, e.g. another SIFT orientation) is correct too
    dup = ground_truth_matches(points1, np.vstack([points2, points2[1]]), depth1, depth2, g)
    assert dup.match[0] == 1 and dup.is_correct([[0, 5], [0, 1]]).tolist() == [True, True]
    # with a 10 px radius point 0 has two keypoints in reach (0.97 and 3.33 px): the nearest wins
    assert ground_truth_matches(points1, points2, depth1, depth2, g, max_px=10.0).match.tolist() == [1, 2, -1, -1, -1]


def test_ground_truth_depth_tolerance(two_planes):
    g, depth1, depth2 = two_planes
    # with depth2 scaled by 2 %, nothing agrees within 1 % any more; within 3 % it does
    p = np.array([[70.0, 40.0]])
    q = p - [100 * 0.5 / 6, 0]
    assert ground_truth_matches(p, q, depth1, depth2 * 1.02, g).match.tolist() == [-1]
    assert ground_truth_matches(p, q, depth1, depth2 * 1.02, g, depth_rtol=0.03).match.tolist() == [0]


def test_ground_truth_empty_and_errors(two_planes):
    g, depth1, depth2 = two_planes
    gt = ground_truth_matches(np.zeros((0, 2)), [[1.0, 2.0]], depth1, depth2, g)
    assert gt.match.shape == (0,) and gt.match.dtype == np.intp and gt.projected.shape == (0, 2)
    gt = ground_truth_matches([[70.0, 40.0]], np.zeros((0, 2)), depth1, depth2, g)
    assert gt.match.tolist() == [-1] and gt.visible.tolist() == [True]
    assert gt.is_correct(np.zeros((0, 2), dtype=np.intp)).shape == (0,)
    with pytest.raises(ValueError, match="depth1"):
        ground_truth_matches([[1.0, 1.0]], [[1.0, 1.0]], depth1[:10], depth2, g)
    with pytest.raises(TypeError, match="geometry"):
        ground_truth_matches([[1.0, 1.0]], [[1.0, 1.0]], depth1, depth2, None)


def test_nearest_within_matches_brute_force():
    rng = np.random.default_rng(0)
    q = rng.uniform(0, 100, (500, 2))
    p = rng.uniform(0, 100, (800, 2))
    p[:20] = p[20:40]  # duplicates: ties go to the lowest index
    q[:5] = np.nan
    idx, dist = nearest_within(q, p, 3.0)
    d = np.hypot(*(q[:, None] - p[None]).transpose(2, 0, 1))
    best = np.argmin(np.where(np.isnan(d), np.inf, d), axis=1)
    dbest = np.take_along_axis(d, best[:, None], 1)[:, 0]
    expected = np.where(dbest <= 3.0, best, -1)
    expected[:5] = -1
    np.testing.assert_array_equal(idx, expected)
    np.testing.assert_allclose(dist[idx >= 0], dbest[idx >= 0])


def test_disparity_ground_truth_hand_case():
    disp = np.full((10, 20), 4.0)
    disp[:, 15:] = np.inf  # unknown
    points1 = np.array([[10.0, 5.0], [2.0, 5.0], [16.0, 5.0], [12.5, 3.0]])
    points2 = np.array([[6.5, 5.0], [8.5, 3.0], [9.0, 3.0]])
    gt = disparity_ground_truth(points1, points2, disp, (20, 10))
    assert gt.match.tolist() == [0, -1, -1, 1]
    assert gt.visible.tolist() == [True, False, False, True]
    np.testing.assert_allclose(gt.projected[[0, 1, 3]], [[6.0, 5.0], [-2.0, 5.0], [8.5, 3.0]])
    assert np.isnan(gt.projected[2]).all()
