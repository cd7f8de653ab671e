"""COLMAP sparse models: read one into views, build one from views, depth ranges from its 3D points."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .views import View, depth_range_from_depths, require_pycolmap

__all__ = ["load_model", "reconstruction_from_views", "auto_depth_ranges", "views_from_reconstruction",
           "check_binary_model"]


def views_from_reconstruction(rec) -> list[View]:
    views = []
    for image_id in sorted(rec.reg_image_ids()):
        im = rec.image(image_id)
        cam = rec.camera(im.camera_id)
        K = np.asarray(cam.calibration_matrix(), dtype=np.float64).copy()
        K[:2, 2] -= 0.5  # COLMAP's pixel convention -> episeg_cv's
        M = np.asarray(im.cam_from_world().matrix(), dtype=np.float64)
        views.append(View(im.name, int(image_id), int(im.camera_id), K, M[:, :3], M[:, 3],
                          (int(cam.width), int(cam.height)), cam.model_name, tuple(float(p) for p in cam.params)))
    return views


def load_model(model_dir):
    """Read a COLMAP sparse model (binary or text) with ``pycolmap.Reconstruction``.

    Returns
    -------
    views : list of View
        The registered images, by image id.
    reconstruction : pycolmap.Reconstruction

    Raises
    ------
    ValueError
        The folder is missing, holds no model, or the model has no registered images.
    """
    pycolmap = require_pycolmap()
    path = Path(model_dir)
    if not path.is_dir():
        raise ValueError(f"model folder {str(path)!r} does not exist")
    if not any((path / f"images.{ext}").is_file() for ext in ("bin", "txt")):
        raise ValueError(f"model folder {str(path)!r} holds no COLMAP model (images.bin or images.txt)")
    check_binary_model(path)
    try:
        rec = pycolmap.Reconstruction(str(path))
    except Exception as e:  # pycolmap raises several types for a broken model
        raise ValueError(f"model folder {str(path)!r} cannot be read: {e}") from e
    views = views_from_reconstruction(rec)
    if not views:
        raise ValueError(f"model {str(path)!r} has no registered images")
    return views, rec


#: The smallest record of each binary model file, in bytes (after the uint64 record count).
_MIN_RECORD = {"cameras.bin": 24, "images.bin": 73, "points3D.bin": 51, "rigs.bin": 16, "frames.bin": 16}


def check_binary_model(path: Path) -> None:
    """Refuse a binary model file that is empty or shorter than its record count says.

    COLMAP reads the count first and allocates for it: an empty or truncated
    ``points3D.bin`` costs minutes and gigabytes before it fails.
    """
    if (path / "images.bin").is_file():
        names = [n for n in _MIN_RECORD if (path / n).exists()]
    else:
        names = []
    for name in names:
        f = path / name
        size = f.stat().st_size
        if size < 8:
            raise ValueError(f"model file {str(f)!r} is {'empty' if size == 0 else 'truncated'} "
                             f"({size} bytes); expected a COLMAP binary model")
        with open(f, "rb") as fh:
            count = int.from_bytes(fh.read(8), "little")
        if count * _MIN_RECORD[name] > size - 8:
            raise ValueError(f"model file {str(f)!r} is truncated or not a COLMAP binary file: it announces {count} "
                             f"records in {size} bytes")


def reconstruction_from_views(views):
    """A pycolmap.Reconstruction with trivial rigs and frames for ``views`` (no points)."""
    pycolmap = require_pycolmap()
    rec = pycolmap.Reconstruction()
    for v in views:
        if not rec.exists_camera(v.camera_id):
            cam = pycolmap.Camera(model=v.camera_model, width=v.image_size[0], height=v.image_size[1],
                                  params=list(v.camera_params), camera_id=v.camera_id)
            rec.add_camera_with_trivial_rig(cam)
        rec.add_image_with_trivial_frame(pycolmap.Image(name=v.name, camera_id=v.camera_id, image_id=v.image_id))
        rec.frame(v.image_id).rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(v.R), v.t)
        rec.register_frame(v.image_id)
    return rec


def auto_depth_ranges(views, reconstruction, **kwargs) -> list[View]:
    """Each view with the depth range of the model's 3D points it observes.

    The depths (camera ``z``) of the points in each image's tracks go to
    :func:`~episeg_cv.collection.depth_range_from_depths` (robust percentiles
    with a margin; keyword arguments are passed on). An image that observes
    too few points keeps ``(0, inf)``.
    """
    by_image: dict[int, list] = {v.image_id: [] for v in views}
    for pt in reconstruction.points3D.values():
        for el in pt.track.elements:
            if el.image_id in by_image:
                by_image[el.image_id].append(pt.xyz)
    out = []
    for v in views:
        X = np.asarray(by_image[v.image_id], dtype=np.float64).reshape(-1, 3)
        out.append(v.with_depth_range(depth_range_from_depths(X @ v.R[2] + v.t[2], **kwargs)))
    return out
