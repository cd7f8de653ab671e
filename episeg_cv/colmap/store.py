"""Features of each image, computed once and cached on disk."""

from __future__ import annotations

import functools
import hashlib
import os
import re
from pathlib import Path

import cv2
import numpy as np

from ..features import PRESETS, FeatureConfig, detect_features
from .views import View

__all__ = ["FeatureStore", "FEATURES_VERSION"]

#: Bumped whenever the features change for the same settings (stale cache files are recomputed).
FEATURES_VERSION = 2


class FeatureStore:
    """Features of each image, computed once and kept on disk as ``.npz`` files.

    A file holds the raw keypoints, their pinhole positions and the
    descriptors, plus a signature of the image file (size and modification
    time), the detector settings and the camera; a stale file is recomputed.
    Files are written atomically (a temporary file, then a rename), so
    concurrent workers and interrupted runs never leave a half-written one.
    For a Dask cluster, ``folder`` must be on a filesystem every worker sees.

    Parameters
    ----------
    folder : str or Path
    image_dir : str or Path
    features : FeatureConfig, optional
        Default: the ``"colmap"`` preset (:data:`episeg_cv.features.PRESETS`).
    """

    def __init__(self, folder, image_dir, features: FeatureConfig | None = None):
        self.folder = Path(folder)
        self.image_dir = Path(image_dir)
        self.features = PRESETS["colmap"] if features is None else features

    @property
    def norm(self) -> str:
        """The descriptor norm of the features."""
        return self.features.norm

    def path(self, view: View) -> Path:
        stem = re.sub(r"[^A-Za-z0-9._-]+", "_", view.name)[-80:]
        digest = hashlib.sha1(view.name.encode()).hexdigest()[:10]
        f = self.features
        return self.folder / f"{stem}.{digest}.{f.detector}{f.max_features}.npz"

    def _signature(self, view: View) -> str:
        st = (self.image_dir / view.name).stat()
        f = self.features
        return repr((FEATURES_VERSION, f.sift_contrast, st.st_size, st.st_mtime_ns, f.detector, f.max_features,
                     f.root_sift, view.camera_model, tuple(float(p) for p in view.camera_params), view.image_size))

    def ensure(self, view: View) -> int:
        """Compute and store the features of ``view`` unless a fresh file exists; the keypoint count."""
        image_path = self.image_dir / view.name
        if not image_path.is_file():
            raise FileNotFoundError(f"image {view.name!r} is missing: {image_path}")
        sig = self._signature(view)
        path = self.path(view)
        if path.is_file():
            try:
                with np.load(path) as z:
                    if str(z["signature"]) == sig:
                        return int(len(z["keypoints"]))
            except (OSError, KeyError, ValueError):
                pass  # unreadable or stale: recompute
        image = cv2.imread(str(image_path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise ValueError(f"image {view.name!r} cannot be read: {image_path}")
        if (image.shape[1], image.shape[0]) != tuple(view.image_size):
            raise ValueError(f"image {view.name!r} is {image.shape[1]}x{image.shape[0]}, but its camera says "
                             f"{view.image_size[0]}x{view.image_size[1]}")
        kp, des = detect_features(image, self.features)
        self.folder.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp.npz")
        np.savez(tmp, keypoints=kp, pinhole=view.undistort(kp), descriptors=des, signature=np.array(sig))
        os.replace(tmp, path)
        return int(len(kp))

    def keypoints(self, view: View) -> np.ndarray:
        """The raw ``(N, 2)`` keypoints of ``view`` only (the descriptors stay on disk)."""
        with np.load(self.path(view)) as z:
            return z["keypoints"]

    def load(self, view: View) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(keypoints, pinhole keypoints, descriptors)`` of ``view`` (run :meth:`ensure` first).

        The last few images loaded stay in memory in each process (read-only
        arrays), since consecutive pairs share images.
        """
        path = self.path(view)
        return _load_features(str(path), path.stat().st_mtime_ns)


@functools.lru_cache(maxsize=8)
def _load_features(path: str, mtime_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    with np.load(path) as z:
        out = z["keypoints"], z["pinhole"], z["descriptors"]
    for a in out:
        a.flags.writeable = False
    return out
