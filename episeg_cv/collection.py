"""Posed image collections: views, pairs, depth ranges, cached features, and the per-pair job.

This is the numpy side of :mod:`episeg_cv.colmap`; it holds no database and
imports ``pycolmap`` only to undistort keypoints of a distorted camera.

Conventions
-----------
- Poses are world-to-camera, ``X_cam = R @ X_world + t`` (as
  :meth:`TwoViewGeometry.from_world_poses`); the pair ``(i, j)`` has
  ``X_j = R X_i + t``.
- Keypoints are in episeg_cv's pixel convention (the centre of the top-left
  pixel is ``(0, 0)``), in the *raw* (distorted) image. COLMAP's convention,
  ``(0.5, 0.5)``, is applied only where the database is written.
- The epipolar constraint needs a pinhole camera. Every keypoint of a camera
  with distortion is mapped through COLMAP's own camera model
  (``pycolmap.Camera.cam_from_img``, the exact inverse COLMAP uses) to a
  normalised ray, then to the pinhole image of the camera's calibration
  matrix ``K`` (focal lengths and principal point of the model, no
  distortion). The constraint, and its pixel tolerance, act there; the
  database gets the raw keypoints.
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ._validation import as_camera_matrix, as_depth_range, as_image_size, as_rotation, as_vector3
from .geometry import TwoViewGeometry
from .matching import DEFAULT_RATIO, filter_pairs, match_descriptors

__all__ = [
    "View",
    "DETECTORS",
    "read_pairs",
    "index_pairs",
    "exhaustive_pairs",
    "overlap_scores",
    "neighbor_pairs",
    "depth_range_from_depths",
    "create_detector",
    "detect_features",
    "is_bounded",
    "FeatureStore",
    "PairJob",
    "match_pair",
]

#: Detector name -> (descriptor norm). SIFT is float32 / L2, ORB and AKAZE are binary / Hamming.
DETECTORS = {"sift": "l2", "orb": "hamming", "akaze": "hamming"}

#: Bumped whenever the features change for the same settings (stale cache files are recomputed).
FEATURES_VERSION = 2

#: COLMAP camera models without distortion: pinhole keypoints are the raw ones.
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")


@dataclass(frozen=True, eq=False)
class View:
    """One posed image.

    Attributes
    ----------
    name : str
        Image path relative to the image folder (as in a COLMAP model).
    image_id, camera_id : int
        COLMAP ids (kept from the model, so the database agrees with it).
    K : (3, 3) float64
        Pinhole intrinsics, pixel centres at integer coordinates.
    R : (3, 3) float64
    t : (3,) float64
        World-to-camera pose, ``X_cam = R @ X_world + t``.
    image_size : (int, int)
        ``(width, height)``.
    camera_model : str
        COLMAP camera model name (``"PINHOLE"``, ``"SIMPLE_RADIAL"``, ``"OPENCV"``, ...).
    camera_params : tuple of float
        COLMAP camera parameters, in COLMAP's pixel convention.
    depth_range : (float, float)
        ``(zmin, zmax)`` of the scene in this camera, used for its segments.

    Examples
    --------
    >>> K = [[100, 0, 49.5], [0, 100, 49.5], [0, 0, 1]]
    >>> a = View("a.png", 1, 1, K, np.eye(3), [0, 0, 0], (100, 100), depth_range=(1, 10))
    >>> b = View("b.png", 2, 1, K, np.eye(3), [-1, 0, 0], (100, 100))   # 1 m to the right of a
    >>> a.camera_params, b.center.tolist()
    ((100.0, 100.0, 50.0, 50.0), [1.0, 0.0, 0.0])
    >>> g = a.geometry_to(b)
    >>> seg = g.segments([[49.5, 49.5]], a.depth_range)
    >>> np.round(seg.start, 1).tolist(), np.round(seg.end, 1).tolist()   # x2 = 49.5 - 100 / z, z in [1, 10]
    ([[-0.5, 49.5]], [[39.5, 49.5]])
    """

    name: str
    image_id: int
    camera_id: int
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    image_size: tuple
    camera_model: str = "PINHOLE"
    camera_params: tuple = field(default=())
    depth_range: tuple = (0.0, float("inf"))

    def __post_init__(self):
        object.__setattr__(self, "K", as_camera_matrix(self.K, f"K of image {self.name!r}"))
        object.__setattr__(self, "R", as_rotation(self.R, f"R of image {self.name!r}"))
        object.__setattr__(self, "t", as_vector3(self.t, f"t of image {self.name!r}"))
        object.__setattr__(self, "image_size", as_image_size(self.image_size, f"image_size of image {self.name!r}"))
        object.__setattr__(self, "depth_range", tuple(float(v) for v in as_depth_range(
            self.depth_range, None, f"depth_range of image {self.name!r}")))
        params = self.camera_params or (self.K[0, 0], self.K[1, 1], self.K[0, 2] + 0.5, self.K[1, 2] + 0.5)
        object.__setattr__(self, "camera_params", tuple(float(p) for p in params))

    def with_depth_range(self, depth_range) -> "View":
        """A copy with another ``depth_range``."""
        return dataclasses.replace(self, depth_range=depth_range)

    def geometry_to(self, other: "View") -> TwoViewGeometry:
        """The :class:`TwoViewGeometry` from this view to ``other`` (pinhole images)."""
        return TwoViewGeometry.from_world_poses(self.K, self.R, self.t, other.K, other.R, other.t,
                                                image_size1=self.image_size, image_size2=other.image_size)

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in the world, ``-R^T t``."""
        return -self.R.T @ self.t

    def undistort(self, points: np.ndarray) -> np.ndarray:
        """Raw keypoints ``(N, 2)`` -> their positions in the pinhole image of ``K``.

        Identity for ``SIMPLE_PINHOLE`` and ``PINHOLE``; otherwise COLMAP's
        own inverse of the camera model (``pycolmap.Camera.cam_from_img``).
        """
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if self.camera_model in PINHOLE_MODELS or len(pts) == 0:
            return pts.copy()
        import pycolmap

        w, h = self.image_size
        cam = pycolmap.Camera(model=self.camera_model, width=w, height=h, params=list(self.camera_params))
        rays = np.asarray(cam.cam_from_img(pts + 0.5), dtype=np.float64).reshape(-1, 2)
        return rays @ self.K[:2, :2].T + self.K[:2, 2]


# --------------------------------------------------------------------------------------
# Pairs
# --------------------------------------------------------------------------------------
def read_pairs(path, names) -> list[tuple[int, int]]:
    """Read a pairs file: one ``name1 name2`` per line (COLMAP's and hloc's format).

    Blank lines and lines starting with ``#`` are skipped; a pair listed twice
    (in either order) is kept once.

    Parameters
    ----------
    path : str or Path
    names : sequence of str
        The collection's image names; a pair is returned as two indices into it.

    Returns
    -------
    list of (int, int)
        Index pairs ``(i, j)`` with ``i < j``, in file order.

    Raises
    ------
    ValueError
        ``path:line: ...`` for a line without two names, an unknown image, or
        an image paired with itself.
    """
    items = []
    with open(path, encoding="utf-8") as f:
        for lineno, raw in enumerate(f, 1):
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.split()
            if len(parts) < 2:
                raise ValueError(f"{path}:{lineno}: expected 'name1 name2', got {line!r}")
            items.append((f"{path}:{lineno}", parts[0], parts[1]))
    return index_pairs(items, names)


def index_pairs(items, names) -> list[tuple[int, int]]:
    """``(where, name1, name2)`` items -> unique index pairs ``(i, j)``, ``i < j``, in order.

    Raises ``ValueError`` prefixed with ``where`` for an unknown image or an image paired with itself.
    """
    index = {n: i for i, n in enumerate(names)}
    out, seen = [], set()
    for where, a, b in items:
        for n in (a, b):
            if n not in index:
                raise ValueError(f"{where}: unknown image {n!r} (not in the model)")
        if a == b:
            raise ValueError(f"{where}: image {a!r} is paired with itself")
        key = (min(index[a], index[b]), max(index[a], index[b]))
        if key not in seen:
            seen.add(key)
            out.append(key)
    return out


def exhaustive_pairs(n: int) -> list[tuple[int, int]]:
    """Every pair ``(i, j)``, ``i < j < n``."""
    return [(i, j) for i in range(n) for j in range(i + 1, n)]


def _sample_grid(image_size, n: int = 12) -> np.ndarray:
    w, h = image_size
    xs = (np.arange(n) + 0.5) * w / n - 0.5
    ys = (np.arange(n) + 0.5) * h / n - 0.5
    return np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)


def overlap_scores(views, samples: int = 12) -> np.ndarray:
    """View overlap from the segment test: which sampled pixels of one view can be seen by the other.

    For each ordered pair ``(i, j)``, a ``samples x samples`` grid of pixels of
    view ``i`` is tested: a pixel counts when its epipolar segment in view
    ``j``, within view ``i``'s depth range, is non-empty (it meets image
    ``j``). The score of the pair is the smaller of the two directions, in
    ``[0, 1]``. With ``depth_range=(0, inf)`` this is only a cheirality and
    field-of-view test; depth ranges make it a real overlap test.

    Returns
    -------
    (n, n) float64
        Symmetric, zero on the diagonal.
    """
    n = len(views)
    s = np.zeros((n, n))
    grids = [_sample_grid(v.image_size, samples) for v in views]
    for i in range(n):
        for j in range(n):
            if i != j:
                seg = views[i].geometry_to(views[j]).segments(grids[i], views[i].depth_range)
                s[i, j] = seg.valid.mean()
    return np.minimum(s, s.T)


def neighbor_pairs(views, k: int, samples: int = 12) -> list[tuple[int, int]]:
    """For each view, its ``k`` best partners by :func:`overlap_scores` (ties: nearer camera first).

    Partners with a zero score are never chosen. Returns the union as sorted
    ``(i, j)``, ``i < j``.
    """
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"neighbors must be a positive integer, got {k!r}")
    scores = overlap_scores(views, samples)
    centers = np.array([v.center for v in views])
    out = set()
    for i in range(len(views)):
        dist = np.linalg.norm(centers - centers[i], axis=1)
        order = np.lexsort((dist, -scores[i]))
        chosen = [j for j in order if j != i and scores[i, j] > 0][:k]
        out.update((min(i, j), max(i, j)) for j in chosen)
    return sorted(out)


# --------------------------------------------------------------------------------------
# Depth ranges
# --------------------------------------------------------------------------------------
def depth_range_from_depths(depths, percentiles=(2.0, 98.0), margin: float = 0.25, min_points: int = 10):
    """A robust depth range from the depths of the 3D points an image sees.

    ``zmin = p_lo / (1 + margin)``, ``zmax = p_hi * (1 + margin)``, where
    ``p_lo, p_hi`` are the given percentiles of the positive depths.

    Returns
    -------
    (float, float)
        ``(0, inf)`` when fewer than ``min_points`` positive depths are given.

    Examples
    --------
    >>> depth_range_from_depths(np.linspace(2.0, 4.0, 101), percentiles=(0, 100), margin=0.0)
    (2.0, 4.0)
    >>> depth_range_from_depths([1.0, 2.0])
    (0.0, inf)
    """
    d = np.asarray(depths, dtype=np.float64).ravel()
    d = d[np.isfinite(d) & (d > 0)]
    if len(d) < min_points:
        return (0.0, float("inf"))
    lo, hi = np.percentile(d, percentiles)
    return (float(lo / (1.0 + margin)), float(hi * (1.0 + margin)))


# --------------------------------------------------------------------------------------
# Features, cached on disk
# --------------------------------------------------------------------------------------
#: SIFT's contrast threshold here: COLMAP's peak threshold (0.02 / 3 per layer), not OpenCV's 0.04.
SIFT_CONTRAST = 0.02


def create_detector(name: str, max_features: int, sift_contrast: float | None = SIFT_CONTRAST):
    """An OpenCV detector: ``"sift"``, ``"orb"`` or ``"akaze"`` (in ``cv2`` or ``cv2.xfeatures2d``).

    ``sift_contrast`` is SIFT's ``contrastThreshold`` (None: OpenCV's default, 0.04).
    ``max_features`` caps SIFT and ORB; AKAZE has no cap.
    """
    if name == "sift":
        extra = {} if sift_contrast is None else {"contrastThreshold": sift_contrast}
        return cv2.SIFT_create(nfeatures=max_features, **extra)
    if name == "orb":
        return cv2.ORB_create(nfeatures=max_features)
    if name == "akaze":
        create = getattr(cv2, "AKAZE_create", None) or getattr(getattr(cv2, "xfeatures2d", None), "AKAZE_create", None)
        if create is None:
            raise ValueError("AKAZE is not available in this OpenCV build")
        return create()
    raise ValueError(f"detector must be one of {tuple(DETECTORS)}, got {name!r}")


def is_bounded(depth_range) -> bool:
    """Whether ``(zmin, zmax)`` says more than ``(0, inf)``."""
    return bool(depth_range[0] > 0 or np.isfinite(depth_range[1]))


def detect_features(image: np.ndarray, detector: str = "sift", max_features: int = 8192):
    """Keypoints and descriptors of a grey image, strongest first, at most ``max_features``.

    SIFT is set up as COLMAP sets it up: the contrast threshold
    :data:`SIFT_CONTRAST` and RootSIFT descriptors (L1-normalised, then the
    square root; COLMAP's ``L1_ROOT``), which match better under L2.

    Returns
    -------
    keypoints : (N, 2) float64
        Pixel positions (centre of the top-left pixel at ``(0, 0)``).
    descriptors : (N, D) float32 (RootSIFT) or uint8 (ORB, AKAZE)
    """
    kp, des = create_detector(detector, max_features).detectAndCompute(image, None)
    if des is None or not kp:
        width = {"sift": 128, "orb": 32, "akaze": 61}[detector]
        return np.zeros((0, 2)), np.zeros((0, width), np.float32 if detector == "sift" else np.uint8)
    order = np.argsort([-k.response for k in kp], kind="stable")[:max_features]
    pts = cv2.KeyPoint_convert(kp).astype(np.float64).reshape(-1, 2)
    des = des[order]
    if detector == "sift":
        des = np.sqrt(des / np.maximum(des.sum(axis=1, keepdims=True), 1e-12)).astype(np.float32)
    return pts[order], np.ascontiguousarray(des)


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
    detector : {"sift", "orb", "akaze"}
    max_features : int
    """

    def __init__(self, folder, image_dir, detector: str = "sift", max_features: int = 8192):
        if detector not in DETECTORS:
            raise ValueError(f"detector must be one of {tuple(DETECTORS)}, got {detector!r}")
        if isinstance(max_features, bool) or not isinstance(max_features, (int, np.integer)) or max_features < 1:
            raise ValueError(f"max_features must be a positive integer, got {max_features!r}")
        self.folder = Path(folder)
        self.image_dir = Path(image_dir)
        self.detector = detector
        self.max_features = int(max_features)

    @property
    def norm(self) -> str:
        return DETECTORS[self.detector]

    def path(self, view: View) -> Path:
        stem = re.sub(r"[^A-Za-z0-9._-]+", "_", view.name)[-80:]
        digest = hashlib.sha1(view.name.encode()).hexdigest()[:10]
        return self.folder / f"{stem}.{digest}.{self.detector}{self.max_features}.npz"

    def _signature(self, view: View) -> str:
        st = (self.image_dir / view.name).stat()
        return repr((FEATURES_VERSION, SIFT_CONTRAST, st.st_size, st.st_mtime_ns, self.detector, self.max_features,
                     view.camera_model, tuple(float(p) for p in view.camera_params), view.image_size))

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
        kp, des = detect_features(image, self.detector, self.max_features)
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


# --------------------------------------------------------------------------------------
# The per-pair job (runs in a worker)
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PairJob:
    """Everything a worker needs to match one pair; small and picklable.

    ``constraint``, ``tol`` and ``ratio`` are as in :func:`match_descriptors`;
    each view's ``depth_range`` bounds its own segments.
    """

    index: int
    view1: View
    view2: View
    store: FeatureStore
    constraint: str = "segment"
    tol: float = 2.0
    ratio: float = DEFAULT_RATIO
    samples: int = 256


@dataclass(frozen=True)
class PairResult:
    """What a worker sends back to the writer.

    ``matches`` and ``inliers`` are ``(M, 2)`` uint32 keypoint indices
    ``(i1, i2)`` into the two images' stored keypoints. ``lengths`` holds the
    summed search lengths in image 2, in pixels, of up to ``PairJob.samples``
    queries: the epipolar line, the segment, and the segment within view 1's
    depth range (all clipped to the image); ``samples`` is their number.
    """

    index: int
    matches: np.ndarray
    inliers: np.ndarray
    lengths: tuple
    samples: int


def match_pair(job: PairJob) -> PairResult:
    """Match one pair on the segment (or line) and keep the inliers of both directions.

    The raw matches are :func:`match_descriptors` from view 1 to view 2 with
    view 1's depth range. The inliers are the raw matches that also satisfy
    the constraint from view 2 to view 1 (with view 2's depth range): a
    match must be consistent with both cameras' depth ranges.
    """
    _, q1, d1 = job.store.load(job.view1)
    _, q2, d2 = job.store.load(job.view2)
    g = job.view1.geometry_to(job.view2)
    pairs, _ = match_descriptors(d1, d2, q1, q2, g, norm=job.store.norm, tol=job.tol,
                                 depth_range=job.view1.depth_range, constraint=job.constraint, ratio=job.ratio)
    keep = filter_pairs(pairs[:, ::-1], q2, q1, g.inverse(), tol=job.tol, depth_range=job.view2.depth_range,
                        constraint=job.constraint)
    sample = q1[:: max(1, len(q1) // max(job.samples, 1))][: job.samples]
    full = g.segments(sample)
    ranged = g.segments(sample, job.view1.depth_range)
    lengths = tuple(float(np.sum(x)) for x in (full.line_length, full.length, ranged.length))
    return PairResult(job.index, pairs.astype(np.uint32), pairs[keep].astype(np.uint32), lengths, len(sample))
