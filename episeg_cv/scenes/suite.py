"""The pose suite: named two-view cases covering every geometric case of the segment.

:func:`pose_suite` lists the cases (forward, backward, lateral, converging,
face-to-face, near-pure rotation, partly behind, a noisy pose) and
:func:`make_pair` renders both views of one, with depth maps for the ground
truth (:class:`~episeg_cv.evaluation.ImagePair`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from .._validation import as_image_size
from ..evaluation import ImagePair
from ..geometry import TwoViewGeometry
from .model import Scene, look_at, make_room_scene
from .render import render

__all__ = ["SUITE_IMAGE_SIZE", "PoseCase", "pose_suite", "make_pair", "intrinsics_for", "scale_intrinsics"]

#: Image size ``(width, height)`` of the pose suite's intrinsics.
SUITE_IMAGE_SIZE = (640, 480)


def intrinsics_for(f: float, size=SUITE_IMAGE_SIZE) -> np.ndarray:
    w, h = size
    return np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])


def scale_intrinsics(K: np.ndarray, old_size, new_size) -> np.ndarray:
    """Intrinsics for the same camera at another resolution (pixel centres at integers)."""
    sx, sy = new_size[0] / old_size[0], new_size[1] / old_size[1]
    return np.array([[K[0, 0] * sx, K[0, 1] * sx, (K[0, 2] + 0.5) * sx - 0.5],
                     [0.0, K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5], [0.0, 0.0, 1.0]])


def _rotation(axis, angle: float) -> np.ndarray:
    """Rodrigues' rotation about ``axis`` by ``angle`` radians."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    S = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + np.sin(angle) * S + (1 - np.cos(angle)) * (S @ S)


@dataclass(frozen=True, eq=False)
class PoseCase:
    """One named two-view configuration of the pose suite.

    Attributes
    ----------
    name, description : str
    seed : int
        Seed of the room (:func:`make_room_scene`) and of the pose noise.
    image_size : (int, int)
        ``(width, height)`` for which ``K1``, ``K2`` are given (640 x 480).
    K1, K2 : (3, 3) float64
        Intrinsics at ``image_size``.
    R1, t1, R2, t2 : (3, 3), (3,) float64
        World-to-camera poses of the two cameras, ``X_cam = R X_world + t``, metres.
    R, t : (3, 3), (3,) float64
        True relative pose, ``X2 = R @ X1 + t`` (exact: e.g. ``t[2] == 0`` for lateral).
    R_given, t_given : (3, 3), (3,) float64
        The relative pose handed to the matcher: equal to ``R, t`` except for
        ``noisy_pose``, where it is off by about 0.5 degrees and 2 % in direction.
    clear_between : bool
        No box stands between the two cameras (so that each sees the other's
        position and the wall behind it).
    """

    name: str
    description: str
    seed: int
    image_size: tuple
    K1: np.ndarray
    K2: np.ndarray
    R1: np.ndarray
    t1: np.ndarray
    R2: np.ndarray
    t2: np.ndarray
    R: np.ndarray
    t: np.ndarray
    R_given: np.ndarray
    t_given: np.ndarray
    clear_between: bool = False

    def __post_init__(self):
        for f in ("K1", "K2", "R1", "t1", "R2", "t2", "R", "t", "R_given", "t_given"):
            getattr(self, f).flags.writeable = False

    def intrinsics(self, image_size=None) -> tuple[np.ndarray, np.ndarray]:
        """``(K1, K2)`` for the same cameras rendered at ``image_size`` (default: ``self.image_size``)."""
        size = self.image_size if image_size is None else as_image_size(image_size, "image_size")
        return scale_intrinsics(self.K1, self.image_size, size), scale_intrinsics(self.K2, self.image_size, size)

    def geometry(self, image_size=None, given: bool = False) -> TwoViewGeometry:
        """The true (or, with ``given``, the matcher's) :class:`TwoViewGeometry` at ``image_size``."""
        size = self.image_size if image_size is None else as_image_size(image_size, "image_size")
        K1, K2 = self.intrinsics(size)
        R, t = (self.R_given, self.t_given) if given else (self.R, self.t)
        return TwoViewGeometry(K1, K2, R, t, image_size1=size, image_size2=size)

    @property
    def centers(self) -> tuple[np.ndarray, np.ndarray]:
        """World positions of the two camera centres, ``-R_i^T t_i``."""
        return -self.R1.T @ self.t1, -self.R2.T @ self.t2

    def keep_clear(self) -> list:
        """World points that boxes keep clear of: the camera centres (and the line between them)."""
        C1, C2 = self.centers
        if not self.clear_between:
            return [C1, C2]
        return [C1 + s * (C2 - C1) for s in np.linspace(0.0, 1.0, 9)]


def _case(name, description, seed, K1, K2, cam1, cam2=None, relative=None, noise=None, clear_between=False) -> PoseCase:
    R1, t1 = look_at(*cam1[:2], *cam1[2:])
    if relative is not None:
        R, t = (np.asarray(a, dtype=np.float64) for a in relative)
        R2, t2 = R @ R1, R @ t1 + t
    else:
        R2, t2 = look_at(*cam2[:2], *cam2[2:])
        R = R2 @ R1.T
        t = t2 - R @ t1
    R_given, t_given = R, t
    if noise is not None:
        rng = np.random.default_rng(seed)
        rot_deg, dir_frac = noise
        R_given = _rotation(rng.normal(size=3), np.deg2rad(rot_deg)) @ R
        u = t / np.linalg.norm(t)
        d = rng.normal(size=3)
        d -= (d @ u) * u
        u2 = u + dir_frac * d / np.linalg.norm(d)
        t_given = u2 / np.linalg.norm(u2) * np.linalg.norm(t)
    return PoseCase(name, description, seed, SUITE_IMAGE_SIZE, K1, K2, R1, t1, R2, t2, R, t, R_given, t_given, clear_between)


def _converging_cameras():
    # camera 2 far back in a corner, camera 1 further in, 25 degrees off camera 2's
    # axis (so camera 1's centre, the epipole, is in image 2); both look at T.
    T = np.array([-2.2, 0.2, 3.6])
    C2 = np.array([3.0, -0.2, -4.3])
    d = T - C2
    d[1] = 0.0
    d /= np.linalg.norm(d)
    C1 = C2 + 5.5 * (_rotation([0, 1, 0], np.deg2rad(-25.0)) @ d) + np.array([0.0, 0.25, 0.0])
    return (C1, T), (C2, T + np.array([0.3, 0.0, 0.0]))


@functools.lru_cache(maxsize=None)
def _suite() -> dict:
    K = intrinsics_for(500.0)
    Kb = intrinsics_for(560.0)
    cases = [
        _case("forward", "camera 2 moves 1 m forward (t3 < 0); the epipole is in image 2", 101, K, K,
              ((0.0, 0.0, -3.6), (0.2, 0.1, 5.0)), ((0.25, 0.05, -2.6), (0.45, 0.15, 5.0), 0.03)),
        _case("backward", "camera 2 moves 1 m backward (t3 > 0); the epipole is in image 2", 102, K, K,
              ((0.1, -0.05, -2.4), (-0.2, 0.1, 5.0)), ((-0.15, 0.0, -3.4), (-0.1, 0.15, 5.0), -0.02)),
        _case("lateral", "sideways motion, t3 = 0 exactly: the epipole is at infinity", 103, K, K,
              ((-0.5, -0.1, -3.5), (-0.3, 0.1, 5.0)),
              relative=(_rotation([0, 1, 0], np.deg2rad(4.0)), [-0.6, 0.05, 0.0])),
        _case("converging", "wide baseline (5.5 m), views converging by about 35 degrees; the epipole is in image 2",
              104, K, Kb, *[(c, tg) for c, tg in _converging_cameras()]),
        _case("face_to_face", "the cameras face each other from opposite ends of the room (8 m apart)", 105, K, K,
              ((0.3, 0.0, -4.0), (-0.5, -0.05, 4.0)), ((-0.4, -0.1, 4.0), (0.2, 0.05, -4.0)), clear_between=True),
        _case("near_pure_rotation", "|t| = 2 cm for a scene 2 to 9 m away, rotation about 9 degrees", 106, K, K,
              ((0.5, 0.0, -2.0), (1.5, 0.2, 5.0)), ((0.515, -0.01, -1.992), (2.6, -0.3, 5.0))),
        _case("partial_behind", "crossing views, camera 2 turned 67 degrees: (R K1^-1 x)_3 < 0 for the left part of image 1", 107, K, K,
              ((1.5, 0.0, -3.0), (1.5 - 5 * np.sin(0.35), 0.25, -3.0 + 5 * np.cos(0.35))),
              ((-2.0, 0.1, -2.0), (-2.0 + 5 * np.sin(0.82), 0.35, -2.0 + 5 * np.cos(0.82)))),
        _case("noisy_pose", "general oblique motion; the matcher is given a pose off by 0.5 degrees and 2 % in direction",
              108, K, K, ((-1.0, 0.0, -3.0), (0.0, 0.3, 5.0)), ((0.2, -0.2, -2.2), (-0.5, 0.1, 5.0), 0.05),
              noise=(0.5, 0.02)),
    ]
    return {c.name: c for c in cases}


def pose_suite() -> dict:
    """The named two-view cases, each with a fixed seed, covering every geometric case.

    ========================  ==============================================================
    ``forward``               ``t3 < 0``, epipole in image 2
    ``backward``              ``t3 > 0``, epipole in image 2
    ``lateral``               ``t3 = 0`` exactly: epipole at infinity
    ``converging``            wide baseline, converging views, epipole in image 2
    ``face_to_face``          cameras facing each other, each seeing the wall behind the other
    ``near_pure_rotation``    ``|t|`` = 2 cm, scene 2 to 9 m away
    ``partial_behind``        ``(R K1^-1 x)_3 < 0`` for part of image 1
    ``noisy_pose``            the matcher's pose is off by 0.5 degrees and 2 % in direction
    ========================  ==============================================================

    Returns
    -------
    dict of str to PoseCase
        A new dict each call (the cases themselves are immutable).

    Examples
    --------
    >>> suite = pose_suite()
    >>> list(suite)[:3]
    ['forward', 'backward', 'lateral']
    >>> float(suite["lateral"].t[2])
    0.0
    """
    return dict(_suite())


@functools.lru_cache(maxsize=16)
def _case_scene(seed: int, keep_clear: tuple) -> Scene:
    return make_room_scene(rng=seed, keep_clear=[np.array(c) for c in keep_clear])


def make_pair(name: str, image_size=SUITE_IMAGE_SIZE, seed: int | None = None, supersample: int = 2) -> ImagePair:
    """Render both views of a case of :func:`pose_suite`.

    Parameters
    ----------
    name : str
        A key of :func:`pose_suite`.
    image_size : (int, int), optional
        ``(width, height)``; the intrinsics are scaled from 640 x 480 (same field of view).
    seed : int, optional
        Seed of the room; default (None) the case's own fixed seed. Boxes are
        kept clear of both cameras (:meth:`PoseCase.keep_clear`) whatever the seed.
    supersample : int, optional
        Passed to :func:`render`.

    Returns
    -------
    ImagePair
        ``image1, image2`` (uint8), ``depth1, depth2`` (metres), ``K1, K2, R, t``
        (true, ``X2 = R X1 + t``), ``geometry_true`` and ``geometry`` (what a
        matcher is given; perturbed for ``noisy_pose``).

    Examples
    --------
    >>> pair = make_pair("forward", image_size=(80, 60))
    >>> pair.image1.shape, pair.depth2.shape, bool(pair.t[2] < 0)
    ((60, 80), (60, 80), True)
    """
    suite = _suite()
    if name not in suite:
        raise ValueError(f"name must be one of {list(suite)}, got {name!r}")
    case = suite[name]
    size = as_image_size(image_size, "image_size")
    s = case.seed if seed is None else int(seed)
    scene = _case_scene(s, tuple(tuple(c.tolist()) for c in case.keep_clear()))
    K1, K2 = case.intrinsics(size)
    image1, depth1 = render(scene, K1, case.R1, case.t1, size, supersample)
    image2, depth2 = render(scene, K2, case.R2, case.t2, size, supersample)
    return ImagePair(name, image1, image2, case.geometry(size, given=True), case.geometry(size), depth1, depth2, None, 3.0)

