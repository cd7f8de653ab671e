"""The COLMAP database: prepared under a temporary name, then one transaction per pair (one writer)."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from pathlib import Path

import numpy as np

from .store import FeatureStore
from .views import View, require_pycolmap

__all__ = ["check_database_path", "create_database", "check_resumable", "write_pair", "interrupts_deferred",
           "read_database_matches"]


def check_database_path(database, resume: bool, overwrite: bool) -> Path:
    path = Path(database)
    if resume and overwrite:
        raise ValueError("resume and overwrite exclude each other")
    if path.is_dir():
        raise ValueError(f"database {str(path)!r} is a folder, expected a file path")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise ValueError(f"database folder {str(parent)!r} does not exist")
    if not os.access(parent, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise ValueError(f"database {str(path)!r} is not writable")
    if path.exists() and not (resume or overwrite):
        raise ValueError(f"database {str(path)!r} exists; pass --overwrite to replace it or --resume to continue it")
    if resume and not path.exists():
        raise ValueError(f"database {str(path)!r} does not exist; nothing to resume")
    return path


def create_database(path: Path, rec, views, store: FeatureStore) -> None:
    """Cameras, rigs, frames, images and keypoints, written under a temporary name, then renamed.

    Keypoints are read from ``store`` one image at a time.
    """
    pycolmap = require_pycolmap()
    tmp = path.with_name(f".{path.name}.{os.getpid()}.partial")
    tmp.unlink(missing_ok=True)
    try:
        db = pycolmap.Database.open(str(tmp))
        with pycolmap.DatabaseTransaction(db):
            for cam in rec.cameras.values():
                db.write_camera(cam, use_camera_id=True)
            for rig in rec.rigs.values():
                db.write_rig(rig, use_rig_id=True)
            for v in views:
                db.write_image(pycolmap.Image(name=v.name, camera_id=v.camera_id, image_id=v.image_id),
                               use_image_id=True)
            for frame in rec.frames.values():
                f = pycolmap.Frame(frame_id=frame.frame_id, rig_id=frame.rig_id)
                for d in frame.data_ids:
                    f.add_data_id(d)
                db.write_frame(f, use_frame_id=True)
            for v in views:
                db.write_keypoints(v.image_id, (store.keypoints(v) + 0.5).astype(np.float32))
        db.close()
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def check_resumable(path: Path, views, counts, pair_list) -> set:
    """The pairs of ``pair_list`` already complete in ``path``; refuses a database of other images or features."""
    pycolmap = require_pycolmap()
    db = pycolmap.Database.open(str(path))
    try:
        have = {im.image_id: im.name for im in db.read_all_images()}
        want = {v.image_id: v.name for v in views}
        if have != want:
            raise ValueError(f"database {str(path)!r} holds other images than the model; use --overwrite")
        for v, n in zip(views, counts):
            if db.num_keypoints_for_image(v.image_id) != n:
                raise ValueError(f"database {str(path)!r} holds other keypoints for {v.name!r} "
                                 "(other detector settings?); use --overwrite")
        # matches and two-view geometry are written in one transaction; a pair with matches but
        # no geometry can only come from an exception inside it (pycolmap commits on exit): redo it
        done = set()
        for i, j in pair_list:
            a, b = views[i].image_id, views[j].image_id
            if db.exists_two_view_geometry(a, b):
                done.add((i, j))
            elif db.exists_matches(a, b):
                db.delete_matches(a, b)
        return done
    finally:
        db.close()


def write_pair(db, v1: View, v2: View, matches: np.ndarray, inliers: np.ndarray) -> None:
    pycolmap = require_pycolmap()
    if v1.image_id > v2.image_id:  # COLMAP stores (smaller id, larger id)
        v1, v2, matches, inliers = v2, v1, matches[:, ::-1], inliers[:, ::-1]
    g = v1.geometry_to(v2)
    tvg = pycolmap.TwoViewGeometry()
    tvg.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
    tvg.E = g.essential_matrix
    tvg.F = g.fundamental_matrix
    tvg.cam2_from_cam1 = pycolmap.Rigid3d(pycolmap.Rotation3d(g.R), g.t)
    tvg.inlier_matches = np.ascontiguousarray(inliers, dtype=np.uint32)
    with interrupts_deferred(), pycolmap.DatabaseTransaction(db):
        db.write_matches(v1.image_id, v2.image_id, np.ascontiguousarray(matches, dtype=np.uint32))
        db.write_two_view_geometry(v1.image_id, v2.image_id, tvg)


@contextlib.contextmanager
def interrupts_deferred():
    """Hold SIGINT (Ctrl-C) until the block ends, then deliver it to the previous handler.

    pycolmap's transaction commits even when an exception leaves it, so a
    KeyboardInterrupt between two writes would commit half a pair.
    """
    if threading.current_thread() is not threading.main_thread() \
            or signal.getsignal(signal.SIGINT) in (signal.SIG_IGN, None):
        yield
        return
    caught = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught:
            signal.raise_signal(signal.SIGINT)


def read_database_matches(database) -> dict:
    """``{(name1, name2): (matches, inliers)}`` of a database, for comparing runs.

    Matches are ``(M, 2)`` uint32, keypoint indices of ``name1`` then
    ``name2``, with ``name1`` the image of smaller id, rows sorted. Pairs
    without any match are left out (COLMAP's reader skips them).
    """
    pycolmap = require_pycolmap()
    db = pycolmap.Database.open(str(database))
    try:
        names = {im.image_id: im.name for im in db.read_all_images()}
        out = {}
        ids, tvgs = db.read_two_view_geometries()
        for pid, tvg in zip(ids, tvgs):
            a, b = divmod(int(pid), 2147483647)  # COLMAP's pair id
            m = np.asarray(db.read_matches(a, b), dtype=np.uint32).reshape(-1, 2)
            inl = np.asarray(tvg.inlier_matches, dtype=np.uint32).reshape(-1, 2)
            out[(names[a], names[b])] = (m[np.lexsort(m.T[::-1])], inl[np.lexsort(inl.T[::-1])])
        return out
    finally:
        db.close()
