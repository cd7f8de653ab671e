"""Features of each image, computed once and cached on disk."""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import logging
import os
import re
import threading
import zipfile
from pathlib import Path

import numpy as np

from ..features import PRESETS, FeatureConfig, detect_features
from ..io.paths import input_file, output_folder
from .images import read_grey
from .views import View

_log = logging.getLogger("episeg_cv")

__all__ = ["FeatureStore", "FEATURES_VERSION"]

#: Bumped whenever the features change for the same settings (stale cache files are recomputed).
FEATURES_VERSION = 5  # 5: images read in their stored grid, EXIF orientation ignored (:mod:`.images`)


class FeatureStore:
    """Features of each image, computed once and kept on disk as ``.npz`` files.

    A file holds the raw keypoints, their pinhole positions and the
    descriptors, plus a signature: the SHA-256 of the image file's content,
    the detector settings and the camera. A stale or unreadable file is
    recomputed.
    Files are written atomically (a temporary file, then a rename), so
    concurrent workers and interrupted runs never leave a half-written one.
    For a Dask cluster, ``folder`` must be on a filesystem every worker sees.

    Parameters
    ----------
    folder : str or Path
    image_dir : str or Path
    features : FeatureConfig, optional
        Default: the ``"collection"`` preset (:data:`episeg_cv.features.PRESETS`).
    """

    def __init__(self, folder, image_dir, features: FeatureConfig | None = None):
        self.folder = Path(folder)
        self.image_dir = Path(image_dir)
        self.features = PRESETS["collection"] if features is None else features

    @property
    def norm(self) -> str:
        """The descriptor norm of the features."""
        return self.features.norm

    def path(self, view: View) -> Path:
        stem = re.sub(r"[^A-Za-z0-9._-]+", "_", view.name)[-80:]
        digest = hashlib.sha1(view.name.encode()).hexdigest()[:10]
        return self.folder / f"{stem}.{digest}.{self._suffix()}.npz"

    def _suffix(self) -> str:
        return f"{self.features.detector}{self.features.max_features}"

    def digest(self, view: View) -> str:
        """SHA-256 of the image file's bytes: what its features (and a resumed database) depend on."""
        image_path = input_file(self.image_dir / view.name, f"image {view.name!r}")
        h = hashlib.sha256()
        with open(image_path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        return h.hexdigest()

    def _signature(self, view: View, digest: str) -> str:
        f = self.features
        return repr((FEATURES_VERSION, digest, f.sift_contrast, f.detector, f.max_features, f.root_sift,
                     f.sift_sigma, f.fix_upscale_bias, view.camera_model,
                     tuple(float(p) for p in view.camera_params), view.image_size))

    def describe(self) -> dict:
        """The settings of these features, for the run record of a database."""
        return dataclasses.asdict(self.features)

    def ensure(self, view: View) -> tuple[int, str]:
        """Compute and store the features of ``view`` unless a fresh file exists.

        Returns ``(number of keypoints, SHA-256 of the image)``. A cache file that is stale
        (another image content or setting) or unreadable (truncated, empty) is recomputed.
        Keypoints where the camera's distortion cannot be inverted are left out
        (:meth:`View.undistortable`).
        """
        digest = self.digest(view)
        sig = self._signature(view, digest)
        n = self._cached(view, sig)
        if n is not None:
            return n, digest
        kp, des = self._detect(view)
        ok = view.undistortable(kp)
        if not ok.all():
            _log.info("image %r: %d of %d keypoints lie where the camera's distortion cannot be inverted; left out",
                      view.name, int((~ok).sum()), len(kp))
            kp, des = kp[ok], des[ok]
        self._save(view, kp, view.undistort(kp), des, sig)
        return int(len(kp)), digest

    def _cached(self, view: View, sig: str) -> int | None:
        """The number of keypoints of a fresh cache file of ``view``, or None. The arrays read to check it
        stay in this process's memory (:meth:`load` then needs no second read)."""
        path = self.path(view)
        if path.is_file():
            try:
                mtime = path.stat().st_mtime_ns
                with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:  # (our handle: closed on errors)
                    if str(z["signature"]) == sig and _complete(z, self.features):
                        arrays = z["keypoints"], z["pinhole"], z["descriptors"]
                        _remember(str(path), mtime, arrays)
                        return int(len(arrays[0]))
            except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
                pass  # unreadable or stale: recompute
        return None

    def _detect(self, view: View) -> tuple[np.ndarray, np.ndarray]:
        image_path = self.image_dir / view.name
        image = read_grey(image_path)
        if image is None:
            raise ValueError(f"image {view.name!r} cannot be read (not an image OpenCV can decode): {image_path}")
        if (image.shape[1], image.shape[0]) != tuple(view.image_size):
            raise ValueError(f"image {view.name!r} is {image.shape[1]}x{image.shape[0]}, but its camera says "
                             f"{view.image_size[0]}x{view.image_size[1]}")
        return detect_features(image, self.features)

    def _save(self, view: View, kp, pinhole, des, sig: str) -> None:
        path = self.path(view)
        output_folder(self.folder, "feature cache")
        tmp = path.with_name(f"{path.name}.{os.getpid()}.{threading.get_ident()}.tmp.npz")
        try:
            np.savez(tmp, keypoints=kp, pinhole=pinhole, descriptors=des, signature=np.array(sig))
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)

    def keypoints(self, view: View) -> np.ndarray:
        """The raw ``(N, 2)`` keypoints of ``view`` (run :meth:`ensure` first)."""
        return self.load(view)[0]

    def pinhole(self, view: View) -> np.ndarray:
        """The ``(N, 2)`` keypoints of ``view`` in its pinhole image (NaN where there is none)."""
        return self.load(view)[1]

    def load(self, view: View) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(keypoints, pinhole keypoints, descriptors)`` of ``view`` (run :meth:`ensure` first).

        Loaded images stay in memory in each process (read-only arrays), up to
        :data:`MEMORY_BUDGET` bytes, least recently used first out.
        """
        path = self.path(view)
        return _load_features(str(path), path.stat().st_mtime_ns)


def _complete(z, features: FeatureConfig) -> bool:
    """Whether a cache file holds every array, consistent with each other and with the detector."""
    kp, pin, des = z["keypoints"], z["pinhole"], z["descriptors"]
    n = len(kp)
    want = np.float32 if features.detector == "sift" else np.uint8
    return (kp.shape == (n, 2) and pin.shape == (n, 2) and des.ndim == 2 and len(des) == n and des.dtype == want
            and kp.dtype == np.float64 and pin.dtype == np.float64)


#: Bytes of loaded features each process keeps in memory (least recently used first out): every
#: pair reads two images, so a collection that fits is read from disk once per image, not once per pair.
MEMORY_BUDGET = 1 << 30
_loaded: "collections.OrderedDict[tuple[str, int], tuple]" = collections.OrderedDict()
_loaded_lock = threading.Lock()


def _load_features(path: str, mtime_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    key = (path, mtime_ns)
    with _loaded_lock:
        if key in _loaded:
            _loaded.move_to_end(key)
            return _loaded[key]
    try:
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:
            out = z["keypoints"], z["pinhole"], z["descriptors"]
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"feature cache file {path!r} cannot be read ({type(exc).__name__}); "
                         "it was changed during the run") from None
    if not _remember(path, mtime_ns, out):  # once per image: the matcher trusts them
        raise ValueError(f"feature cache file {path!r} holds descriptors that are NaN or inf")
    return out


def _remember(path: str, mtime_ns: int, arrays: tuple) -> bool:
    """Keep ``(keypoints, pinhole, descriptors)`` of a cache file in memory, read-only (least recently used
    first out beyond :data:`MEMORY_BUDGET`); False, and nothing kept, when a descriptor is NaN or inf."""
    des = arrays[2]
    if des.dtype != np.uint8 and not np.isfinite(des).all():
        return False
    for a in arrays:
        a.flags.writeable = False
    with _loaded_lock:
        _loaded[(path, mtime_ns)] = arrays
        total = sum(a.nbytes for v in _loaded.values() for a in v)
        while len(_loaded) > 1 and total > MEMORY_BUDGET:
            total -= sum(a.nbytes for a in _loaded.popitem(last=False)[1])
    return True
