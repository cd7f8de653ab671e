"""Shipped data: the default synthetic pair and the Middlebury Motorcycle pair."""

import json

import cv2
import numpy as np
import pytest

from episeg_cv.datasets import data_dir, load_default_pair, load_motorcycle
from episeg_cv.geometry import TwoViewGeometry
from episeg_cv.evaluation import ImagePair
from episeg_cv.scenes import make_pair


@pytest.fixture(scope="module")
def default():
    return load_default_pair()


@pytest.fixture(scope="module")
def motorcycle():
    return load_motorcycle()


@pytest.fixture(scope="module")
def motorcycle_sift(motorcycle):
    """SIFT keypoints of both images, and ratio-test matches (0.7) that keep the row (|dy| < 1)."""
    sift = cv2.SIFT_create(3000)
    k1, d1 = sift.detectAndCompute(motorcycle.image1, None)
    k2, d2 = sift.detectAndCompute(motorcycle.image2, None)
    p1 = np.array([k.pt for k in k1])
    p2 = np.array([k.pt for k in k2])
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    m = np.array([(a.queryIdx, a.trainIdx) for a, b in knn if a.distance < 0.7 * b.distance])
    m = m[np.abs(p1[m[:, 0], 1] - p2[m[:, 1], 1]) < 1.0]
    return p1, p2, m


def test_data_dir_is_the_repository_data():
    d = data_dir()
    assert (d / "default" / "image1.png").is_file() and (d / "motorcycle" / "calib.json").is_file()


def test_default_pair_loads(default):
    assert isinstance(default, ImagePair)
    for img in (default.image1, default.image2):
        assert img.shape == (480, 640) and img.dtype == np.uint8
    for depth in (default.depth1, default.depth2):
        assert depth.shape == (480, 640) and depth.dtype == np.float64
        assert np.isfinite(depth).mean() > 0.99 and depth.min() > 0.5
    assert isinstance(default.geometry, TwoViewGeometry)
    calib = json.loads((data_dir() / "default" / "calib.json").read_text())
    np.testing.assert_array_equal(default.K1, calib["K1"])
    np.testing.assert_array_equal(default.t, calib["t"])
    assert list(default.geometry.image_size1) == calib["image_size1"] == [640, 480]
    assert default.t[2] < 0  # the forward case: the epipole is in image 2
    e = default.geometry.epipole
    assert 0 <= e[0] < 640 and 0 <= e[1] < 480


def test_default_pair_is_what_the_script_renders(default):
    # data/make_default_pair.py renders pose_suite()["forward"] at 640 x 480
    pair = make_pair("forward", (640, 480))
    assert np.mean(np.abs(pair.image1.astype(int) - default.image1)) < 0.5
    assert np.mean(np.abs(pair.image2.astype(int) - default.image2)) < 0.5
    np.testing.assert_allclose(default.depth1, pair.depth1, rtol=1e-6)
    np.testing.assert_allclose(default.geometry.R, pair.R, atol=1e-12)


def test_default_pair_ground_truth_on_sift(default):
    sift = cv2.SIFT_create(1500)
    k1, d1 = sift.detectAndCompute(default.image1, None)
    k2, d2 = sift.detectAndCompute(default.image2, None)
    p1 = np.array([k.pt for k in k1])
    p2 = np.array([k.pt for k in k2])
    gt = default.ground_truth(p1, p2)
    assert gt.match.shape == (len(p1),)
    assert 0.2 * len(p1) < gt.num_matchable < len(p1)
    # mutual ratio-test matches are mostly correct
    knn = cv2.BFMatcher(cv2.NORM_L2, crossCheck=False).knnMatch(d1, d2, k=2)
    m = np.array([(a.queryIdx, a.trainIdx) for a, b in knn if a.distance < 0.6 * b.distance])
    assert gt.is_correct(m).mean() > 0.8


def test_motorcycle_loads(motorcycle):
    assert motorcycle.image1.shape == motorcycle.image2.shape == (500, 741)
    assert motorcycle.image1.dtype == np.uint8
    assert motorcycle.disparity.shape == (500, 741)
    g = motorcycle.geometry
    assert g.image_size1 == g.image_size2 == (741, 500)
    np.testing.assert_array_equal(g.R, np.eye(3))
    np.testing.assert_array_equal(g.t, [-193.001, 0, 0])
    assert g.K1[0, 0] == g.K2[1, 1] == 994.978
    assert g.K2[0, 2] - g.K1[0, 2] == pytest.approx(31.086)
    assert motorcycle.depth2 is None and motorcycle.max_px == 2.0


def test_motorcycle_depth_agrees_with_disparity(motorcycle):
    # projecting a left pixel at depth1 with the geometry gives x - disp, on the same row
    ys, xs = np.mgrid[0:500:7, 0:741:7]
    p = np.column_stack([xs.ravel(), ys.ravel()]).astype(float)
    d = motorcycle.disparity[ys.ravel(), xs.ravel()].astype(np.float64)
    ok = np.isfinite(d)
    x2, _ = motorcycle.geometry.transfer(p[ok], motorcycle.depth1[ys.ravel()[ok], xs.ravel()[ok]])
    np.testing.assert_allclose(x2[:, 0], p[ok, 0] - d[ok], atol=1e-6)
    np.testing.assert_allclose(x2[:, 1], p[ok, 1], atol=1e-9)


def test_motorcycle_disparity_is_indexed_by_the_left_pixel(motorcycle, motorcycle_sift):
    p1, p2, m = motorcycle_sift
    a, b = p1[m[:, 0]], p2[m[:, 1]]
    disp = motorcycle.disparity
    ia, ib = np.rint(a).astype(int), np.rint(b).astype(int)
    # left-indexed: x_R = x_L - disp[y_L, x_L]
    err_left = np.abs(b[:, 0] - (a[:, 0] - disp[ia[:, 1], ia[:, 0]]))
    # right-indexed (how the skimage docstring's example reads): x_L = x_R + disp[y_R, x_R]
    err_right = np.abs(a[:, 0] - (b[:, 0] + disp[ib[:, 1], ib[:, 0]]))
    med_left = np.median(err_left[np.isfinite(err_left)])
    med_right = np.median(err_right[np.isfinite(err_right)])
    assert len(m) > 300
    assert med_left < 0.3 < 0.7 < med_right, (med_left, med_right)  # about 0.16 vs 1.07 px


def test_motorcycle_ground_truth(motorcycle, motorcycle_sift):
    p1, p2, m = motorcycle_sift
    gt = motorcycle.ground_truth(p1, p2)
    assert gt.match.shape == (len(p1),)
    assert 0.3 * len(p1) < gt.num_matchable < len(p1)
    # unknown disparity is not matchable
    d = motorcycle.disparity[np.rint(p1[:, 1]).astype(int), np.rint(p1[:, 0]).astype(int)]
    assert not np.any(gt.matchable & ~np.isfinite(d))
    assert gt.is_correct(m).mean() > 0.85
