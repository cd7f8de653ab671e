"""COLMAP's own features, reused: keypoints and descriptors read from an existing COLMAP database.

``features="database"`` (``episeg colmap ... --features database``) matches the
keypoints that ``colmap feature_extractor`` or ``pycolmap.extract_features``
wrote into the database, and writes the matches and two-view geometries into
that same database, with its own image ids. The images of the model are found
in the database by name (the ids of the two need not agree).

Conventions: COLMAP stores keypoints with the centre of the top-left pixel at
``(0.5, 0.5)`` (0.5 is subtracted here) and SIFT descriptors as
``uint8 = min(255, round(512 * RootSIFT))``, so ``uint8 / 512`` is RootSIFT
with unit L2 norm, matched under L2.

What is written: matches, two-view geometries, the run record table
(``episeg_run``), and the database's cameras of the model's images, set to the
model's cameras when they differ (COLMAP's triangulator requires the
reconstruction's cameras to be the database's, and the known calibration is
the model's). Cameras, images and keypoints are never added or removed, and
features are never changed. A database that already holds matches is refused
unless ``resume`` (continue a run of ours) or ``overwrite`` (replace every
match and two-view geometry, never the features).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import logging
import os
import sqlite3
from pathlib import Path

import numpy as np

from ..interrupts import interrupts_deferred
from .database import read_run_record, write_run_record
from .store import FEATURES_VERSION, FeatureStore
from .views import View, poses_agree, require_pycolmap, rig_pose

_log = logging.getLogger("episeg_cv")

__all__ = ["DatabaseFeatureStore", "check_feature_database", "database_views", "prepare_feature_database",
           "read_database_features", "reconstruction_from_database", "SOURCE"]

#: The value of ``features`` that selects this module.
SOURCE = "database"
_SQLITE_MAGIC = b"SQLite format 3\x00"


def _open(path):
    return require_pycolmap().Database.open(str(path))


def check_feature_database(database, resume: bool, overwrite: bool) -> Path:
    """The database to read features from and write matches to, checked before any work.

    It must exist, be a writable SQLite file, and hold no matches or two-view
    geometries unless ``resume`` or ``overwrite``.
    """
    path = Path(database)
    if resume and overwrite:
        raise ValueError("resume and overwrite exclude each other")
    if path.is_dir():
        raise ValueError(f"database {str(path)!r} is a folder, expected a file path")
    if not path.is_file():
        raise ValueError(f"database {str(path)!r} does not exist; --features database reads the features from it "
                         "(run colmap feature_extractor or pycolmap.extract_features first)")
    with open(path, "rb") as f:
        if f.read(len(_SQLITE_MAGIC)) != _SQLITE_MAGIC:
            raise ValueError(f"database {str(path)!r} is not a COLMAP database (not an SQLite file)")
    if not os.access(path, os.W_OK) or not os.access(path.parent if str(path.parent) else Path("."), os.W_OK):
        raise ValueError(f"database {str(path)!r} is not writable")
    with _read_only(path) as con:
        n_pairs = con.execute("SELECT (SELECT COUNT(*) FROM matches) + (SELECT COUNT(*) FROM two_view_geometries)"
                              ).fetchone()[0]
    if n_pairs and not (resume or overwrite):
        raise ValueError(f"database {str(path)!r} already holds matches; pass --overwrite to replace them (the "
                         "features are kept) or --resume to continue a run")
    return path


@contextlib.contextmanager
def _read_only(path):
    """An SQLite connection that only reads (pycolmap's open would write to the file; sqlite3's read-only
    mode would leave -wal/-shm files behind, so the connection is read-write and never writes)."""
    try:
        con = sqlite3.connect(Path(path).resolve())  # (read-write mode only so that closing removes -wal/-shm)
    except sqlite3.Error as e:
        raise ValueError(f"database {str(path)!r} cannot be opened: {e}") from None
    try:
        yield con
    except sqlite3.DatabaseError as e:
        raise ValueError(f"database {str(path)!r} is not a COLMAP database ({e})") from None
    finally:
        con.close()


def database_views(path, views) -> list[View]:
    """The views with the database's image and camera ids, found by name.

    Raises ``ValueError`` for an image of the model that is not in the
    database or has no keypoints or descriptors there.
    """
    with _read_only(path) as con:
        images = {name: (iid, cid) for iid, name, cid in con.execute("SELECT image_id, name, camera_id FROM images")}
        with_kp = {r[0] for r in con.execute("SELECT image_id FROM keypoints WHERE rows > 0")}
        with_des = {r[0] for r in con.execute("SELECT image_id FROM descriptors WHERE rows > 0")}
    out = []
    for v in views:
        if v.name not in images:
            raise ValueError(f"image {v.name!r} of the model is not in database {str(path)!r} "
                             f"(it holds {len(images)} images)")
        iid, cid = images[v.name]
        if iid not in with_kp or iid not in with_des:
            raise ValueError(f"image {v.name!r} has no keypoints or descriptors in database {str(path)!r}")
        out.append(dataclasses.replace(v, image_id=int(iid), camera_id=int(cid)))
    return out


def read_database_features(database, image_id: int) -> tuple[np.ndarray, np.ndarray]:
    """``(keypoints (N, 2) float64, descriptors (N, D) float32)`` of one image of a COLMAP database.

    Keypoints in episeg_cv's convention (COLMAP's minus 0.5); uint8 SIFT
    descriptors divided by 512 (RootSIFT), float descriptors as stored.
    Read with a read-only connection: the file is not touched.
    """
    with _read_only(database) as con:
        kp_row = con.execute("SELECT rows, cols, data FROM keypoints WHERE image_id = ?", (int(image_id),)).fetchone()
        des_row = con.execute("SELECT rows, cols, data FROM descriptors WHERE image_id = ?",
                              (int(image_id),)).fetchone()
    if kp_row is None or des_row is None:
        raise ValueError(f"image {image_id} has no keypoints or descriptors in database {str(database)!r}")
    rows, cols, data = kp_row
    kp = np.frombuffer(data or b"", dtype=np.float32).reshape(rows, cols)[:, :2].astype(np.float64) - 0.5
    rows, cols, data = des_row
    blob = data or b""
    dtype = np.uint8 if len(blob) == rows * cols else np.float32
    d = np.frombuffer(blob, dtype=dtype).reshape(rows, cols)
    d = d.astype(np.float32) / 512.0 if dtype == np.uint8 else np.ascontiguousarray(d, dtype=np.float32)
    if len(d) != len(kp):
        raise ValueError(f"image {image_id} has {len(kp)} keypoints but {len(d)} descriptors in database "
                         f"{str(database)!r}")
    if not (np.isfinite(d).all() and np.isfinite(kp).all()):
        raise ValueError(f"image {image_id} has keypoints or descriptors that are NaN or inf in database "
                         f"{str(database)!r}")
    return kp, d


class DatabaseFeatureStore(FeatureStore):
    """COLMAP's features of each image (read from ``database``), cached on disk for the workers.

    The same interface as :class:`~episeg_cv.colmap.FeatureStore`; the views
    must carry the database's image ids (:func:`database_views`). Keypoints
    keep their database indices; where the camera's distortion cannot be
    inverted their pinhole position is NaN, and the matcher skips them.
    """

    def __init__(self, folder, image_dir, database):
        super().__init__(folder, image_dir)
        self.database = Path(database)

    @property
    def norm(self) -> str:
        return "l2"

    def describe(self) -> dict:
        return {"source": SOURCE}

    def _suffix(self) -> str:
        return SOURCE

    def ensure(self, view: View) -> tuple[int, str]:
        """Read the features of ``view`` from the database into the cache unless a fresh file exists.

        Returns ``(number of keypoints, SHA-256 of the image and of its features)``.
        """
        kp, des = read_database_features(self.database, view.image_id)
        h = hashlib.sha256(np.ascontiguousarray(kp).tobytes())
        h.update(np.ascontiguousarray(des).tobytes())
        digest = f"{self.digest(view)} features:{h.hexdigest()[:32]}"
        sig = repr((FEATURES_VERSION, SOURCE, digest, view.camera_model, tuple(float(p) for p in view.camera_params),
                    view.image_size))
        if self._cached(view, sig) is None:
            pinhole = view.undistort(kp)
            ok = view.undistortable(kp)
            if not ok.all():
                _log.info("image %r: %d of %d keypoints lie where the camera's distortion cannot be inverted; "
                          "not matched", view.name, int((~ok).sum()), len(kp))
                pinhole[~ok] = np.nan
            self._save(view, kp, pinhole, des, sig)
        return int(len(kp)), digest


def _camera(v: View):
    pycolmap = require_pycolmap()
    return pycolmap.Camera(model=v.camera_model, width=v.image_size[0], height=v.image_size[1],
                           params=list(v.camera_params), camera_id=v.camera_id)


def _same_camera(a, b) -> bool:
    return (a.model_name == b.model_name and (a.width, a.height) == (b.width, b.height)
            and np.allclose(np.asarray(a.params, dtype=float), np.asarray(b.params, dtype=float), rtol=1e-9, atol=1e-9))


def prepare_feature_database(path: Path, views, record: dict, resume: bool, overwrite: bool, warn) -> bool:
    """Make a database of COLMAP's features ready for our matches (call under :func:`database_lock`).

    ``overwrite`` deletes every match and two-view geometry; the database's cameras of the model's
    images are set to the model's where they differ (``warn`` says which); the run record is written
    unless ``resume`` (then :func:`~episeg_cv.colmap.database.check_resumable` reads it). Returns
    whether the run resumes: not when ``resume`` finds neither a run record nor matches (nothing to
    resume, a fresh start).
    """
    by_camera: dict[int, View] = {}
    for v in views:
        other = by_camera.setdefault(v.camera_id, v)
        if not _same_camera(_camera(other), _camera(v)):
            raise ValueError(f"images {other.name!r} and {v.name!r} share camera {v.camera_id} in database "
                             f"{str(path)!r} but have different cameras in the model; extract their features "
                             "with one camera per model camera")
    if resume and read_run_record(path) is None:
        db = _open(path)
        try:
            empty = not (db.num_matched_image_pairs() or db.num_verified_image_pairs())
        finally:
            db.close()
        resume = not empty  # nothing of ours to resume: start as a new run
    db = _open(path)
    try:
        with interrupts_deferred(), require_pycolmap().DatabaseTransaction(db):
            if overwrite:
                db.clear_matches()
                db.clear_two_view_geometries()
            for cid, v in sorted(by_camera.items()):
                have, want = db.read_camera(cid), _camera(v)
                if not _same_camera(have, want):
                    warn(f"database camera {cid} ({have.model_name} {have.params_to_string()}) set to the model's "
                         f"({want.model_name} {want.params_to_string()}), which the triangulation uses")
                    db.update_camera(want)
    finally:
        db.close()
    if not resume:
        write_run_record(path, record)
    return resume


def reconstruction_from_database(path, views):
    """A pycolmap.Reconstruction of ``views`` (no points) with the database's cameras, rigs, frames and ids.

    A frame of a multi-camera rig gets its ``rig_from_world`` from the view of its reference camera (or,
    without it, from another of its views through that camera's ``sensor_from_rig``); every other view
    of the frame must agree with it (:func:`~.model.rig_consistent` makes refined views so). A rig
    whose ``sensor_from_rig`` the database does not hold (``colmap rig_configurator`` without poses)
    takes it from the views of a frame that has the reference camera's image.

    Raises
    ------
    ValueError
        A view whose pose is not its rig's: ``sensor_from_rig`` composed with the frame's pose differs
        from it by more than 1e-6 (:func:`~.views.poses_agree`: rotation entries, translation relative
        to ``max(1, |t|)``); a rig without ``sensor_from_rig`` and no frame to find it from.
    """
    pycolmap = require_pycolmap()
    db = _open(path)
    try:
        images = {im.name: im for im in db.read_all_images()}
        cameras = {c.camera_id: c for c in db.read_all_cameras()}
        rigs = {r.rig_id: r for r in db.read_all_rigs()}
        frames = {f.frame_id: f for f in db.read_all_frames()}
    finally:
        db.close()
    rec = pycolmap.Reconstruction()
    chosen = [images[v.name] for v in views]
    for cid in sorted({im.camera_id for im in chosen}):
        rec.add_camera(cameras[cid])
    members = {}  # frame id -> [(view, image)]
    for v, im in zip(views, chosen):
        if im.frame_id not in frames:
            raise ValueError(f"image {v.name!r} has no frame in database {str(path)!r}")
        members.setdefault(im.frame_id, []).append((v, im))
    for rid in sorted({frames[f].rig_id for f in members}):
        _calibrate(rigs[rid], [g for f, g in members.items() if frames[f].rig_id == rid], cameras, path)
        rec.add_rig(rigs[rid])
    for fid, group in sorted(members.items()):
        frame, rig = frames[fid], rigs[frames[fid].rig_id]
        poses = [rig_pose(rig, cameras[im.camera_id].sensor_id, v.R, v.t) for v, im in group]
        ref = next((k for k, (_, im) in enumerate(group) if rig.is_ref_sensor(cameras[im.camera_id].sensor_id)), 0)
        R, t = poses[ref]
        for (v, _), (Rk, tk) in zip(group, poses):
            if not poses_agree(R, t, Rk, tk):
                raise ValueError(f"the pose of image {v.name!r} is not its rig's in database {str(path)!r}: "
                                 f"sensor_from_rig and the pose of {group[ref][0].name!r} put it elsewhere")
        f = pycolmap.Frame(frame_id=fid, rig_id=frame.rig_id)
        for d in frame.data_ids:
            if d.id in {im.image_id for _, im in group}:
                f.add_data_id(d)
        f.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(R), t)
        rec.add_frame(f)
    for v, im in zip(views, chosen):
        rec.add_image(pycolmap.Image(name=v.name, camera_id=im.camera_id, image_id=im.image_id, frame_id=im.frame_id))
    for fid in sorted(members):
        rec.register_frame(fid)
    return rec


def _calibrate(rig, groups, cameras, path) -> None:
    """Set the ``sensor_from_rig`` that ``rig`` lacks from the views of a frame holding the reference camera's
    image (``groups``: per frame ``[(view, image)]``)."""
    pycolmap = require_pycolmap()
    for sensor in rig.non_ref_sensors:
        if rig.has_sensor_from_rig(sensor):
            continue
        for group in groups:
            by_sensor = {cameras[im.camera_id].sensor_id: v for v, im in group}
            if rig.ref_sensor_id in by_sensor and sensor in by_sensor:
                ref, other = by_sensor[rig.ref_sensor_id], by_sensor[sensor]
                R = other.R @ ref.R.T  # cam_from_world = sensor_from_rig * rig_from_world, the ref camera's the rig's
                rig.set_sensor_from_rig(sensor, pycolmap.Rigid3d(pycolmap.Rotation3d(R), other.t - R @ ref.t))
                break
        else:
            raise ValueError(f"a rig of database {str(path)!r} has no sensor_from_rig for camera {sensor.id}, and no "
                             "frame holds both its image and the reference camera's to find it")
