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


def _blobs(size=(320, 240), seed=0):
    """Gaussian blobs (sigma 3 px) at known sub-pixel centres on a grey background."""
    rng = np.random.default_rng(seed)
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    centres = np.array([[cx + rng.uniform(-0.5, 0.5), cy + rng.uniform(-0.5, 0.5)]
                        for cy in range(30, h - 20, 40) for cx in range(30, w - 20, 40)])
    img = sum(np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 3.0 ** 2)) for cx, cy in centres)
    return np.clip(40 + 180 * img, 0, 255).astype(np.uint8), centres


def test_upscale_bias_is_removed():
    """OpenCV's SIFT reports blob centres 0.25 px right and down (its 2x upscale); the collection preset does not."""
    image, centres = _blobs()
    for name, expected in (("colmap", 0.25), ("collection", 0.0)):
        kp, _ = detect_features(image, PRESETS[name])
        err = kp[:, None] - centres[None]
        nearest = np.argmin(np.linalg.norm(err, axis=2), axis=1)
        e = kp - centres[nearest]
        e = e[np.linalg.norm(e, axis=1) < 2]  # the blob keypoints (not those of the grid of blobs as a whole)
        assert len(e) > 100
        np.testing.assert_allclose(np.median(e, axis=0), [expected, expected], atol=0.03)


def test_collection_preset_is_cv2_sift_with_its_settings(image):
    import cv2

    cfg = PRESETS["collection"].replace(max_features=500)
    assert (cfg.sift_contrast, cfg.sift_sigma, cfg.root_sift, cfg.fix_upscale_bias) == (0.01, 1.4, True, True)
    kp, des = detect_features(image, cfg)
    ref_kp, ref_des = cv2.SIFT_create(nfeatures=500, contrastThreshold=0.01, sigma=1.4).detectAndCompute(image, None)
    order = np.argsort([-k.response for k in ref_kp], kind="stable")[:500]
    np.testing.assert_allclose(kp, cv2.KeyPoint_convert(ref_kp)[order] - 0.25, atol=1e-4)
    ref = ref_des[order] / ref_des[order].sum(axis=1, keepdims=True)
    np.testing.assert_allclose(des, np.sqrt(ref), atol=1e-6)
    # more keypoints than COLMAP's threshold finds, on the same image
    assert len(detect_features(image, PRESETS["collection"])[0]) > len(detect_features(image, PRESETS["colmap"])[0])


@pytest.mark.parametrize("kwargs, match", [({"sift_sigma": 0}, "sift_sigma"), ({"sift_contrast": -0.1}, "sift_contrast"),
                                           ({"sift_sigma": float("inf")}, "sift_sigma"),
                                           ({"sift_contrast": "0.01"}, "sift_contrast")])
def test_sift_settings_are_checked(kwargs, match):
    with pytest.raises(ValueError, match=match):
        FeatureConfig(**kwargs)
