"""Calibration files: read and write a two-view calibration.

:func:`load_calibration` reads JSON, or the YAML / XML that ``cv2.FileStorage``
writes (what ``cv2.stereoCalibrate`` users usually save), into a
:class:`Calibration`, whose :attr:`~Calibration.geometry` is the
:class:`~episeg_cv.TwoViewGeometry` a matcher needs.

Lens distortion
---------------
The epipolar segment is a pinhole construction. When a file holds distortion
coefficients (``dist1``/``dist2``, or OpenCV's ``D1``/``D2``), the keypoints
must first be moved into the pinhole image with :func:`~episeg_cv.undistort_points`
(``cv2.undistortPoints`` with ``P = K``): the undistorted positions are pixels of
an ideal camera with the same ``K`` and image size. The ``episeg`` command does
this for you; the matches still index the keypoints as detected.

Conventions: ``X2 = R @ X1 + t`` (as ``cv2.stereoCalibrate`` returns ``R, T``);
pixel centres at integer coordinates; ``image_size`` is ``(width, height)``.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from .._validation import MAX_IMAGE_SIDE, short_repr, as_camera_matrix, as_image_size, as_rotation, as_vector3
from ..distortion import as_distortion
from ..geometry import TwoViewGeometry, as_geometry
from .paths import input_file, output_file, read_json, written_atomically

__all__ = ["Calibration", "load_calibration", "save_calibration"]

_LAYOUTS = ("K1, K2, R, t [, image_size1, image_size2, dist1, dist2]; "
            "cameras: [{K, R, t, image_size, dist}, {...}]; K1, R1, t1, K2, R2, t2; P1, P2; "
            "or OpenCV's M1, D1, M2, D2, R, T")


@dataclass(frozen=True, eq=False)
class Calibration:
    """Intrinsics, relative pose, image sizes and distortion of two cameras.

    Attributes
    ----------
    K1, K2 : (3, 3) float64
        Intrinsics in pixels (pixel centres at integer coordinates).
    R : (3, 3) float64 or None
        Rotation from camera 1 to camera 2: ``X2 = R @ X1 + t``; None (with
        ``t``) when the file gives the intrinsics only (:attr:`has_pose`).
    t : (3,) float64 or None
        Translation, in the file's length unit (the unit of a depth range).
    image_size1, image_size2 : (int, int) or None
        ``(width, height)``; None when the file does not say (see
        :meth:`with_image_sizes`).
    dist1, dist2 : (k,) float64 or None
        OpenCV distortion coefficients (``k`` in 4, 5, 8, 12, 14); None when
        absent or all zero.
    source : str
        Where it was read from (for messages).

    Examples
    --------
    >>> import numpy as np
    >>> K = [[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]]
    >>> c = Calibration(np.array(K), np.array(K), np.eye(3), np.array([-1.0, 0, 0]), (640, 480), (640, 480))
    >>> c.geometry.epipole.tolist()          # t_3 = 0: the epipole is at infinity
    [-inf, nan]
    >>> c.has_distortion
    False
    """

    K1: np.ndarray
    K2: np.ndarray
    R: np.ndarray
    t: np.ndarray
    image_size1: tuple | None = None
    image_size2: tuple | None = None
    dist1: np.ndarray | None = None
    dist2: np.ndarray | None = None
    source: str = "<calibration>"

    def __post_init__(self):
        src = self.source
        object.__setattr__(self, "K1", _checked(as_camera_matrix, self.K1, "K1", src))
        object.__setattr__(self, "K2", _checked(as_camera_matrix, self.K2, "K2", src))
        if (self.R is None) != (self.t is None):
            given, missing = ("R", "t") if self.t is None else ("t", "R")
            raise ValueError(f"{src}: the pose has {given} but no {missing}: give both, or neither to estimate the "
                             "pose from the images")
        if self.R is not None:
            object.__setattr__(self, "R", _checked(as_rotation, self.R, "R", src))
            object.__setattr__(self, "t", _checked(as_vector3, self.t, "t", src))
        for name in ("image_size1", "image_size2"):
            v = getattr(self, name)
            if v is not None:
                if isinstance(v, np.ndarray):
                    v = tuple(v.ravel().tolist())
                object.__setattr__(self, name, _checked(as_image_size, v, name, src))
        for name in ("dist1", "dist2"):
            object.__setattr__(self, name, as_distortion(getattr(self, name), name, src))
        for name in ("K1", "K2", "R", "t", "dist1", "dist2"):
            a = getattr(self, name)
            if a is not None:
                a.flags.writeable = False

    @property
    def has_distortion(self) -> bool:
        """True when either camera has non-zero distortion coefficients."""
        return self.dist1 is not None or self.dist2 is not None

    @property
    def has_pose(self) -> bool:
        """True when the file gives the relative pose ``R, t`` (not only the intrinsics)."""
        return self.R is not None

    @property
    def geometry(self) -> TwoViewGeometry:
        """The :class:`~episeg_cv.TwoViewGeometry` of the (undistorted) pair.

        Raises
        ------
        ValueError
            The image sizes are unknown (use :meth:`with_image_sizes` first), or
            there is no pose (estimate it: :func:`~episeg_cv.estimate_geometry`).
        """
        if not self.has_pose:
            raise ValueError(f"{self.source}: no pose (R, t), only the intrinsics; estimate the pose from the images "
                             "(episeg_cv.estimate_geometry with K1, K2, or episeg match)")
        if self.image_size1 is None or self.image_size2 is None:
            raise ValueError(f"{self.source}: image sizes unknown; add 'image_size1' and 'image_size2' "
                             "([width, height]) to the file or pass them to load_calibration")
        return TwoViewGeometry(self.K1, self.K2, self.R, self.t, image_size1=self.image_size1,
                               image_size2=self.image_size2)

    def with_image_sizes(self, image_size1, image_size2) -> "Calibration":
        """Fill in missing image sizes; check those the file gives against these.

        Parameters
        ----------
        image_size1, image_size2 : (int, int)
            ``(width, height)`` of the images, e.g. ``image.shape[1::-1]``.

        Raises
        ------
        ValueError
            The file gives a different size.
        """
        sizes = []
        for name, given in (("image_size1", image_size1), ("image_size2", image_size2)):
            given = as_image_size(given, name)
            own = getattr(self, name)
            if own is not None and own != given:
                raise ValueError(f"{self.source}: {name} is {own[0]}x{own[1]} but the image is {given[0]}x{given[1]}")
            sizes.append(given)
        return replace(self, image_size1=sizes[0], image_size2=sizes[1])

    @classmethod
    def from_geometry(cls, geometry: TwoViewGeometry, dist1=None, dist2=None) -> "Calibration":
        """The calibration of a :class:`~episeg_cv.TwoViewGeometry`, with optional distortion."""
        geometry = as_geometry(geometry)
        return cls(geometry.K1.copy(), geometry.K2.copy(), geometry.R.copy(), geometry.t.copy(),
                   geometry.image_size1, geometry.image_size2, dist1, dist2, "<geometry>")


def _checked(fn, value, name, source):
    try:
        return fn(value, name)
    except (ValueError, TypeError) as exc:
        raise type(exc)(f"{source}: {exc}") from None


# --------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------
def load_calibration(path, image_size1=None, image_size2=None) -> Calibration:
    """Read a two-view calibration from a JSON, YAML or XML file.

    Accepted layouts (keys are case-sensitive; ``t`` may be ``(3,)``, ``(3, 1)``
    or ``(1, 3)``; sizes are ``[width, height]``; distortion is optional and
    uses OpenCV's coefficient order ``k1, k2, p1, p2[, k3, ...]``):

    Every layout may leave out the pose (``R``, ``t``, ``T``, ``R1``...) to give
    the intrinsics only: :attr:`Calibration.has_pose` is then False and the pose
    is to be estimated from the images (:func:`~episeg_cv.estimate_geometry`).
    Part of a pose (``R`` without ``t``) is an error.

    1. Relative pose, ``X2 = R X1 + t``::

           {"K1": 3x3, "K2": 3x3, "R": 3x3, "t": [3],
            "image_size1": [w, h], "image_size2": [w, h],
            "dist1": [k...], "dist2": [k...]}

       ``"K"`` alone stands for both ``K1`` and ``K2``, and ``"image_size"``
       for both sizes.
    2. World-to-camera poses per camera (``X_cam = R X_world + t``, OpenCV and
       COLMAP)::

           {"cameras": [{"K": 3x3, "R": 3x3, "t": [3], "image_size": [w, h], "dist": [k...]},
                        {...}]}

       or flat: ``K1, R1, t1, K2, R2, t2`` (+ sizes, distortion).
    3. Projection matrices ``P = K [R | t]``: ``P1``, ``P2`` (3x4) + sizes.
    4. OpenCV's ``stereoCalibrate`` names, in JSON or in a ``cv2.FileStorage``
       file (``.yml``, ``.yaml``, ``.xml``, optionally ``.gz``): ``M1``, ``D1``,
       ``M2``, ``D2``, ``R``, ``T``. Sizes from ``image_size1``/``image_size2``,
       ``image_size``/``imageSize``, ``image_width``/``image_height`` or
       ``width``/``height`` if present. Matrices written by
       ``cv2.FileStorage`` in JSON (``"type_id": "opencv-matrix"``) are read too.

    Files with ``.json`` are parsed as JSON; any other suffix goes to
    ``cv2.FileStorage``.

    Parameters
    ----------
    path : str or os.PathLike
    image_size1, image_size2 : (int, int), optional
        ``(width, height)`` of the images. Fill in sizes the file does not
        give; when it does, they must agree.

    Returns
    -------
    Calibration

    Raises
    ------
    OSError
        The file does not exist or cannot be read.
    ValueError
        Unparseable file, or a missing or malformed key. The message names the
        file, the key and the expected shape, e.g.
        ``calib.json: key 'K1' must be a 3x3 matrix, got shape (3, 4)``.

    Examples
    --------
    >>> from episeg_cv.datasets import data_dir
    >>> c = load_calibration(data_dir() / "default" / "calib.json")
    >>> c.image_size1, c.has_distortion, c.geometry.image_size2
    ((640, 480), False, (640, 480))
    """
    path = input_file(path, "calibration file")
    name = path.name
    if path.suffix.lower() == ".json":
        data = read_json(path, "calibration file", MAX_CALIBRATION_BYTES)
        if isinstance(data, dict):
            data = {k: _keyed(_from_opencv_json, v, k, name) for k, v in data.items()}
        if not isinstance(data, dict):
            raise ValueError(f"{name}: the top level must be a JSON object, got {type(data).__name__}")
    else:
        data = _read_filestorage(path)
    calib = _from_mapping(data, name)
    if image_size1 is not None or image_size2 is not None:
        if image_size1 is None or image_size2 is None:
            raise ValueError("image_size1 and image_size2 must be given together")
        calib = calib.with_image_sizes(image_size1, image_size2)
    return calib


def _keyed(fn, value, key, source):
    try:
        return fn(value)
    except ValueError as exc:
        raise ValueError(f"{source}: key '{key}': {exc}") from None


def _from_opencv_json(v):
    """A matrix as ``cv2.FileStorage`` writes it in JSON, or ``v`` unchanged (ValueError when malformed)."""
    if isinstance(v, dict) and v.get("type_id") == "opencv-matrix" and {"rows", "cols", "data"} <= v.keys():
        try:
            return np.asarray(v["data"], dtype=np.float64).reshape(int(v["rows"]), int(v["cols"]))
        except (ValueError, TypeError, OverflowError):
            raise ValueError(f"an opencv-matrix must hold rows x cols numbers in 'data', got rows {short_repr(v['rows'])}, "
                             f"cols {short_repr(v['cols'])} and {short_repr(v['data'])}") from None
    if isinstance(v, list):
        return [_from_opencv_json(x) for x in v]
    if isinstance(v, dict):
        return {k: _from_opencv_json(x) for k, x in v.items()}
    return v


#: A calibration file is a few kilobytes; larger files are refused before any parser sees them.
MAX_CALIBRATION_BYTES = 1 << 20
#: Deepest nesting of brackets (YAML) or elements (XML) accepted: OpenCV's parser recurses on the C
#: stack, so a file nested 100000 levels deep would crash the process, not raise.
MAX_NESTING = 64


def _nesting_depth(text: str, xml: bool) -> int:
    """The deepest nesting of ``[``/``{`` (YAML, JSON) or of elements (XML), outside quoted strings."""
    depth = best = 0
    if xml:
        for m in re.finditer(r"<(/?)([^<>]*?)(/?)>", text):
            closing, body, empty = m.groups()
            if body.startswith(("?", "!")) or empty:
                continue
            depth += -1 if closing else 1
            best = max(best, depth)
        return best
    quote = None
    for ch in text:
        if quote:
            if ch == quote:
                quote = None
        elif ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
            best = max(best, depth)
        elif ch in "]}":
            depth -= 1
    return best


def _read_filestorage(path: Path) -> dict:
    size = path.stat().st_size
    if size > MAX_CALIBRATION_BYTES:
        raise ValueError(f"{path.name}: {size} bytes is too large for a calibration file (at most "
                         f"{MAX_CALIBRATION_BYTES})")
    text = path.read_bytes().decode("utf-8", errors="replace")
    xml = text.lstrip().startswith("<")
    depth = _nesting_depth(text, xml)
    if depth > MAX_NESTING:
        raise ValueError(f"{path.name}: nested {depth} levels deep (at most {MAX_NESTING}); not a calibration file")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        opened = fs.isOpened()
    except Exception as exc:  # cv2.error, or SystemError wrapping it, on a parse error
        raise ValueError(f"{path.name}: cannot parse as OpenCV YAML/XML ({_cv_reason(exc)})") from None
    if not opened:
        raise ValueError(f"{path.name}: cannot open as OpenCV YAML/XML (use .json, .yml, .yaml or .xml)")
    try:
        root = fs.root()
        out = {}
        for k in (root.keys() if root.isMap() else []):  # an empty file (header only) has no map: nothing in it
            try:
                out[k] = _node_value(fs.getNode(k))
            except (cv2.error, SystemError, ValueError, OverflowError) as exc:
                raise ValueError(f"{path.name}: key '{k}' cannot be read ({_cv_reason(exc)})") from None
        return out
    except (cv2.error, SystemError) as exc:
        raise ValueError(f"{path.name}: cannot parse as OpenCV YAML/XML ({_cv_reason(exc)})") from None
    finally:
        fs.release()


def _cv_reason(exc: BaseException) -> str:
    """The last line of an OpenCV error (its assertion), without the source location."""
    text = str(exc.__cause__ or exc).strip().splitlines()
    last = text[-1] if text else type(exc).__name__
    return re.sub(r"^.*?error: \(-?\d+:[^)]*\)\s*", "", last).strip() or last


def _node_value(node):
    if node.isMap():
        m = node.mat()
        if m is not None:
            return np.asarray(m, dtype=np.float64)
        return {k: _node_value(node.getNode(k)) for k in node.keys()}
    if node.isSeq():
        return [_node_value(node.at(i)) for i in range(node.size())]
    if node.isInt():
        return int(node.real())
    if node.isReal():
        return node.real()
    if node.isString():
        return node.string()
    return None


def _matrix(data: dict, key: str, shape: tuple, source: str, required: bool = True):
    if key not in data or data[key] is None:
        if not required:
            return None
        raise ValueError(f"{source}: missing key '{key}' (a {_shape_words(shape)}); accepted layouts: {_LAYOUTS}")
    v = data[key]
    try:
        arr = np.asarray(v, dtype=np.float64)
    except (ValueError, TypeError):
        raise ValueError(f"{source}: key '{key}' must be a {_shape_words(shape)} of numbers, got {short_repr(v, 60)}") from None
    if shape == (3,) and arr.size == 3 and arr.ndim <= 2:
        arr = arr.reshape(3)
    if arr.shape != shape:
        raise ValueError(f"{source}: key '{key}' must be a {_shape_words(shape)}, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{source}: key '{key}' must be finite, got NaN or inf")
    return arr


def _shape_words(shape) -> str:
    if len(shape) == 1:
        return f"vector of {shape[0]} numbers"
    return f"{shape[0]}x{shape[1]} matrix"


def _size(data: dict, keys, source: str):
    for key in keys:
        if isinstance(key, tuple):  # (width_key, height_key)
            if key[0] in data and key[1] in data:
                v, label = (data[key[0]], data[key[1]]), f"'{key[0]}'/'{key[1]}'"
            else:
                continue
        elif key in data and data[key] is not None:
            v, label = data[key], f"'{key}'"
        else:
            continue
        try:
            arr = np.asarray(v, dtype=np.float64).ravel()
        except (ValueError, TypeError):
            arr = np.zeros(0)
        if arr.size != 2 or not np.all(np.isfinite(arr)) or np.any(arr <= 0) or np.any(arr != np.round(arr)) \
                or np.any(arr > MAX_IMAGE_SIDE):
            raise ValueError(f"{source}: key {label} must be [width, height], two positive integers at most "
                             f"{MAX_IMAGE_SIDE}, got {short_repr(v)}")
        return int(arr[0]), int(arr[1])
    return None


def _from_mapping(data: dict, source: str) -> Calibration:
    def get_dist(*keys):
        for k in keys:
            if k in data and data[k] is not None:
                return as_distortion(data[k], k, source)
        return None

    shared = _size(data, ("image_size", "imageSize", ("image_width", "image_height"), ("width", "height")), source)
    size1 = _size(data, ("image_size1",), source) or shared
    size2 = _size(data, ("image_size2",), source) or shared

    if "cameras" in data:
        cams = data["cameras"]
        if not isinstance(cams, list) or len(cams) != 2 or not all(isinstance(c, dict) for c in cams):
            raise ValueError(f"{source}: key 'cameras' must be a list of two objects with K, R, t, got {short_repr(cams, 60)}")
        Ks, Rs, ts, sizes, dists = [], [], [], [], []
        for i, cam in enumerate(cams):
            where = f"{source}: cameras[{i}]"
            Ks.append(_matrix(cam, "K", (3, 3), where))
            _pose_keys(cam, (("R",), ("t",)), where)
            Rs.append(_matrix(cam, "R", (3, 3), where, required=False))
            ts.append(_matrix(cam, "t", (3,), where, required=False))
            sizes.append(_size(cam, ("image_size", ("width", "height")), where) or (size1, size2)[i])
            dists.append(as_distortion(cam.get("dist"), "dist", where))
        if (Rs[0] is None) != (Rs[1] is None):
            raise ValueError(f"{source}: one camera has a pose (R, t) and the other not: give both, or neither to "
                             "estimate the pose from the images")
        R, t = _relative(Rs, ts, source) if Rs[0] is not None else (None, None)
        return Calibration(Ks[0], Ks[1], R, t, sizes[0], sizes[1], dists[0], dists[1], source)

    if "P1" in data and "P2" in data and "K1" not in data and "M1" not in data:
        P1 = _matrix(data, "P1", (3, 4), source)
        P2 = _matrix(data, "P2", (3, 4), source)
        try:
            g = TwoViewGeometry.from_projection_matrices(P1, P2, image_size1=size1 or (1, 1), image_size2=size2 or (1, 1))
        except ValueError as exc:
            raise ValueError(f"{source}: {exc}") from None
        return Calibration(g.K1.copy(), g.K2.copy(), g.R.copy(), g.t.copy(), size1, size2,
                           get_dist("dist1", "D1"), get_dist("dist2", "D2"), source)

    if any(k in data for k in ("M1", "M2", "D1", "D2", "T")) and not any(k in data for k in ("K1", "K2", "K", "t")):
        # cv2.stereoCalibrate names
        K1 = _checked(as_camera_matrix, _matrix(data, "M1", (3, 3), source), "M1", source)
        K2 = _checked(as_camera_matrix, _matrix(data, "M2", (3, 3), source), "M2", source)
        _pose_keys(data, (("R",), ("T", "t")), source)
        R = _matrix(data, "R", (3, 3), source, required=False)
        t = _matrix(data, "T" if "T" in data else "t", (3,), source, required=False)
        return Calibration(K1, K2, R, t, size1, size2, get_dist("D1", "dist1"), get_dist("D2", "dist2"), source)

    K = _matrix(data, "K", (3, 3), source, required=False)
    K1 = _matrix(data, "K1", (3, 3), source, required=K is None)
    K2 = _matrix(data, "K2", (3, 3), source, required=K is None)
    K1 = K if K1 is None else K1
    K2 = K if K2 is None else K2
    if any(k in data for k in ("R1", "R2", "t1", "t2")):  # flat world poses
        _pose_keys(data, (("R1",), ("R2",), ("t1",), ("t2",)), source)
        Rs = [_matrix(data, "R1", (3, 3), source), _matrix(data, "R2", (3, 3), source)]
        ts = [_matrix(data, "t1", (3,), source), _matrix(data, "t2", (3,), source)]
        R, t = _relative(Rs, ts, source)
    elif _pose_keys(data, (("R",), ("t", "T")), source):
        R = _matrix(data, "R", (3, 3), source)
        t = _matrix(data, "t", (3,), source) if "t" in data or "T" not in data else _matrix(data, "T", (3,), source)
    else:  # the intrinsics only: the pose is to be estimated from the images
        R = t = None
    return Calibration(K1, K2, R, t, size1, size2, get_dist("dist1", "D1"), get_dist("dist2", "D2"), source)


def _pose_keys(data: dict, groups, source) -> bool:
    """Whether the pose is given (True) or absent (False); ``ValueError`` when only part of it is.

    ``groups`` lists the keys of a whole pose, each as a tuple of alternative names (``("t", "T")``).
    """
    present = [[k for k in g if k in data and data[k] is not None] for g in groups]
    if not any(present):
        return False
    missing = [g[0] for g, p in zip(groups, present) if not p]
    if missing:
        given = ", ".join(k for p in present for k in p)
        shape = "a 3x3 matrix" if missing[0].startswith("R") else "a vector of 3 numbers"
        raise ValueError(f"{source}: missing key '{missing[0]}' ({shape}): a partial pose ({given} given); give the "
                         "whole pose, or none of it (the intrinsics only) to estimate the pose from the images")
    return True


def _relative(Rs, ts, source):
    """``R = R2 R1^T``, ``t = t2 - R t1`` from world-to-camera poses."""
    for i, R in enumerate(Rs):
        _checked(as_rotation, R, f"R{i + 1}", source)
    R = Rs[1] @ Rs[0].T
    return R, ts[1] - R @ ts[0]


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------
def save_calibration(path, calibration: Calibration) -> Path:
    """Write a calibration as JSON (layout 1) or, for ``.yml``/``.yaml``/``.xml``, OpenCV's names.

    The JSON written is read back by :func:`load_calibration`; the YAML/XML
    holds ``M1, D1, M2, D2, R, T, image_size1, image_size2`` as
    ``cv2.FileStorage`` writes them.

    Parameters
    ----------
    path : str or os.PathLike
    calibration : Calibration or TwoViewGeometry

    Returns
    -------
    pathlib.Path
        The path written.

    Examples
    --------
    >>> import tempfile, os
    >>> from episeg_cv.datasets import load_default_pair
    >>> c = Calibration.from_geometry(load_default_pair().geometry)
    >>> with tempfile.TemporaryDirectory() as d:
    ...     back = load_calibration(save_calibration(os.path.join(d, "c.yml"), c))
    >>> bool(np.allclose(back.R, c.R)), back.image_size2
    (True, (640, 480))
    """
    if isinstance(calibration, TwoViewGeometry):
        calibration = Calibration.from_geometry(calibration)
    if not isinstance(calibration, Calibration):
        raise TypeError(f"calibration must be a Calibration or a TwoViewGeometry, got {type(calibration).__name__}")
    c = calibration
    path = output_file(path, "calibration file")
    if path.suffix.lower() == ".json":
        out = {"convention": "X2 = R X1 + t; pixel centres at integer coordinates; image_size = [width, height]",
               "K1": c.K1.tolist(), "K2": c.K2.tolist()}
        if c.has_pose:
            out.update(R=c.R.tolist(), t=c.t.tolist())
        for name in ("image_size1", "image_size2"):
            if getattr(c, name) is not None:
                out[name] = list(getattr(c, name))
        for name in ("dist1", "dist2"):
            if getattr(c, name) is not None:
                out[name] = getattr(c, name).tolist()
        with written_atomically(path) as tmp:
            tmp.write_text(json.dumps(out, indent=2) + "\n")
        return path
    with written_atomically(path) as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        if not fs.isOpened():
            raise OSError(f"cannot write calibration file {str(path)!r} (use .json, .yml, .yaml or .xml)")
        try:
            fs.write("M1", c.K1)
            fs.write("D1", np.zeros((1, 5)) if c.dist1 is None else c.dist1.reshape(1, -1))
            fs.write("M2", c.K2)
            fs.write("D2", np.zeros((1, 5)) if c.dist2 is None else c.dist2.reshape(1, -1))
            if c.has_pose:
                fs.write("R", c.R)
                fs.write("T", c.t.reshape(3, 1))
            for name in ("image_size1", "image_size2"):
                if getattr(c, name) is not None:
                    fs.write(name, np.array(getattr(c, name), dtype=np.int32))
        finally:
            fs.release()
    return path
