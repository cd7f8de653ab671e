"""Posed collections without a COLMAP model: the poses JSON, and Middlebury's ``*_par.txt``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


from .._validation import as_camera_matrix, as_image_size, short_repr
from ..io.paths import read_json
from .images import image_size
from .model import load_model
from .views import View, is_bounded

__all__ = ["load_poses", "save_poses", "camera_of", "load_par", "is_par_file", "load_views"]


def camera_of(K, size, dist):
    """COLMAP camera model and params for pinhole ``K`` (episeg_cv convention) and OpenCV ``dist``."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5
    d = [float(v) for v in dist]
    if not d or not any(d):
        return "PINHOLE", (fx, fy, cx, cy)
    if len(d) == 4:
        return "OPENCV", (fx, fy, cx, cy, *d)
    if len(d) in (5, 8):
        return "FULL_OPENCV", (fx, fy, cx, cy, *(d + [0.0] * (8 - len(d))))
    raise ValueError(f"dist must have 0, 4, 5 or 8 OpenCV coefficients, got {len(d)}")


def load_poses(path) -> list[View]:
    """Read a poses JSON: the input for users without a COLMAP model.

    Format::

        {"images": [{"name": "img_000.png", "width": 640, "height": 480,
                     "K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],
                     "R": [[...], [...], [...]], "t": [tx, ty, tz],
                     "dist": [k1, k2, p1, p2],              (optional, OpenCV order)
                     "depth_range": [zmin, zmax]},          (optional)
                    ...]}

    ``R, t`` are world-to-camera (``X_cam = R X_world + t``). ``K`` puts the
    centre of the top-left pixel at ``(0, 0)`` (OpenCV's convention). ``dist``
    has 4 (COLMAP ``OPENCV``), 5 or 8 (``FULL_OPENCV``) coefficients. Images
    with the same ``K``, size and ``dist`` share one COLMAP camera. Image ids
    are 1, 2, ... in file order.

    Raises
    ------
    ValueError
        Unreadable JSON, a missing field or a bad value, naming the image.
    """
    data = read_json(path, "poses file")
    items = data.get("images") if isinstance(data, dict) else data
    if not isinstance(items, list) or not items:
        raise ValueError(f"poses file {str(path)!r} must hold a non-empty list 'images'")
    views, cameras, names = [], {}, set()
    for k, item in enumerate(items):
        where = f"poses file {str(path)!r}, image {k}"
        if not isinstance(item, dict):
            raise ValueError(f"{where}: expected an object, got {type(item).__name__}")
        missing = [f for f in ("name", "K", "R", "t", "width", "height") if f not in item]
        if missing:
            raise ValueError(f"{where}: missing {', '.join(missing)}")
        if not isinstance(item["name"], str) or not item["name"]:
            raise ValueError(f"{where}: name must be a non-empty string (the image's path), got "
                             f"{short_repr(item['name'])}")
        name = item["name"]
        if name in names:
            raise ValueError(f"{where}: image {name!r} is listed twice")
        names.add(name)
        try:
            K = as_camera_matrix(item["K"], "K")
            size = as_image_size((item["width"], item["height"]), "width, height")
            model, params = camera_of(K, size, item.get("dist", ()))
            key = (model, params, size)
            cameras.setdefault(key, len(cameras) + 1)
            views.append(View(name, k + 1, cameras[key], K, item["R"], item["t"], size, model, params,
                              item.get("depth_range", (0.0, float("inf")))))
        except (TypeError, ValueError, OverflowError) as e:
            raise ValueError(f"{where} ({name!r}): {' '.join(str(e).split())}") from None
    return views


def save_poses(path, views) -> None:
    """Write ``views`` as a poses JSON (:func:`load_poses` reads it back; distortion is not written)."""
    items = [{"name": v.name, "width": v.image_size[0], "height": v.image_size[1], "K": v.K.tolist(),
              "R": v.R.tolist(), "t": v.t.tolist(),
              **({"depth_range": list(v.depth_range)} if is_bounded(v.depth_range) else {})} for v in views]
    Path(path).write_text(json.dumps({"images": items}, indent=1), encoding="utf-8")


def is_par_file(path) -> bool:
    """Whether ``path`` names a Middlebury multi-view camera file (``*_par.txt``)."""
    return Path(path).name.endswith("_par.txt")


def load_par(path, image_dir) -> list[View]:
    """Read a Middlebury multi-view camera file (``*_par.txt``, Seitz et al., CVPR 2006).

    Format: an optional first line with the number of images, then one line per image::

        name.png k11 k12 k13 k21 k22 k23 k31 k32 k33 r11 r12 r13 r21 r22 r23 r31 r32 r33 t1 t2 t3

    The projection matrix is ``K [R | t]``, world-to-camera (``X_cam = R X + t``),
    with the image origin at the top-left. ``K`` is taken as given, in episeg_cv's
    (OpenCV's) pixel convention. The files carry no image size: it is read from
    the header of each image in ``image_dir``, in its stored grid (:mod:`.images`:
    the EXIF orientation is ignored, as COLMAP does). Rotations with rounding errors are repaired (see
    :func:`~episeg_cv._validation.as_rotation`). Image ids are 1, 2, ... in file
    order; images with the same ``K`` and size share a camera.

    Raises
    ------
    ValueError
        An unreadable file, a line with the wrong number of values (with its
        line number), a count that disagrees with the lines, a missing image,
        or a bad value.
    """
    path, image_dir = Path(path), Path(image_dir)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"camera file {str(path)!r} cannot be read: {e}") from e
    items, count = [], None
    for lineno, raw in enumerate(lines, 1):
        parts = raw.split()
        if not parts or parts[0].startswith("#"):
            continue
        if count is None and not items and len(parts) == 1 and parts[0].isdigit():
            count = int(parts[0])
            continue
        if len(parts) != 22:
            raise ValueError(f"{path}:{lineno}: expected 'name' and 21 numbers (K, R, t), got {len(parts)} fields")
        try:
            values = np.array([float(v) for v in parts[1:]])
        except ValueError as e:
            raise ValueError(f"{path}:{lineno}: {e}") from e
        items.append((lineno, parts[0], values))
    if not items:
        raise ValueError(f"camera file {str(path)!r} lists no image")
    if count is not None and count != len(items):
        raise ValueError(f"camera file {str(path)!r} announces {count} images but lists {len(items)}")
    views, cameras, names = [], {}, set()
    for k, (lineno, name, values) in enumerate(items):
        where = f"{path}:{lineno} ({name!r})"
        if name in names:
            raise ValueError(f"{where}: image listed twice")
        names.add(name)
        size = image_size(image_dir / name)
        if size is None:
            raise ValueError(f"{where}: image {str(image_dir / name)!r} is missing or cannot be read")
        K = values[:9].reshape(3, 3)
        try:
            model, params = camera_of(K, size, ())
            cameras.setdefault((params, size), len(cameras) + 1)
            views.append(View(name, k + 1, cameras[(params, size)], K, values[9:18].reshape(3, 3), values[18:],
                              size, model, params))
        except (TypeError, ValueError) as e:
            raise ValueError(f"{where}: {e}") from e
    return views


def load_views(model, image_dir=None):
    """``(views, reconstruction or None)`` from a model folder, a poses JSON, a Middlebury ``*_par.txt``
    (its image sizes are read from ``image_dir``) or a list of View."""
    if isinstance(model, (list, tuple)):
        if not model or not all(isinstance(v, View) for v in model):
            raise ValueError("model must be a non-empty list of View, a model folder or a poses JSON")
        return list(model), None
    path = Path(model)
    if not path.exists():
        raise ValueError(f"model {str(path)!r} does not exist (expected a COLMAP model folder, a poses JSON or a "
                         "Middlebury *_par.txt)")
    if path.is_file() and is_par_file(path):
        if image_dir is None:
            raise ValueError(f"a Middlebury camera file ({path.name}) needs the image folder for the image sizes")
        return load_par(path, image_dir), None
    if path.is_file():
        return load_poses(path), None
    return load_model(path)
