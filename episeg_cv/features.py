"""Keypoints and descriptors: one detector factory with named presets.

The CLI's two-view commands and the posed-collection pipeline use the same
function, :func:`detect_features`, with a :class:`FeatureConfig`. Two presets
name the setups in use:

- ``"opencv"``: OpenCV's own defaults (SIFT contrast threshold 0.04, plain
  L2-normalised SIFT descriptors), what a ``cv2.SIFT_create()`` user gets;
- ``"colmap"``: SIFT as COLMAP sets it up (contrast threshold 0.02, RootSIFT
  descriptors), for collections compared against COLMAP's own pipeline.

Keypoints come back as ``(N, 2)`` float64 pixels (the centre of the top-left
pixel at ``(0, 0)``), strongest response first, at most ``max_features``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from ._validation import as_choice, as_positive_int

__all__ = ["DETECTORS", "FeatureConfig", "PRESETS", "create_detector", "detect_features"]

#: Detector name -> descriptor norm. SIFT is float32 / L2, ORB and AKAZE are binary / Hamming.
DETECTORS = {"sift": "l2", "orb": "hamming", "akaze": "hamming"}

#: The largest ``max_features`` OpenCV's detectors take (a C ``int``).
MAX_FEATURES = 2**31 - 1

#: Descriptor width of each detector (for empty results).
_WIDTHS = {"sift": 128, "orb": 32, "akaze": 61}


@dataclass(frozen=True)
class FeatureConfig:
    """How keypoints are detected and described.

    Attributes
    ----------
    detector : {"sift", "orb", "akaze"}
        ``cv2.SIFT``, ``cv2.ORB`` or AKAZE (in ``cv2`` or ``cv2.xfeatures2d``).
    max_features : int
        Keep at most this many keypoints, strongest response first (SIFT and
        ORB also cap inside the detector).
    sift_contrast : float or None
        SIFT's ``contrastThreshold``; None keeps OpenCV's default (0.04).
    root_sift : bool
        Replace SIFT descriptors by RootSIFT (L1-normalised, then the square
        root; COLMAP's ``L1_ROOT``), which match better under L2. Binary
        descriptors are left as they are.
    """

    detector: str = "sift"
    max_features: int = 8192
    sift_contrast: float | None = None
    root_sift: bool = False

    def __post_init__(self):
        as_choice(self.detector, "detector", tuple(DETECTORS))
        object.__setattr__(self, "max_features", as_positive_int(self.max_features, "max_features"))
        if self.max_features > MAX_FEATURES:
            raise ValueError(f"max_features must be at most {MAX_FEATURES} (OpenCV's int), got {self.max_features}")

    @property
    def norm(self) -> str:
        """The descriptor norm: ``"l2"`` or ``"hamming"``."""
        return DETECTORS[self.detector]

    def replace(self, **changes) -> "FeatureConfig":
        """A copy with some fields changed (and checked)."""
        return dataclasses.replace(self, **changes)


#: Named setups (see the module docstring).
PRESETS = {
    "opencv": FeatureConfig(),
    "colmap": FeatureConfig(sift_contrast=0.02, root_sift=True),
}


def create_detector(config: FeatureConfig):
    """The OpenCV detector of ``config``."""
    if config.detector == "sift":
        extra = {} if config.sift_contrast is None else {"contrastThreshold": config.sift_contrast}
        return cv2.SIFT_create(nfeatures=config.max_features, **extra)
    if config.detector == "orb":
        return cv2.ORB_create(nfeatures=config.max_features)
    create = getattr(cv2, "AKAZE_create", None) or getattr(getattr(cv2, "xfeatures2d", None), "AKAZE_create", None)
    if create is None:
        raise ValueError("AKAZE is not available in this OpenCV build")
    return create()


def detect_features(image: np.ndarray, config: FeatureConfig = PRESETS["colmap"]):
    """Keypoints and descriptors of a grey image, strongest first, at most ``config.max_features``.

    Parameters
    ----------
    image : (H, W) uint8
        A grey image.
    config : FeatureConfig, optional
        Default: the ``"colmap"`` preset.

    Returns
    -------
    keypoints : (N, 2) float64
        Pixel positions (centre of the top-left pixel at ``(0, 0)``).
    descriptors : (N, D) float32 (SIFT, RootSIFT) or uint8 (ORB, AKAZE)

    Examples
    --------
    >>> import numpy as np
    >>> kp, des = detect_features(np.zeros((40, 40), np.uint8))     # nothing to detect: typed empties
    >>> kp.shape, des.shape, des.dtype
    ((0, 2), (0, 128), dtype('float32'))
    """
    kp, des = create_detector(config).detectAndCompute(image, None)
    if des is None or not kp:
        dtype = np.float32 if config.detector == "sift" else np.uint8
        return np.zeros((0, 2)), np.zeros((0, _WIDTHS[config.detector]), dtype)
    order = np.argsort([-k.response for k in kp], kind="stable")[:config.max_features]
    pts = cv2.KeyPoint_convert(kp).astype(np.float64).reshape(-1, 2)
    des = des[order]
    if config.root_sift and config.detector == "sift":
        des = np.sqrt(des / np.maximum(des.sum(axis=1, keepdims=True), 1e-12)).astype(np.float32)
    return pts[order], np.ascontiguousarray(des)
