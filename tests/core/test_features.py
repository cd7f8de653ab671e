"""The detector factory and its presets (episeg_cv.features)."""

import numpy as np
import pytest

from episeg_cv import scenes
from episeg_cv.features import PRESETS, FeatureConfig, detect_features


@pytest.fixture(scope="module")
def image():
    return scenes.make_pair("forward", image_size=(320, 240)).image1


def test_sift_descriptors_are_rootsift(image):
    kp, des = detect_features(image, PRESETS["colmap"].replace(max_features=300))
    assert kp.shape == (300, 2) and des.dtype == np.float32
    np.testing.assert_allclose((des ** 2).sum(axis=1), 1.0, rtol=1e-5)  # sqrt of an L1-normalised vector
    for name, width in (("orb", 32), ("akaze", 61)):
        kp, des = detect_features(image, PRESETS["colmap"].replace(detector=name, max_features=200))
        assert des.dtype == np.uint8 and des.shape[1] == width and 0 < len(kp) <= 200
    kp, des = detect_features(np.zeros((50, 50), np.uint8))
    assert kp.shape == (0, 2) and des.shape == (0, 128)


def test_opencv_preset_is_plain_sift_strongest_first(image):
    import cv2

    kp, des = detect_features(image, PRESETS["opencv"].replace(max_features=200))
    ref_kp, ref_des = cv2.SIFT_create(nfeatures=200).detectAndCompute(image, None)  # OpenCV's defaults
    order = np.argsort([-k.response for k in ref_kp], kind="stable")[:200]
    np.testing.assert_array_equal(kp, cv2.KeyPoint_convert(ref_kp)[order])
    np.testing.assert_array_equal(des, ref_des[order])


def test_config_is_checked():
    with pytest.raises(ValueError, match="detector"):
        FeatureConfig(detector="surf")
    with pytest.raises(ValueError, match="max_features"):
        FeatureConfig(max_features=0)
    with pytest.raises(TypeError, match="max_features"):
        FeatureConfig(max_features=2.5)
    assert FeatureConfig(detector="orb").norm == "hamming" and FeatureConfig().norm == "l2"
