"""COLMAP sparse models: read one into views, build one from views, depth ranges from its 3D points."""

from __future__ import annotations

import dataclasses
import re
import struct
from pathlib import Path

import numba as nb
import numpy as np

from .views import View, camera_pose, depth_range_from_depths, require_pycolmap, rig_pose

__all__ = ["load_model", "reconstruction_from_views", "auto_depth_ranges", "views_from_reconstruction", "rig_consistent",
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
    if (path / "images.bin").is_file():  # pycolmap reads a truncated binary file silently, as garbage
        damaged = diagnose_model(path)
        if damaged:
            raise ValueError(f"model folder {str(path)!r} cannot be read: {damaged}")
    try:
        rec = pycolmap.Reconstruction(str(path))
    except Exception as e:  # pycolmap raises several types for a broken model
        where = diagnose_model(path)
        reason = where or re.sub(r"^\[[^\]]*\]\s*", "", " ".join(str(e).split()))
        raise ValueError(f"model folder {str(path)!r} cannot be read: {reason}") from None
    try:
        views = views_from_reconstruction(rec)
    except ValueError as e:
        raise ValueError(f"model folder {str(path)!r}: {diagnose_model(path) or e}") from None
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


#: Parameters of each COLMAP camera model, by its id in the binary format.
_MODEL_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12, 11: 16}
#: Tokens of a data line of each text file: (fixed count, size of the repeated group after it).
_TEXT_LINES = {"cameras.txt": (4, None), "points3D.txt": (8, 2)}


def diagnose_model(path: Path) -> str | None:
    """Which file of a model is damaged, and how (a short reason); None when nothing is found.

    Walks the records of ``rigs``, ``cameras``, ``frames``, ``images`` and ``points3D`` (binary: every
    record must fit in the file and the file must end with the last one; text: every data line must
    have the fields COLMAP reads). Used to name the file when pycolmap refuses a model.
    """
    if (path / "images.bin").is_file():
        for name, walk in (("rigs.bin", _walk_rigs), ("cameras.bin", _walk_cameras), ("frames.bin", _walk_frames),
                           ("images.bin", _walk_images), ("points3D.bin", _walk_points)):
            f = path / name
            if f.is_file():
                try:
                    walk(f.read_bytes())
                except struct.error:
                    return f"{name} is damaged (it is truncated inside a record)"
                except (ValueError, IndexError) as e:
                    return f"{name} is damaged ({e})"
        return None
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        f = path / name
        if not f.is_file():
            continue
        lines = [ln.split() for ln in f.read_text(errors="replace").splitlines() if ln.strip() and not ln.startswith("#")]
        for k, tokens in enumerate(lines):
            problem = _text_line_problem(name, k, tokens)
            if problem:
                return f"{name} is damaged (data line {k + 1}: {problem})"
        if name == "images.txt" and not lines:
            return "images.txt has no images"
    return None


def _text_line_problem(name: str, k: int, tokens: list) -> str | None:
    if name == "images.txt":
        if k % 2 == 0 and len(tokens) < 10:
            return f"an image line needs 10 fields (id, qw, qx, qy, qz, tx, ty, tz, camera id, name), got {len(tokens)}"
        if k % 2 == 1 and len(tokens) % 3:
            return f"a points line needs (x, y, point3D id) triples, got {len(tokens)} fields"
        return _numbers(tokens[:9] if k % 2 == 0 else tokens)
    fixed, group = _TEXT_LINES[name]
    if len(tokens) < fixed or (group and (len(tokens) - fixed) % group):
        return f"{len(tokens)} fields do not form a {name[:-4]} line"
    return _numbers(tokens if name != "cameras.txt" else [tokens[0], *tokens[2:]])


def _numbers(tokens) -> str | None:
    for t in tokens:
        try:
            float(t)
        except ValueError:
            return f"{t!r} is not a number"
    return None


def _walk_cameras(b: bytes) -> None:
    (n,), o = struct.unpack_from("<Q", b, 0), 8
    for _ in range(n):
        _, model, _, _ = struct.unpack_from("<iiQQ", b, o)
        if model not in _MODEL_PARAMS:
            raise ValueError(f"unknown camera model id {model}")
        o += 24 + 8 * _MODEL_PARAMS[model]
    _ends(b, o)


def _walk_rigs(b: bytes) -> None:
    (n,), o = struct.unpack_from("<Q", b, 0), 8
    for _ in range(n):
        _, sensors = struct.unpack_from("<II", b, o)
        o += 8 + (8 if sensors else 0)  # the reference sensor (type, id)
        for _ in range(max(sensors - 1, 0)):  # the others: type, id, has_pose, [pose: 7 doubles]
            (has_pose,) = struct.unpack_from("<B", b, o + 8)
            o += 9 + 56 * bool(has_pose)
    _ends(b, o)


def _walk_frames(b: bytes) -> None:
    (n,), o = struct.unpack_from("<Q", b, 0), 8
    for _ in range(n):  # frame id, rig id, rig_from_world (7 doubles), data ids (type, sensor id, uint64 id)
        (data,) = struct.unpack_from("<I", b, o + 64)
        o += 68 + 16 * data
    _ends(b, o)


def _walk_images(b: bytes) -> None:
    (n,), o = struct.unpack_from("<Q", b, 0), 8
    for _ in range(n):
        o += 4 + 56 + 4
        end = b.find(b"\0", o)
        if end < 0:
            raise ValueError("it is truncated inside an image's name")
        (points,) = struct.unpack_from("<Q", b, end + 1)
        o = end + 1 + 8 + 24 * points
    _ends(b, o)


def _walk_points(b: bytes) -> None:
    (n,) = struct.unpack_from("<Q", b, 0)
    _ends(b, int(_points_end(np.frombuffer(b, dtype=np.uint8), n)))


@nb.njit(cache=True, nogil=True)
def _points_end(b, n):
    """Where the ``n`` records of a ``points3D.bin`` end (``len(b) + 1`` when one runs past the end)."""
    o = 8
    for _ in range(n):
        if o + 51 > b.shape[0]:
            return b.shape[0] + 1
        track = 0
        for k in range(8):  # little-endian uint64 track length at byte 43 of the record
            track |= np.int64(b[o + 43 + k]) << (8 * k)
        if track < 0 or track > b.shape[0]:
            return b.shape[0] + 1
        o += 51 + 8 * track
    return o


def _ends(b: bytes, o: int) -> None:
    if o != len(b):
        raise ValueError(f"its records end at byte {o} of {len(b)}" if o < len(b) else
                         f"it is truncated at {len(b)} bytes")


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


def rig_consistent(views, rec) -> list[View]:
    """``views`` with the poses that the multi-camera rigs of ``rec`` imply.

    In each frame of a rig with more than one camera, the view of the reference camera sets the frame's
    pose (``rig_from_world``), and every other view of the frame gets ``sensor_from_rig`` times it: the
    rig's calibration holds. Views of one-camera rigs, and views not in ``rec``, are returned as given.
    :func:`~episeg_cv.colmap.match_model` applies it to poses refined view by view (``refine_poses``).
    """
    by_name = {im.name: im for im in rec.images.values()}
    frames = {}
    for k, v in enumerate(views):
        im = by_name.get(v.name)
        if im is not None and rec.rig(rec.frame(im.frame_id).rig_id).num_sensors() > 1:
            frames.setdefault(im.frame_id, []).append(k)
    out = list(views)
    for fid, ks in frames.items():
        rig = rec.rig(rec.frame(fid).rig_id)
        sensor = [rec.cameras[by_name[views[k].name].camera_id].sensor_id for k in ks]
        ref = next((i for i, s in enumerate(sensor) if rig.is_ref_sensor(s)), 0)
        R, t = rig_pose(rig, sensor[ref], views[ks[ref]].R, views[ks[ref]].t)
        for k, s in zip(ks, sensor):
            Rk, tk = camera_pose(rig, s, R, t)
            out[k] = dataclasses.replace(views[k], R=Rk, t=tk)
    return out


def auto_depth_ranges(views, reconstruction, **kwargs) -> list[View]:
    """Each view with the depth range of the model's 3D points it observes.

    The depths (camera ``z``) of the points in each image's tracks go to
    :func:`~episeg_cv.collection.depth_range_from_depths` (robust percentiles
    with a margin; keyword arguments are passed on). An image that observes
    too few points keeps ``(0, inf)``.
    """
    xyz = {pid: p.xyz for pid, p in reconstruction.points3D.items()}
    out = []
    for v in views:
        # an image's observations, not every point's track: a third of the time (99k observations: 0.11 s)
        obs = reconstruction.image(v.image_id).get_observation_points2D() \
            if reconstruction.exists_image(v.image_id) else []
        X = np.asarray([xyz[p.point3D_id] for p in obs], dtype=np.float64).reshape(-1, 3)
        out.append(v.with_depth_range(depth_range_from_depths(X @ v.R[2] + v.t[2], **kwargs)))
    return out
