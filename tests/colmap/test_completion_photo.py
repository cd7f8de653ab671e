"""The compiled photometric check of track completion (:func:`episeg_cv.colmap.completion.photo_consistency`)
against a plain NumPy reference, OpenCV's remap, and hand-made cases."""

import cv2
import numpy as np
import pytest

from episeg_cv import threads
from episeg_cv.colmap import _completion_kernel as kernel
from episeg_cv.colmap.completion import MAX_ANGLE, PATCH, photo_consistency

K = np.array([[100.0, 0, 60], [0, 100.0, 50], [0, 0, 1]])


def _texture(seed, shape=(100, 120), sigma=0.8):
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.uniform(0, 255, shape).astype(np.float32), (0, 0), sigma)


def _camera(R, c):
    return K @ np.column_stack([R, -R @ c])


def _rot_y(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def _bilinear(image, x, y):
    """Exact bilinear interpolation, NaN unless the four neighbours are inside (pixel centres at integers)."""
    h, w = image.shape
    x0, y0 = np.floor(x), np.floor(y)
    inside = (x0 >= 0) & (x0 <= w - 2) & (y0 >= 0) & (y0 <= h - 2)
    i, j = np.where(inside, x0, 0).astype(int), np.where(inside, y0, 0).astype(int)
    a, b = x - x0, y - y0
    im = image.astype(np.float64)
    v = ((1 - a) * (1 - b) * im[j, i] + a * (1 - b) * im[j, i + 1] + (1 - a) * b * im[j + 1, i]
         + a * b * im[j + 1, i + 1])
    return np.where(inside, v, np.nan)


def _reference(P, centers, X, k, y, obs, images, half=PATCH):
    """The NCC of one proposal with each of its group's views, written out in NumPy (no angle test)."""
    o = np.arange(-half, half + 1.0)
    gx, gy = np.meshgrid(o, o)
    px = np.column_stack([y[0] + gx.ravel(), y[1] + gy.ravel(), np.ones(gx.size)])
    rays = px @ np.linalg.inv(P[k][:, :3]).T
    normal = (centers[k] - X) / np.linalg.norm(centers[k] - X)
    plane = centers[k] + ((X - centers[k]) @ normal / (rays @ normal))[:, None] * rays
    a = _bilinear(images[k], px[:, 0], px[:, 1])
    out = []
    for v in obs:
        h = np.column_stack([plane, np.ones(len(plane))]) @ P[v].T
        b = _bilinear(images[v], h[:, 0] / h[:, 2], h[:, 1] / h[:, 2])
        a0, b0 = a - a.mean(), b - b.mean()
        out.append((a0 @ b0) / np.sqrt((a0 @ a0) * (b0 @ b0)))
    return np.array(out)


def _scene():
    """Three cameras round a textured plane z = 5 (views 1, 2 turned 8 and -12 degrees towards it), each
    image the plane's texture as that camera sees it."""
    R = [np.eye(3), _rot_y(-8.0), _rot_y(12.0)]
    c = [np.zeros(3), np.array([0.6, 0.05, 0.1]), np.array([-0.9, -0.1, 0.3])]
    P = np.array([_camera(r, cc) for r, cc in zip(R, c)])
    tex = _texture(0)
    images = [tex]
    for v in (1, 2):  # the plane z = 5 seen from view v: the homography view 0 -> view v, sampled backwards
        n, d = np.array([0, 0, 1.0]), 5.0
        H = K @ (R[v] + np.outer(-R[v] @ c[v], n) / d) @ np.linalg.inv(K)
        images.append(cv2.warpPerspective(tex, H, tex.shape[::-1], flags=cv2.INTER_LINEAR))
    return P, np.array(c), images


def test_sample_is_opencv_remap():
    """The kernel's bilinear sample gives OpenCV's remap (float32 maps, constant NaN border) bit for bit,
    borders included."""
    rng = np.random.default_rng(3)
    im = _texture(1, (37, 53), 1.0)
    x = rng.uniform(-2, 55, 4000)
    y = rng.uniform(-2, 39, 4000)
    x[:200], y[200:400] = np.round(x[:200]), np.round(y[200:400])  # exact edges: 52 and 36 are outside
    want = cv2.remap(im, x.astype(np.float32)[None], y.astype(np.float32)[None], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)[0]
    got = np.array([kernel.sample(im.ravel(), 0, 53, 37, a, b) for a, b in zip(x, y)])
    np.testing.assert_array_equal(got, want)
    assert 0 < np.isnan(got).sum() < len(got)


def test_ncc_is_the_numpy_reference_and_half_a_pixel_is_not():
    """On a plane seen by three cameras, the NCC of proposals at sub-pixel positions equals the NumPy
    reference (float32 rounding); the reference shifted by half a pixel differs, by far more."""
    P, centers, images = _scene()
    rng = np.random.default_rng(5)
    y = rng.uniform([30, 25], [90, 75], (12, 2))
    rays = np.column_stack([y, np.ones(len(y))]) @ np.linalg.inv(K).T
    X = rays * (5.0 / rays[:, 2:])  # on the plane, in view 0
    for k, obs in ((0, [1, 2]), (1, [0, 2]), (2, [1])):  # each view in turn the proposal's
        h = np.column_stack([X, np.ones(len(X))]) @ P[k].T
        yk = h[:, :2] / h[:, 2:]
        obs_image = np.array([obs + [-1] * (2 - len(obs))] * len(X))
        got = photo_consistency(P, centers, X, np.full(len(X), k), yk, obs_image, images.__getitem__)
        want = np.array([_reference(P, centers, X[t], k, yk[t], obs, images).min() for t in range(len(X))])
        shifted = np.array([_reference(P, centers, X[t], k, yk[t] + [0.5, 0.0], obs, images).min()
                            for t in range(len(X))])
        inside = np.isfinite(want)  # (NaN: a patch leaves an image, in both)
        assert inside.sum() >= 4 and (want[inside] > 0.9).all()  # true correspondences correlate
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)
        assert np.nanmax(np.abs(shifted - want)) > 100 * 1e-5


def test_hand_made_translation():
    """Two parallel cameras 0.5125 apart see z = 5 shifted by 10.25 pixels; view 1's image is view 0's
    moved by that (bilinear), so a keypoint's patch has NCC near 1, the NumPy reference's value."""
    tex = _texture(2)
    P = np.array([_camera(np.eye(3), np.array([b, 0, 0])) for b in (0.0, 0.5125)])
    centers = np.array([[0.0, 0, 0], [0.5125, 0, 0]])
    M = np.float32([[1, 0, -10.25], [0, 1, 0]])
    ims = [tex, cv2.warpAffine(tex, M, (120, 100), flags=cv2.INTER_LINEAR)]
    X = np.array([[-0.1, 0.05, 5.0], [0.2, -0.2, 5.0]])
    y = X[:, :2] / 5.0 * 100 + [60, 50]
    got = photo_consistency(P, centers, X, np.array([0, 0]), y, np.array([[1], [1]]), ims.__getitem__)
    want = [_reference(P, centers, X[t], 0, y[t], [1], ims)[0] for t in range(2)]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    assert (got > 0.95).all()


def test_angle_border_and_no_view():
    """NaN beyond MAX_ANGLE or with a patch beyond an image; inf without any group view; an empty input."""
    P, centers, images = _scene()
    X = np.array([[0.0, 0.0, 5.0]])
    y0 = np.array([[60.0, 50.0]])
    f = lambda c1, k, y, obs: photo_consistency(P, c1, X, np.array([k]), y, np.array([obs]), images.__getitem__)
    assert np.isfinite(f(centers, 0, y0, [1, 2]))[0]
    far = centers.copy()
    far[2] = X[0] + 5 * np.array([np.sin(np.radians(MAX_ANGLE + 1)), 0, -np.cos(np.radians(MAX_ANGLE + 1))])
    assert np.isnan(f(far, 0, y0, [1, 2]))[0]  # (the test uses the centres only; the images stay)
    assert np.isnan(f(centers, 0, np.array([[3.0, 50.0]]), [1]))[0]  # the patch leaves view 0's image
    assert f(centers, 0, y0, [-1, -1])[0] == np.inf
    assert photo_consistency(P, centers, X[:0], np.zeros(0, np.int64), y0[:0], np.zeros((0, 2), np.int64),
                             images.__getitem__).shape == (0,)


def test_parallel_twin_is_serial():
    P, centers, images = _scene()
    rng = np.random.default_rng(9)
    y = rng.uniform([10, 10], [110, 90], (300, 2))
    rays = np.column_stack([y, np.ones(len(y))]) @ np.linalg.inv(K).T
    X = rays * (rng.uniform(4, 6, len(y)) / rays[:, 2])[:, None]
    args = (P, centers, X, np.zeros(len(X), np.int64), y, np.tile([1, 2], (len(X), 1)), images.__getitem__)
    with threads.limited(1):
        one = photo_consistency(*args)
    pixels = np.concatenate([im.ravel() for im in images])
    Kinv = np.linalg.inv(P[:, :, :3])
    par = kernel.photo_parallel(Kinv, P, centers, X, args[3], y, args[5], pixels,
                                np.array([0, 12000, 24000]), np.full(3, 120), np.full(3, 100), PATCH,
                                np.cos(np.radians(MAX_ANGLE)), 4)
    np.testing.assert_array_equal(one, par)
    assert np.isfinite(one).sum() > 50


if __name__ == "__main__":
    pytest.main([__file__, "-q"])
