"""Tests of episeg_cv.geometry: TwoViewGeometry and EpipolarSegments.

Four kinds of fixture (``docs/style.md``): hand-computed cases (the
paper's Table 1 cases c and d, every degenerate case), synthetic two-view
scenes with known ``K, R, t`` (hypothesis), reference values from ``cv2``, and
invariants (swapping the views, alternative constructors).

Pose convention: ``X2 = R @ X1 + t``. Pixel centres at integer coordinates.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from episeg_cv import EpipolarSegments, Rejection, TwoViewGeometry

# One tolerance per purpose, in one place. Distances are in pixels; the segment
# tolerance is relative to the pixel scale of the scene (focal length, image size).
SEG_RTOL = 1e-6  # a visible point lies within SEG_RTOL * scale px of its segment
RTOL, ATOL = 1e-9, 1e-9  # float64 comparisons of exactly computed quantities

SIZE = (100, 100)
K_PAPER = np.array([[50.0, 0, 50], [0, 50, 50], [0, 0, 1]])  # the paper's K, read in OpenCV's pixel-centre convention
K_CORNER = np.array([[50.0, 0, 49.5], [0, 50, 49.5], [0, 0, 1]])  # the same K read in the pixel-corner convention


def grid(size=SIZE, step=1.0):
    """Pixel centres (step 1), or the centres of a finer grid of cells covering the image."""
    w, h = size
    off = 0.0 if step == 1.0 else -0.5 + step / 2
    xs, ys = np.meshgrid(off + step * np.arange(int(round(w / step))), off + step * np.arange(int(round(h / step))))
    return np.column_stack([xs.ravel(), ys.ravel()])


def rodrigues(rv) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rv, dtype=np.float64).reshape(3, 1))[0]


def rot_y(deg) -> np.ndarray:
    return rodrigues([0.0, np.radians(deg), 0.0])


def inside(p, size, pad=0.0):
    w, h = size
    return (p[:, 0] >= -0.5 + pad) & (p[:, 0] <= w - 0.5 - pad) & (p[:, 1] >= -0.5 + pad) & (p[:, 1] <= h - 0.5 - pad)


def project(K, X):
    """Pixels of camera-frame points X (any sign of depth) and their depths."""
    x = X @ K.T
    return x[:, :2] / x[:, 2:3], X[:, 2]


def finite_min_dist(p, *targets):
    """min_i |p - targets[i]| over the finite targets, row-wise (inf if none)."""
    out = np.full(len(p), np.inf)
    for q in targets:
        q = np.broadcast_to(q, p.shape)
        ok = np.all(np.isfinite(q), axis=1)
        d = np.full(len(p), np.inf)
        d[ok] = np.hypot(*(p[ok] - q[ok]).T)
        out = np.minimum(out, d)
    return out


# -- random scenes (hypothesis draws the parameters, numpy the points) --------------------

@st.composite
def scenes(draw):
    """A random pair of cameras: K1 != K2, any relative pose (including facing away)."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))

    def camera():
        w, h = int(rng.integers(40, 1200)), int(rng.integers(40, 1200))
        f = rng.uniform(0.3, 3.0) * max(w, h)
        K = np.array([[f, rng.uniform(-0.01, 0.01) * f, rng.uniform(0.3, 0.7) * w],
                      [0, f * rng.uniform(0.8, 1.25), rng.uniform(0.3, 0.7) * h],
                      [0, 0, 1]])
        return K, (w, h)

    K1, size1 = camera()
    K2, size2 = camera()
    # a rotation vector of any direction and any angle up to pi: includes cameras facing away
    # (no subnormal floats: K t then loses most of its bits, and the line through the
    # epipole with them; a translation below 1e-300 of the scene scale is not a use case)
    rv = np.array(draw(st.tuples(*[st.floats(-1.0, 1.0, allow_subnormal=False)] * 3)))
    angle = draw(st.floats(0.0, np.pi))
    rv = rv / np.linalg.norm(rv) * angle if np.linalg.norm(rv) > 0 else np.zeros(3)
    t = np.array(draw(st.tuples(*[st.floats(-3.0, 3.0, allow_subnormal=False)] * 3)))
    if draw(st.booleans()):
        # "look-at": camera 2 at centre C looks at a point seen by camera 1, with some roll,
        # so that many points are visible in both views
        target = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), 1.0]) * rng.uniform(1, 5)
        C = rng.normal(size=3) * rng.uniform(0.1, 4.0)
        z = target - C
        z /= np.linalg.norm(z)
        x = np.cross(rng.normal(size=3), z)
        x /= np.linalg.norm(x)
        R2w = np.column_stack([x, np.cross(z, x), z])  # camera 2 -> camera 1 frame
        R = R2w.T @ rodrigues(rv * 0.05)
        t = -R @ C
    else:
        R = rodrigues(rv)
    geom = TwoViewGeometry(K1, K2, R, t, image_size1=size1, image_size2=size2)
    return geom, rng


def random_rays(geom, rng, n):
    """Pixels uniform in image 1 and depths log-uniform over four decades."""
    w, h = geom.image_size1
    x1 = np.column_stack([rng.uniform(-0.5, w - 0.5, n), rng.uniform(-0.5, h - 0.5, n)])
    scale = max(np.linalg.norm(geom.t), 1e-3)
    z1 = scale * 10 ** rng.uniform(-2, 2, n)
    return x1, z1


def points_3d(geom, x1, z1):
    n1 = np.column_stack([x1, np.ones(len(x1))]) @ np.linalg.inv(geom.K1).T
    return z1[:, None] * n1


def pixel_scale(geom):
    return max(geom.K2[0, 0], geom.K2[1, 1], *geom.image_size2)


PROPERTY = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@PROPERTY
@given(scenes())
def test_visible_points_lie_on_their_segment(scene):
    geom, rng = scene
    x1, z1 = random_rays(geom, rng, 2000)
    X2 = points_3d(geom, x1, z1) @ geom.R.T + geom.t
    x2, z2 = project(geom.K2, X2)
    vis = (z2 > 0) & inside(x2, geom.image_size2)
    seg = geom.segments(x1[vis])
    assert seg.valid.all()
    tol = SEG_RTOL * pixel_scale(geom)
    d = seg.distance(x2[vis])
    assert np.all(d <= tol), d.max()
    assert np.all(seg.classify(x2[vis], tol) == Rejection.ON_SEGMENT)
    # the line through them too, and the reported lengths are consistent
    has_line = np.all(np.isfinite(seg.line), axis=1)  # no line when t = 0, or x1 is the epipole of image 1
    assert np.all(seg.line_distance(x2[vis])[has_line] <= tol)
    assert np.all(seg.length <= seg.line_length + tol)


@PROPERTY
@given(scenes())
def test_points_behind_camera2_are_off_the_segment(scene):
    """A point in front of camera 1 but behind camera 2 (z2 < 0) whose mirrored image
    ``K2 X2 / z2`` lands in image 2 lies on the epipolar line, but not on the segment.

    Exact bound: the visible set and the mirrored set are disjoint intervals of the
    line, so the distance from a mirrored point to the segment is at least its
    distance to the nearer of the epipole and p_inf (the only finite points where the
    two intervals can meet)."""
    geom, rng = scene
    # points seen from camera 1 ...
    x1, z1 = random_rays(geom, rng, 1000)
    X2 = points_3d(geom, x1, z1) @ geom.R.T + geom.t
    # ... and points on the mirrored rays of image 2 (negative depth z2), seen from camera 1
    w, h = geom.image_size2
    y = np.column_stack([rng.uniform(-0.5, w - 0.5, 1000), rng.uniform(-0.5, h - 0.5, 1000)])
    z2 = -max(np.linalg.norm(geom.t), 1e-3) * 10 ** rng.uniform(-2, 2, 1000)
    X2 = np.vstack([X2, z2[:, None] * (np.column_stack([y, np.ones(1000)]) @ np.linalg.inv(geom.K2).T)])
    X1 = (X2 - geom.t) @ geom.R  # R^T (X2 - t)
    x2, z2 = project(geom.K2, X2)
    x1, z1 = project(geom.K1, X1)
    mirrored = (z1 > 0) & (z2 < 0) & inside(x2, geom.image_size2) & np.all(np.abs(x1) < 1e9, axis=1)
    seg = geom.segments(x1[mirrored])
    p = x2[mirrored]
    tol = SEG_RTOL * pixel_scale(geom)
    bound = finite_min_dist(p, seg.epipole, seg.infinity_point)
    d = seg.distance(p)
    assert np.all(d >= bound - tol)
    far = bound > 10 * tol
    labels = seg.take(np.flatnonzero(far)).classify(p[far], tol)
    assert not np.any(labels == Rejection.ON_SEGMENT)
    assert np.all(np.isin(labels, [Rejection.BEYOND_EPIPOLE, Rejection.BEYOND_INFINITY, Rejection.EMPTY_SEGMENT,
                                   Rejection.OUT_OF_RANGE]))


@PROPERTY
@given(scenes(), st.floats(0.0, 1.0), st.floats(1.05, 20.0), st.booleans())
def test_depth_range(scene, zmin_frac, ratio, per_point):
    """Depths inside [zmin, zmax] project onto the segment; depths < zmin/2 or > 2 zmax
    project off it, by at least their distance to the images of zmin and zmax (the
    finite ends of the unclipped segment)."""
    geom, rng = scene
    x1, z1 = random_rays(geom, rng, 2000)
    scale = max(np.linalg.norm(geom.t), 1e-3)
    if per_point:
        zmin = scale * 10 ** rng.uniform(-1.5, 1.0, len(x1))
        zmax = zmin * rng.uniform(1.05, 20.0, len(x1))
    else:
        zmin = np.full(len(x1), scale * 10 ** (zmin_frac * 2.5 - 1.5))
        zmax = zmin * ratio
    X2 = points_3d(geom, x1, z1) @ geom.R.T + geom.t
    x2, z2 = project(geom.K2, X2)
    vis = (z2 > 0) & inside(x2, geom.image_size2)
    tol = SEG_RTOL * pixel_scale(geom)

    def seg_of(mask):
        dr = (zmin[mask], zmax[mask]) if per_point else (float(zmin[0]), float(zmax[0]))
        return geom.segments(x1[mask], depth_range=dr)

    inner = vis & (z1 >= zmin) & (z1 <= zmax)
    seg = seg_of(inner)
    assert seg.valid.all()
    assert np.all(seg.distance(x2[inner]) <= tol)

    outer = vis & ((z1 < zmin / 2) | (z1 > 2 * zmax))
    seg = seg_of(outer)
    ends = []
    for z in (zmin[outer], zmax[outer]):
        q, zq = geom.transfer(x1[outer], z)
        q[zq <= 0] = np.nan  # behind camera 2: that end of the segment is at infinity
        ends.append(q)
    bound = finite_min_dist(x2[outer], *ends)
    assert np.all(seg.distance(x2[outer]) >= bound - tol)
    far = bound > 10 * tol
    labels = seg.take(np.flatnonzero(far)).classify(x2[outer][far], tol)
    assert not np.any(labels == Rejection.ON_SEGMENT)


# -- hand-computed: the paper's Table 1 -------------------------------------------------

def table1_geometry(K, t, R=np.eye(3)):
    return TwoViewGeometry(K, K, R, t, image_size1=SIZE, image_size2=SIZE)


def test_table1_case_c_is_two_thirds():
    """R = I, t = (0, 0, 1): the segment runs from the epipole (the image centre) to
    p_inf = x1. Along a line through the centre, with half-chord h, a pixel at
    distance r has reduction 1 - r / (2 h); for a square centred on e, r / h is the
    Chebyshev norm over the half-width, whose mean over the square is 2/3, hence
    a mean reduction of 1 - 1/3 = 2/3."""
    geom = table1_geometry(K_CORNER, [0, 0, 1])
    # dense, near-continuous sampling (0.25 px, cell centres): 2/3 up to O(step^2)
    red = geom.segments(grid(step=0.25)).reduction
    assert abs(red.mean() - 2 / 3) < 1e-5
    # one query per pixel centre: rings k = 0..49 of Chebyshev radius k + 1/2 hold 8k + 4 pixels,
    # so mean(r / h) = sum 8 (k + 1/2)^2 / (50 * 100^2) = 0.6666 and the reduction is 0.6667 exactly
    red = geom.segments(grid()).reduction
    expected = 1 - sum(8 * (k + 0.5) ** 2 for k in range(50)) / (50 * 100**2) / 2
    assert expected == pytest.approx(0.6667, abs=1e-12)
    assert red.mean() == pytest.approx(expected, abs=1e-12)
    assert abs(red.mean() - 2 / 3) < 1e-4


def test_table1_case_c_pixel_centre_convention():
    """With cx = cy = 50 read in OpenCV's convention the epipole (50, 50) is half a pixel
    off the image centre (49.5, 49.5): the mean is 0.66659, and the pixel at the
    epipole itself has no epipolar line (reduction NaN)."""
    geom = table1_geometry(K_PAPER, [0, 0, 1])
    pts = grid()
    red = geom.segments(pts).reduction
    nan = np.flatnonzero(np.isnan(red))
    assert nan.tolist() == [50 * 100 + 50]
    assert abs(np.nanmean(red) - 2 / 3) < 1e-4
    assert np.nanmean(red) == pytest.approx(0.66659, abs=5e-6)


def test_table1_case_c_single_point_by_hand():
    """x1 = centre + (30, 15): e = (49.5, 49.5), p_inf = x1, r = 15 sqrt(5). The line,
    of direction (2, 1), leaves the square at x = 49.5 +- 50, so the chord is
    2 h = 2 * 25 sqrt(5) and the reduction is 1 - 15 / 50 = 0.7."""
    geom = table1_geometry(K_CORNER, [0, 0, 1])
    seg = geom.segments([[79.5, 64.5]])
    np.testing.assert_allclose(seg.start, [[49.5, 49.5]], atol=ATOL)
    np.testing.assert_allclose(seg.end, [[79.5, 64.5]], atol=ATOL)
    np.testing.assert_allclose(seg.infinity_point, [[79.5, 64.5]], atol=ATOL)
    np.testing.assert_allclose(seg.epipole, [49.5, 49.5], atol=ATOL)
    np.testing.assert_allclose(seg.length, [15 * np.sqrt(5)], rtol=RTOL)
    np.testing.assert_allclose(seg.line_length, [50 * np.sqrt(5)], rtol=RTOL)
    np.testing.assert_allclose(seg.reduction, [0.7], rtol=RTOL)
    np.testing.assert_allclose(np.abs(seg.line[0]), np.abs([1, -2, 49.5]) / np.sqrt(5), atol=ATOL)
    assert set(np.round(np.sort(seg.line_start[0].tolist() + seg.line_end[0].tolist()), 9)) == {-0.5, 24.5, 74.5, 99.5}


def test_table1_case_d_lateral():
    """t = (1, 0, 0): w(z1) = z1 [x1; 1] + (50, 0, 0), the pixel x1 + (50 / z1, 0). The
    segment runs from the right edge (z1 -> 0) to p_inf = x1; the line is the whole row.
    Reduction (x + 0.5) / 100 per pixel, mean exactly 1/2, whatever cx is."""
    pts = grid()
    for K in (K_PAPER, K_CORNER):
        seg = table1_geometry(K, [1, 0, 0]).segments(pts)
        assert seg.valid.all()
        np.testing.assert_allclose(seg.end, pts, atol=ATOL)
        np.testing.assert_allclose(seg.start, np.column_stack([np.full(len(pts), 99.5), pts[:, 1]]), atol=ATOL)
        np.testing.assert_allclose(seg.line_length, 100.0, rtol=RTOL)
        np.testing.assert_allclose(seg.reduction, (pts[:, 0] + 0.5) / 100, atol=1e-12)
        assert seg.reduction.mean() == pytest.approx(0.5, abs=1e-12)
        assert seg.epipole[0] == np.inf


# -- degenerate cases ------------------------------------------------------------------

K_A = np.array([[400.0, 2.0, 310.0], [0, 380.0, 245.0], [0, 0, 1]])
K_B = np.array([[520.0, 0.0, 330.0], [0, 530.0, 235.0], [0, 0, 1]])
VGA = (640, 480)


def general_geometry(R, t):
    return TwoViewGeometry(K_A, K_B, R, t, image_size1=VGA, image_size2=VGA)


def test_epipole_at_infinity():
    """t_3 = 0: a ray from p_inf in the direction of (b1, b2), b = K2 t (Proposition 2, rectified stereo)."""
    R = rodrigues([0.02, -0.03, 0.01])
    t = np.array([1.0, -0.4, 0.0])
    geom = general_geometry(R, t)
    assert not np.all(np.isfinite(geom.epipole))
    x1 = np.array([[100.0, 200.0], [320.0, 240.0], [500.0, 300.0]])
    seg = geom.segments(x1)
    a = np.column_stack([x1, np.ones(3)]) @ geom.infinity_homography.T
    p_inf = a[:, :2] / a[:, 2:3]
    b = K_B @ t
    assert inside(p_inf, VGA).all()
    assert seg.valid.all()
    np.testing.assert_allclose(seg.end, p_inf, atol=1e-9)
    direction = seg.start - seg.end
    cross = direction[:, 0] * b[1] - direction[:, 1] * b[0]
    np.testing.assert_allclose(cross / np.linalg.norm(direction, axis=1), 0, atol=1e-9)
    assert np.all(direction @ b[:2] > 0)
    assert not np.all(inside(seg.start, VGA, pad=1e-9), axis=None)  # the start is on the border
    np.testing.assert_allclose(seg.reduction, 1 - seg.length / seg.line_length)


# (R n1)_3 = -n_x exactly with R a rotation of 90 degrees about y; and with a K1 of powers
# of two, K1^-1 is exact, so a3 = 0 exactly for x1 on the column x = cx.
R_Y90 = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
K_POW2 = np.array([[512.0, 0, 320], [0, 512, 240], [0, 0, 1]])


def infinity_geometry():
    return TwoViewGeometry(K_POW2, K_B, R_Y90, [0.1, 0.2, 1.0], image_size1=VGA, image_size2=VGA)


def test_infinity_point_at_infinity():
    """(R n1)_3 = 0 with t_3 > 0: a ray from the epipole in the direction of (a1, a2)."""
    geom = infinity_geometry()
    x1 = np.array([320.0, 100.0, 1.0])
    seg = geom.segments([x1[:2]])
    a = geom.infinity_homography @ x1
    assert a[2] == 0.0
    assert not np.all(np.isfinite(seg.infinity_point))
    assert seg.valid[0]
    np.testing.assert_allclose(geom.epipole, (K_B @ [0.1, 0.2, 1.0])[:2], atol=1e-12)
    np.testing.assert_allclose(seg.start[0], geom.epipole, atol=1e-9)
    direction = seg.end[0] - seg.start[0]
    assert abs(direction[0] * a[1] - direction[1] * a[0]) / np.linalg.norm(direction) < 1e-9 * np.linalg.norm(a[:2])
    assert direction @ a[:2] > 0
    assert not inside(seg.end, VGA, pad=1e-6)[0]  # the segment runs to the border


def test_ray_wholly_behind_camera2():
    """a3 < 0 and b3 < 0 (cameras facing away): the paper's 'does not occur'. Empty."""
    geom = general_geometry(rot_y(180), [0.1, 0.0, -1.0])
    x1 = grid(VGA, step=80.0)
    seg = geom.segments(x1)
    a = np.column_stack([x1, np.ones(len(x1))]) @ geom.infinity_homography.T
    assert np.all(a[:, 2] < 0) and geom.t[2] < 0
    assert not seg.valid.any()
    assert np.isnan(seg.start).all() and np.isnan(seg.end).all()
    assert np.all(seg.length == 0)
    # the line itself is well defined, and a point on it is labelled EMPTY_SEGMENT
    assert np.all(np.isfinite(seg.line))
    p = seg.line_start + 0.3 * (seg.line_end - seg.line_start)
    ok = np.all(np.isfinite(p), axis=1)
    assert ok.any()
    assert np.all(seg.distance(np.nan_to_num(p)) == np.inf)
    assert np.all(seg.classify(p[ok] if ok.all() else np.nan_to_num(p), 1e-6)[ok] == Rejection.EMPTY_SEGMENT)


def test_pure_rotation():
    """t = 0: the segment is the single point H_inf x1, whatever the depth range."""
    R = rodrigues([0.05, -0.1, 0.02])
    geom = general_geometry(R, [0.0, 0.0, 0.0])
    x1 = np.array([[300.0, 200.0], [350.0, 260.0], [10.0, 470.0]])
    h = np.column_stack([x1, np.ones(3)]) @ geom.infinity_homography.T
    expected = h[:, :2] / h[:, 2:3]
    for dr in [(0.0, np.inf), (1.0, 3.0)]:
        seg = geom.segments(x1, depth_range=dr)
        vis = inside(expected, VGA)
        assert np.array_equal(seg.valid, vis)
        np.testing.assert_allclose(seg.start[vis], expected[vis], atol=1e-9)
        np.testing.assert_allclose(seg.end[vis], expected[vis], atol=1e-9)
        np.testing.assert_allclose(seg.distance(np.nan_to_num(expected))[vis], 0, atol=1e-9)
        assert np.all(seg.length <= 1e-9)
        assert np.isnan(seg.line).all()  # no epipolar line when t = 0


@pytest.mark.parametrize("t3", [1e-12, -1e-12, 1e-9])
def test_near_zero_t3_is_continuous(t3):
    R = rodrigues([0.02, -0.03, 0.01])
    x1 = grid(VGA, step=64.0)
    exact = general_geometry(R, [1.0, -0.4, 0.0]).segments(x1)
    near = general_geometry(R, [1.0, -0.4, t3]).segments(x1)
    assert np.array_equal(exact.valid, near.valid)
    np.testing.assert_allclose(near.start, exact.start, atol=1e-3)
    np.testing.assert_allclose(near.end, exact.end, atol=1e-3)
    np.testing.assert_allclose(near.reduction, exact.reduction, atol=1e-6)


@pytest.mark.parametrize("a3", [1e-12, -1e-12, 1e-9])
def test_near_zero_infinity_point_is_continuous(a3):
    """Move x1 off the column x = cx so that (K2 R n1)_3 = a3 instead of 0."""
    geom = infinity_geometry()
    x_exact = np.array([[320.0, 100.0]])
    x_near = x_exact - [[512.0 * a3, 0.0]]  # n_x = -a3, so (R n1)_3 = a3
    assert abs(geom.infinity_homography[2] @ np.r_[x_near[0], 1] - a3) < 1e-15
    exact, near = geom.segments(x_exact), geom.segments(x_near)
    assert exact.valid[0] and near.valid[0]
    np.testing.assert_allclose(near.start, exact.start, atol=1e-6)
    np.testing.assert_allclose(near.end, exact.end, atol=1e-3)
    np.testing.assert_allclose(near.reduction, exact.reduction, atol=1e-6)
    np.testing.assert_allclose(near.line, exact.line, atol=1e-6)


def test_empty_input():
    geom = general_geometry(rot_y(10), [1.0, 0.0, 0.2])
    for pts in ([], np.zeros((0, 2))):
        for dr in [(0.0, np.inf), (np.zeros(0), np.ones(0))]:
            seg = geom.segments(pts, depth_range=dr)
            assert isinstance(seg, EpipolarSegments) and len(seg) == 0
            for name, shape, dtype in [("start", (0, 2), np.float64), ("end", (0, 2), np.float64),
                                       ("valid", (0,), np.bool_), ("line", (0, 3), np.float64),
                                       ("infinity_point", (0, 2), np.float64), ("line_start", (0, 2), np.float64),
                                       ("line_end", (0, 2), np.float64), ("length", (0,), np.float64),
                                       ("line_length", (0,), np.float64), ("reduction", (0,), np.float64)]:
                arr = getattr(seg, name)
                assert arr.shape == shape and arr.dtype == dtype, name
            assert seg.epipole.shape == (2,)
            assert seg.distance(np.zeros((0, 2))).shape == (0,)
            assert seg.line_distance([]).shape == (0,)
            labels = seg.classify(np.zeros((0, 2)), 1.0)
            assert labels.shape == (0,) and labels.dtype == np.int8
            assert len(seg.take(np.zeros(0, dtype=int))) == 0
    p2, z2 = geom.transfer(np.zeros((0, 2)), 1.0)
    assert p2.shape == (0, 2) and z2.shape == (0,)


def test_outputs_are_read_only():
    seg = general_geometry(rot_y(10), [1.0, 0.0, 0.2]).segments([[1.0, 2.0]])
    with pytest.raises(ValueError):
        seg.start[0, 0] = 1.0


# -- reference values from cv2 -----------------------------------------------------------

def test_line_matches_cv2_computeCorrespondEpilines():
    R = rodrigues([0.1, -0.2, 0.05])
    geom = general_geometry(R, [0.5, -0.1, 0.3])
    x1 = np.random.default_rng(0).uniform(0, 640, (50, 2))
    seg = geom.segments(x1)
    # reference: cv2.computeCorrespondEpilines(points, whichImage=1, F) -> (N, 1, 3), a^2 + b^2 = 1
    ref = cv2.computeCorrespondEpilines(x1.reshape(-1, 1, 2), 1, geom.fundamental_matrix).reshape(-1, 3)
    sign = np.sign(np.sum(ref * seg.line, axis=1))
    assert np.all(sign != 0)
    np.testing.assert_allclose(seg.line, ref * sign[:, None], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.hypot(seg.line[:, 0], seg.line[:, 1]), 1.0, rtol=1e-12)


def test_essential_and_fundamental_by_hand():
    # R: 90 degrees about z, so R e_x = e_y, R e_y = -e_x. t = (1, 2, 3).
    R = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    t = np.array([1.0, 2.0, 3.0])
    tx = np.array([[0, -3, 2], [3, 0, -1], [-2, 1, 0]])
    E = np.array([[-3, 0, 2], [0, -3, -1], [1, 2, 0]])  # [t]_x R, multiplied out by hand
    np.testing.assert_array_equal(tx @ R, E)
    K1 = np.array([[2.0, 0, 1], [0, 4, 2], [0, 0, 1]])
    K2 = np.array([[5.0, 0, 0], [0, 5, 0], [0, 0, 1]])
    geom = TwoViewGeometry(K1, K2, R, t, image_size1=(4, 4), image_size2=(4, 4))
    np.testing.assert_allclose(geom.essential_matrix, E, atol=ATOL)
    # K1^-1 = [[1/2, 0, -1/2], [0, 1/4, -1/2], [0, 0, 1]], K2^-T = diag(1/5, 1/5, 1)
    F = np.array([[-3 / 10, 0, 3 / 2 / 5 + 2 / 5],
                  [0, -3 / 20, 3 / 2 / 5 - 1 / 5],
                  [1 / 2, 2 / 4, -1 / 2 - 1]])
    np.testing.assert_allclose(geom.fundamental_matrix, F, atol=ATOL)
    np.testing.assert_allclose(geom.epipole, [5 / 3, 10 / 3], atol=ATOL)


def test_fundamental_matches_cv2_findFundamentalMat():
    rng = np.random.default_rng(1)
    R = rodrigues([0.05, 0.2, -0.03])
    geom = general_geometry(R, [-1.0, 0.1, 0.2])
    x1, z1 = rng.uniform(0, 480, (60, 2)), rng.uniform(2, 10, 60)
    x2, z2 = geom.transfer(x1, z1)
    assert np.all(z2 > 0)
    # reference: cv2.findFundamentalMat(pts1, pts2, cv2.FM_8POINT) on exact correspondences
    F_cv, _ = cv2.findFundamentalMat(x1, x2, cv2.FM_8POINT)
    F = geom.fundamental_matrix
    F, F_cv = F / np.linalg.norm(F), F_cv / np.linalg.norm(F_cv)
    F_cv *= np.sign(np.sum(F * F_cv))
    np.testing.assert_allclose(F, F_cv, atol=1e-6)
    h1, h2 = np.column_stack([x1, np.ones(60)]), np.column_stack([x2, np.ones(60)])
    np.testing.assert_allclose(np.einsum("ij,jk,ik->i", h2, geom.fundamental_matrix, h1), 0, atol=1e-9)


# -- invariants ----------------------------------------------------------------------------

@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenes())
def test_inverse_symmetry(scene):
    """y on seg(x) iff x on seg'(y), for points at any depth (either sign) along x's ray."""
    geom, rng = scene
    inv = geom.inverse()
    x1, z1 = random_rays(geom, rng, 1000)
    z1 *= rng.choice([-1.0, 1.0], len(z1))
    y, z2 = geom.transfer(x1, z1)
    both = inside(y, geom.image_size2) & (np.abs(z2) > 1e-9 * np.abs(z1))
    x1, y, z1, z2 = x1[both], y[both], z1[both], z2[both]
    tol1, tol2 = SEG_RTOL * pixel_scale(geom), SEG_RTOL * pixel_scale(inv)
    fwd, bwd = geom.segments(x1), inv.segments(y)
    d_fwd, d_bwd = fwd.distance(y), bwd.distance(x1)
    true = (z1 > 0) & (z2 > 0)
    assert np.all(d_fwd[true] <= tol1) and np.all(d_bwd[true] <= tol2)
    # false pairs: off in both directions, where they are clearly separated from e and p_inf
    sep_f = finite_min_dist(y, fwd.epipole, fwd.infinity_point) > 10 * tol1
    sep_b = finite_min_dist(x1, bwd.epipole, bwd.infinity_point) > 10 * tol2
    clear = ~true & sep_f & sep_b
    assert np.all(d_fwd[clear] > tol1) and np.all(d_bwd[clear] > tol2)


def test_inverse_twice_is_identity():
    geom = TwoViewGeometry(K_A, K_B, rodrigues([0.3, -1.0, 2.0]), [0.3, -2.0, 1.0],
                           image_size1=(640, 480), image_size2=(800, 600))
    inv = geom.inverse()
    assert inv.image_size1 == (800, 600) and inv.image_size2 == (640, 480)
    np.testing.assert_array_equal(inv.K1, K_B)
    np.testing.assert_array_equal(inv.K2, K_A)
    np.testing.assert_allclose(inv.R, geom.R.T, atol=ATOL)
    np.testing.assert_allclose(inv.t, -geom.R.T @ geom.t, atol=ATOL)
    back = inv.inverse()
    for name in ("K1", "K2", "R", "t"):
        np.testing.assert_allclose(getattr(back, name), getattr(geom, name), rtol=1e-12, atol=1e-12)
    assert (back.image_size1, back.image_size2) == (geom.image_size1, geom.image_size2)
    np.testing.assert_allclose(inv.fundamental_matrix, geom.fundamental_matrix.T, atol=1e-15)


def _world_poses(rng):
    R1, R2 = rodrigues(rng.normal(size=3)), rodrigues(rng.normal(size=3))
    t1, t2 = rng.normal(size=3), rng.normal(size=3)
    return R1, t1, R2, t2


def test_from_world_poses():
    rng = np.random.default_rng(2)
    R1, t1, R2, t2 = _world_poses(rng)
    geom = TwoViewGeometry.from_world_poses(K_A, R1, t1, K_B, R2, t2, image_size1=VGA, image_size2=(320, 240))
    # a world point, expressed in each camera, must satisfy X2 = R X1 + t
    Xw = rng.normal(size=(10, 3))
    X1, X2 = Xw @ R1.T + t1, Xw @ R2.T + t2
    np.testing.assert_allclose(X1 @ geom.R.T + geom.t, X2, atol=1e-12)
    np.testing.assert_allclose(geom.R, R2 @ R1.T, atol=1e-12)
    np.testing.assert_allclose(geom.t, t2 - R2 @ R1.T @ t1, atol=1e-12)
    np.testing.assert_array_equal(geom.K1, K_A)
    np.testing.assert_array_equal(geom.K2, K_B)
    assert geom.image_size2 == (320, 240)
    # identity first pose: the relative pose is the second
    g = TwoViewGeometry.from_world_poses(K_A, np.eye(3), np.zeros(3), K_B, R2, t2, image_size1=VGA, image_size2=VGA)
    np.testing.assert_allclose(g.R, R2, atol=1e-15)
    np.testing.assert_allclose(g.t, t2, atol=1e-15)


def test_view_geometry_is_from_world_poses_to_the_bit():
    """``View.geometry_to`` builds from the views' checked values without checking them again: the same bits."""
    from episeg_cv.colmap import View

    rng = np.random.default_rng(5)
    for _ in range(20):
        R1, t1, R2, t2 = _world_poses(rng)
        a = View("a.png", 1, 1, K_A, R1, t1, VGA)
        b = View("b.png", 2, 1, K_B, R2, t2, (320, 240))
        want = TwoViewGeometry.from_world_poses(K_A, a.R, a.t, K_B, b.R, b.t, image_size1=VGA, image_size2=(320, 240))
        got = a.geometry_to(b)
        for name in ("K1", "K2", "R", "t", "infinity_homography", "epipole_homogeneous"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
        assert (got.image_size1, got.image_size2) == (VGA, (320, 240)) and not got.R.flags.writeable


@pytest.mark.parametrize("s1, s2", [(1.0, 1.0), (3.7, 0.02), (-1.0, -1.0), (-2.5, 4.0), (1e3, -1e-3)])
def test_from_projection_matrices(s1, s2):
    """P = s K [R | t] for any non-zero s, including negative: same K, R and t."""
    rng = np.random.default_rng(3)
    R1, t1, R2, t2 = _world_poses(rng)
    P1 = s1 * K_A @ np.column_stack([R1, t1])
    P2 = s2 * K_B @ np.column_stack([R2, t2])
    direct = TwoViewGeometry.from_world_poses(K_A, R1, t1, K_B, R2, t2, image_size1=VGA, image_size2=VGA)
    geom = TwoViewGeometry.from_projection_matrices(P1, P2, image_size1=VGA, image_size2=VGA)
    np.testing.assert_allclose(geom.K1, K_A, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(geom.K2, K_B, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(geom.R, direct.R, atol=1e-10)
    np.testing.assert_allclose(geom.t, direct.t, atol=1e-10)  # the scale of P cancels: t in world units
    x1 = np.array([[100.0, 100.0], [320.0, 240.0]])
    a, b = geom.segments(x1), direct.segments(x1)
    np.testing.assert_array_equal(a.valid, b.valid)
    np.testing.assert_allclose(a.start, b.start, atol=1e-6)
    np.testing.assert_allclose(a.end, b.end, atol=1e-6)


# -- classify ------------------------------------------------------------------------------

def test_classify_labels_by_hand():
    """Case c (cx = 49.5): for x1 = (79.5, 49.5) the line is the row y = 49.5, the epipole
    is (49.5, 49.5), p_inf = x1 and the segment is [49.5, 79.5] x {49.5}. With depths in
    [2, 4], w(z1) = z1 [x1; 1] + (49.5, 49.5, 1) puts the ends at x = (79.5 z1 + 49.5) / (z1 + 1),
    that is 69.5 and 73.5."""
    geom = table1_geometry(K_CORNER, [0, 0, 1])
    x1 = np.array([[79.5, 49.5]])
    cases = [((60.0, 49.5), Rejection.ON_SEGMENT), ((90.0, 49.5), Rejection.BEYOND_INFINITY),
             ((30.0, 49.5), Rejection.BEYOND_EPIPOLE), ((60.0, 60.0), Rejection.OFF_LINE),
             ((79.4, 49.5), Rejection.ON_SEGMENT), ((79.5, 50.0), Rejection.ON_SEGMENT)]
    seg = geom.segments(np.repeat(x1, len(cases), axis=0))
    pts = np.array([c[0] for c in cases])
    np.testing.assert_array_equal(seg.classify(pts, 1.0), [c[1] for c in cases])

    seg = geom.segments(x1, depth_range=(2.0, 4.0))
    np.testing.assert_allclose(seg.start, [[69.5, 49.5]], atol=ATOL)
    np.testing.assert_allclose(seg.end, [[73.5, 49.5]], atol=ATOL)
    ranged = [((71.0, 49.5), Rejection.ON_SEGMENT), ((60.0, 49.5), Rejection.OUT_OF_RANGE),
              ((76.0, 49.5), Rejection.OUT_OF_RANGE), ((85.0, 49.5), Rejection.BEYOND_INFINITY),
              ((40.0, 49.5), Rejection.BEYOND_EPIPOLE), ((71.0, 55.0), Rejection.OFF_LINE)]
    seg = seg.take(np.zeros(len(ranged), dtype=int))
    np.testing.assert_array_equal(seg.classify([c[0] for c in ranged], 1.0), [c[1] for c in ranged])

    # EMPTY_SEGMENT: cameras facing away (a3 < 0, b3 < 0); the line is still the row y = 49.5
    away = table1_geometry(K_CORNER, [0, 0, -1], R=rot_y(180))
    seg = away.segments(x1)
    assert not seg.valid[0]
    np.testing.assert_allclose(np.abs(seg.line[0]), [0, 1, 49.5], atol=ATOL)
    assert seg.classify([[10.0, 49.5]], 1.0)[0] == Rejection.EMPTY_SEGMENT
    assert seg.classify([[10.0, 60.0]], 1.0)[0] == Rejection.OFF_LINE
    assert len(Rejection.NAMES) == 6


# -- depth range and margin ------------------------------------------------------------------

def test_per_point_depth_range_equals_scalar_calls():
    R = rodrigues([0.05, -0.1, 0.02])
    geom = general_geometry(R, [-0.8, 0.1, 0.3])
    rng = np.random.default_rng(4)
    x1 = rng.uniform(0, 480, (20, 2))
    zmin = rng.uniform(0, 3, 20)
    zmax = zmin + rng.uniform(0.1, 10, 20)
    zmax[::4] = np.inf
    seg = geom.segments(x1, depth_range=(zmin, zmax))
    for i in range(len(x1)):
        one = geom.segments(x1[i:i + 1], depth_range=(zmin[i], zmax[i]))
        assert one.valid[0] == seg.valid[i]
        np.testing.assert_allclose(one.start[0], seg.start[i], atol=1e-12)
        np.testing.assert_allclose(one.end[0], seg.end[i], atol=1e-12)
    # mixed: an array zmin with a scalar zmax
    mixed = geom.segments(x1, depth_range=(zmin, np.inf))
    full = geom.segments(x1, depth_range=(zmin, np.full(20, np.inf)))
    np.testing.assert_array_equal(mixed.start, full.start)


def test_depth_range_shortens_the_segment():
    geom = table1_geometry(K_CORNER, [0, 0, 1])
    x1 = grid(step=7.0)
    full = geom.segments(x1)
    part = geom.segments(x1, depth_range=(0.5, 3.0))
    assert np.all(part.length <= full.length + 1e-12)
    np.testing.assert_allclose(part.line_length, full.line_length)
    # both ends finite and in front of camera 2: the ends are the images of zmin and zmax
    p, _ = geom.transfer(x1, 0.5)
    q, _ = geom.transfer(x1, 3.0)
    np.testing.assert_allclose(part.start, p, atol=1e-9)
    np.testing.assert_allclose(part.end, q, atol=1e-9)


def test_margin_grows_the_clip_rectangle():
    geom = table1_geometry(K_CORNER, [1, 0, 0])  # case d: the segment runs to the right edge
    x1 = np.array([[20.0, 30.0], [20.0, 99.0]])
    plain = geom.segments(x1)
    grown = geom.segments(x1, margin=10.0)
    np.testing.assert_allclose(plain.start[:, 0], 99.5, atol=ATOL)
    np.testing.assert_allclose(grown.start[:, 0], 109.5, atol=ATOL)
    np.testing.assert_allclose(grown.line_length, 120.0, rtol=RTOL)
    assert grown.margin == 10.0
    # a point just outside the image is found only with the margin
    outside = geom.segments([[20.0, 30.0]]).distance([[105.0, 30.0]])
    assert outside[0] == pytest.approx(5.5)
    assert geom.segments([[20.0, 30.0]], margin=10.0).distance([[105.0, 30.0]])[0] == 0.0
    # a pixel of image 1 whose ray images wholly outside image 2 is found only with the margin
    away = geom.segments([[20.0, 103.0]])
    assert not away.valid[0]
    assert geom.segments([[20.0, 103.0]], margin=5.0).valid[0]


def test_camera_inverse_is_the_inverse():
    """Property: the closed-form ``K^-1`` (skew, off-centre principal points, focal lengths 1 to 1e5)."""
    from episeg_cv.geometry import _camera_inverse

    rng = np.random.default_rng(0)
    for _ in range(50):
        f = 10 ** rng.uniform(0, 5, 2)
        K = np.array([[f[0], rng.normal(0, 5), rng.uniform(-1e3, 1e4)], [0, f[1], rng.uniform(-1e3, 1e4)], [0, 0, 1]])
        np.testing.assert_allclose(_camera_inverse(K), np.linalg.inv(K), rtol=1e-12, atol=1e-15)
