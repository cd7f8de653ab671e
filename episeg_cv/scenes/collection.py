"""Posed collections: many rendered views of one room, with exact poses and depth."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validation import as_image_size
from ..geometry import TwoViewGeometry
from .model import look_at, make_room_scene
from .render import render
from .suite import SUITE_IMAGE_SIZE, intrinsics_for, scale_intrinsics

__all__ = ["PosedCollection", "collection_poses", "make_collection", "MAX_HELD_BYTES"]

#: The most memory a :class:`PosedCollection` may hold (its images and depth maps).
MAX_HELD_BYTES = 4 * 2**30


@dataclass(frozen=True, eq=False)
class PosedCollection:
    """Several rendered views of one room, with exact poses and depth.

    Made by :func:`make_collection`.

    Attributes
    ----------
    names : tuple of str
        File names, ``view_000.png``, ...
    images : tuple of (H, W) uint8
    depths : tuple of (H, W) float64
        ``z`` per pixel, metres, ``inf`` where the view sees nothing.
    K : (3, 3) float64
        Shared intrinsics (pixel centres at integer coordinates).
    R : (n, 3, 3) float64
    t : (n, 3) float64
        World-to-camera poses, ``X_cam = R[i] @ X_world + t[i]``.
    image_size : (int, int)
        ``(width, height)``.
    """

    names: tuple
    images: tuple
    depths: tuple
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    image_size: tuple

    def __len__(self) -> int:
        return len(self.names)

    def geometry(self, i: int, j: int) -> TwoViewGeometry:
        """True :class:`TwoViewGeometry` from view ``i`` to view ``j``."""
        return TwoViewGeometry.from_world_poses(self.K, self.R[i], self.t[i], self.K, self.R[j], self.t[j],
                                                image_size1=self.image_size, image_size2=self.image_size)


def collection_poses(n_views: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera poses of :func:`make_collection`: a walk on an arc with several baselines.

    The cameras stand on an arc of radius 3.2 m around the room's centre at
    about 1.5 m from the back wall, turning from -45 to +45 degrees, and look
    at points near the front wall; every third camera steps 0.9 m towards
    its target (forward motion, so epipoles fall inside the images). Neighbours
    are about 0.5 m apart, the ends of the arc about 4.5 m.

    Returns
    -------
    R : (n, 3, 3) float64
    t : (n, 3) float64
    """
    n = int(n_views)
    if n < 2:
        raise ValueError(f"n_views must be at least 2, got {n_views!r}")
    Rs, ts = [], []
    for i, a in enumerate(np.deg2rad(np.linspace(-45.0, 45.0, n))):
        c = np.array([3.2 * np.sin(a), -0.15 + 0.1 * np.sin(2.7 * i), 0.3 - 3.2 * np.cos(a)])
        target = np.array([1.6 * np.sin(1.3 * a) + 0.4 * np.sin(1.9 * i), 0.2, 4.0])
        if i % 3 == 2:
            d = target - c
            c = c + 0.9 * d / np.linalg.norm(d)
        R, t = look_at(c, target, roll=0.03 * np.sin(3.1 * i))
        Rs.append(R)
        ts.append(t)
    return np.array(Rs), np.array(ts)


def make_collection(n_views: int = 12, image_size=SUITE_IMAGE_SIZE, seed: int = 7, focal: float = 500.0,
                    supersample: int = 2) -> PosedCollection:
    """Render ``n_views`` posed views of one room with boxes (see :func:`collection_poses`).

    Parameters
    ----------
    n_views : int, optional
        At least 2.
    image_size : (int, int), optional
        ``(width, height)``.
    seed : int, optional
        Seed of the room (:func:`make_room_scene`); boxes keep clear of every camera.
    focal : float, optional
        Focal length in pixels at 640 x 480, scaled with ``image_size``.
    supersample : int, optional
        Passed to :func:`render`.

    Returns
    -------
    PosedCollection

    Examples
    --------
    >>> c = make_collection(3, image_size=(64, 48))
    >>> len(c), c.images[0].shape, c.R.shape
    (3, (48, 64), (3, 3, 3))
    """
    size = as_image_size(image_size, "image_size")
    held = int(n_views) * size[0] * size[1] * 9  # an image (uint8) and a depth map (float64) per view
    if held > MAX_HELD_BYTES:
        raise ValueError(f"n_views = {n_views} at {size[0]}x{size[1]} would hold {held / 2**30:.1f} GiB of images and "
                         f"depth maps in memory (at most {MAX_HELD_BYTES / 2**30:.0f} GiB); use fewer views or a "
                         "smaller image_size")
    R, t = collection_poses(n_views)
    centers = [-Ri.T @ ti for Ri, ti in zip(R, t)]
    scene = make_room_scene(rng=seed, keep_clear=centers, clearance=0.9)
    K = scale_intrinsics(intrinsics_for(float(focal)), SUITE_IMAGE_SIZE, size)
    images, depths = [], []
    for Ri, ti in zip(R, t):
        img, depth = render(scene, K, Ri, ti, size, supersample)
        img.flags.writeable = False
        depth.flags.writeable = False
        images.append(img)
        depths.append(depth)
    for a in (K, R, t):
        a.flags.writeable = False
    names = tuple(f"view_{i:03d}.png" for i in range(len(R)))
    return PosedCollection(names, tuple(images), tuple(depths), K, R, t, size)
