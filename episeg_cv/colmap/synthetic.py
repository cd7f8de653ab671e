"""A synthetic posed collection on disk: images, a COLMAP model and a poses JSON (tests, benchmarks, the CLI)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .model import reconstruction_from_views
from .poses import save_poses
from .views import View, require_pycolmap

__all__ = ["save_collection"]


def save_collection(collection, folder, points_per_view: int = 300, seed: int = 0) -> dict:
    """Write a :class:`~episeg_cv.scenes.PosedCollection` as images, a COLMAP model and a poses JSON.

    The model's 3D points are sampled from each view's depth map and observed
    (tracks) in every view where they are visible (inside the image and in
    front of the rendered surface within 1 % of depth), as a model from an
    earlier COLMAP run would have them; ``depth_range="auto"`` reads them.

    Returns
    -------
    dict
        ``{"images": Path, "model": Path, "poses": Path}``.
    """
    pycolmap = require_pycolmap()
    folder = Path(folder)
    img_dir, model_dir = folder / "images", folder / "model"
    img_dir.mkdir(parents=True, exist_ok=True)
    model_dir.mkdir(parents=True, exist_ok=True)
    c = collection
    views = []
    for k, (name, image) in enumerate(zip(c.names, c.images)):
        cv2.imwrite(str(img_dir / name), image)
        views.append(View(name, k + 1, 1, c.K, c.R[k], c.t[k], c.image_size))
    save_poses(folder / "poses.json", views)

    rng = np.random.default_rng(seed)
    w, h = c.image_size
    Kinv = np.linalg.inv(c.K)
    points = []
    for k, depth in enumerate(c.depths):
        xy = np.column_stack([rng.integers(0, w, points_per_view), rng.integers(0, h, points_per_view)])
        z = depth[xy[:, 1], xy[:, 0]]
        ok = np.isfinite(z)
        Xc = (np.column_stack([xy[ok], np.ones(ok.sum())]) @ Kinv.T) * z[ok, None]
        points.append((Xc - c.t[k]) @ c.R[k])  # camera -> world
    X = np.concatenate(points)
    obs = [[] for _ in views]  # per view: (point index, xy)
    for k, depth in enumerate(c.depths):
        Xc = X @ c.R[k].T + c.t[k]
        with np.errstate(divide="ignore", invalid="ignore"):
            p = Xc @ c.K.T
            p = p[:, :2] / p[:, 2:]
        inside = (Xc[:, 2] > 0) & np.all(np.isfinite(p), axis=1) & (p[:, 0] > -0.5) & (p[:, 0] < w - 0.5) \
            & (p[:, 1] > -0.5) & (p[:, 1] < h - 0.5)
        idx = np.flatnonzero(inside)
        px = np.clip(np.rint(p[idx]).astype(int), 0, [w - 1, h - 1])
        visible = np.abs(depth[px[:, 1], px[:, 0]] - Xc[idx, 2]) <= 0.01 * Xc[idx, 2]
        obs[k] = [(int(i), p[i]) for i in idx[visible]]
    rec = reconstruction_from_views(views)
    tracks: dict[int, list] = {}
    for k, v in enumerate(views):
        im = rec.image(v.image_id)
        im.points2D = pycolmap.Point2DList([pycolmap.Point2D(xy + 0.5) for _, xy in obs[k]])
        for idx2d, (i, _) in enumerate(obs[k]):
            tracks.setdefault(i, []).append(pycolmap.TrackElement(v.image_id, idx2d))
    for i, els in sorted(tracks.items()):
        if len(els) >= 2:
            rec.add_point3D(X[i], pycolmap.Track(els))
    rec.write(str(model_dir))
    return {"images": img_dir, "model": model_dir, "poses": folder / "poses.json"}
