"""What the two-view commands share: reading images and calibrations, detecting, matching, labelling."""

from __future__ import annotations


import cv2
import numpy as np

from .. import __version__
from ..features import FeatureConfig, detect_features
from ..geometry import Rejection, TwoViewGeometry
from ..io import load_calibration
from ..io.paths import input_file
from ..matching import AcceptRule, SearchConfig, explain_pairs
from ..opencv import SegmentMatcher, pairs_of
from .console import Console, UserError

__all__ = ["MAX_LINES", "read_image", "image_size", "load_calib", "detect", "run_matching", "labels_of",
           "versions"]

#: Lines drawn in the match figures (a random subset; the legend gives the full counts).
MAX_LINES = 300


def read_image(path) -> np.ndarray:
    """A grey image, or a one-line error naming the file."""
    p = input_file(path, "image")
    img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise UserError(f"cannot read image {p} (not an image format OpenCV can decode)")
    return img


def image_size(img) -> tuple[int, int]:
    """``(width, height)`` of an image array."""
    return int(img.shape[1]), int(img.shape[0])


def load_calib(path, img1, img2, console: Console):
    """The calibration of ``path``, with the images' sizes filled in (and checked)."""
    calib = load_calibration(path, image_size1=image_size(img1), image_size2=image_size(img2))
    console.info(f"calibration {path}: image sizes {calib.image_size1} and {calib.image_size2}, "
                 f"distortion {'yes' if calib.has_distortion else 'no'}")
    return calib


def detect(image: np.ndarray, features: FeatureConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(keypoints (N, 2), descriptors)`` of ``image`` (:func:`episeg_cv.features.detect_features`)."""
    return detect_features(image, features)


def _ratio_matches(knn, ratio: float):
    """Lowe's ratio test on ``knnMatch(k=2)`` output."""
    return [m[0] for m in knn if len(m) >= 2 and m[0].distance < ratio * m[1].distance]


def run_matching(geometry: TwoViewGeometry, des1, des2, pts1, pts2, norm, search: SearchConfig,
                 rule: AcceptRule) -> tuple[np.ndarray, np.ndarray]:
    """``(pairs, distances)`` with :class:`~episeg_cv.SegmentMatcher`.

    ``search.constraint == "none"`` is plain ``cv2.BFMatcher``: ``knnMatch(k=2)``
    and the ratio test, or ``match`` with ``crossCheck`` (as OpenCV offers them).
    """
    if len(des1) == 0 or len(des2) == 0:
        return np.zeros((0, 2), np.intp), np.zeros(0, np.float32)
    m = SegmentMatcher(geometry, norm, search=search, rule=rule)
    if search.constraint == "none" and not rule.cross_check:
        dm = _ratio_matches(m.knnMatch(des1, des2, pts1, pts2, 2), rule.ratio)
    else:
        dm = m.match(des1, des2, pts1, pts2)
    return pairs_of(dm), np.array([d.distance for d in dm], dtype=np.float32)


def labels_of(pairs, pts1, pts2, geometry: TwoViewGeometry, search: SearchConfig) -> tuple[list, dict]:
    """The :class:`~episeg_cv.Rejection` name of each pair, and the count of each name."""
    codes, counts = explain_pairs(pairs, pts1, pts2, geometry, search=search)
    return [Rejection.NAMES[c] for c in codes], counts


def versions() -> dict:
    """The versions that a matches file records."""
    return {"episeg_cv": __version__, "opencv": cv2.__version__, "numpy": np.__version__}
