"""The COLMAP database: prepared under a temporary name, then one transaction per pair (one writer).

Beside COLMAP's own tables, the database holds a small table ``episeg_run``
(COLMAP ignores it): the settings of the run that wrote it and the content
hash of every image. ``resume`` compares them with the new run and refuses a
database written with other settings or from other images, saying what
changed, so that one database never mixes two runs. While a run writes a
database it holds an exclusive lock on it (``flock``): a second run on the
same database is refused.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sqlite3
from pathlib import Path

import numpy as np

from ..geometry import _camera_inverse, _skew
from ..interrupts import interrupts_deferred
from .store import FeatureStore
from .views import View, require_pycolmap

try:
    import fcntl
except ImportError:  # pragma: no cover - not on Windows
    fcntl = None

__all__ = ["check_database_path", "create_database", "check_resumable", "write_pair", "write_pairs",
           "read_database_matches", "database_lock", "pair_unchanged", "RUN_TABLE", "read_run_record",
           "write_run_record", "remove_stale_partials"]

#: The table holding the run record (settings and image hashes).
RUN_TABLE = "episeg_run"
_SQLITE_MAGIC = b"SQLite format 3\x00"
_SIDE_FILES = ("", "-wal", "-shm", "-journal")


def check_database_path(database, resume: bool, overwrite: bool) -> Path:
    """The database path, checked before any work: a file path in a writable folder, and
    existing exactly when ``resume`` (or ``overwrite``) says so."""
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
    if resume:
        with open(path, "rb") as f:
            if f.read(len(_SQLITE_MAGIC)) != _SQLITE_MAGIC:
                raise ValueError(f"database {str(path)!r} is not a COLMAP database (not an SQLite file)")
    return path


@contextlib.contextmanager
def database_lock(path: Path):
    """Hold an exclusive lock on the database file ``path`` for the block; ``ValueError`` when another
    run holds it. (Nothing to lock where ``fcntl`` does not exist.)"""
    if fcntl is None:
        yield
        return
    fd = os.open(path, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ValueError(f"database {str(path)!r} is being written by another run; wait for it to end") from None
        yield
    finally:
        os.close(fd)


def _partial_name(path: Path, pid: int) -> Path:
    return path.with_name(f".{path.name}.{pid}.partial")


def _remove_with_side_files(path: Path) -> None:
    for suffix in _SIDE_FILES:
        Path(f"{path}{suffix}").unlink(missing_ok=True)


def remove_stale_partials(path: Path) -> list:
    """Remove what runs killed while preparing ``path`` left behind (``.NAME.PID.partial`` and its
    ``-wal``/``-shm``/``-journal`` files, or a partial folder, when process PID no longer exists); the
    paths removed."""
    removed = []
    for tmp in path.parent.glob(f".{path.name}.*.partial"):
        pid = tmp.name[len(path.name) + 2:-len(".partial")]
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)
            continue  # that run is still alive
        except ProcessLookupError:
            pass
        except PermissionError:
            continue  # alive, another user's
        if tmp.is_dir():  # a triangulation's partial folder
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            _remove_with_side_files(tmp)
        removed.append(tmp)
    return removed


def write_run_record(path: Path, record: dict) -> None:
    """Write (or replace) the run record of database ``path``."""
    con = sqlite3.connect(path)
    try:
        with con:
            con.execute(f"CREATE TABLE IF NOT EXISTS {RUN_TABLE} (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
            con.executemany(f"INSERT OR REPLACE INTO {RUN_TABLE} VALUES (?, ?)",
                            [(k, json.dumps(v, sort_keys=True)) for k, v in record.items()])
    finally:
        con.close()


def read_run_record(path) -> dict | None:
    """The run record of a database (``{"settings": ..., "images": {name: sha256}}``), or None."""
    con = sqlite3.connect(path)  # (read-write: a read-only connection leaves -wal/-shm files behind)
    try:
        rows = con.execute(f"SELECT key, value FROM {RUN_TABLE}").fetchall()
    except sqlite3.OperationalError as e:
        if "no such table" in str(e):
            return None
        raise ValueError(f"database {str(path)!r} cannot be read (sqlite3: {e})") from None
    except sqlite3.DatabaseError as e:
        raise ValueError(f"database {str(path)!r} is damaged or not an SQLite database (sqlite3: {e})") from None
    finally:
        con.close()
    return {k: json.loads(v) for k, v in rows}


@contextlib.contextmanager
def create_database(path: Path, rec, views, store: FeatureStore, record: dict, overwrite: bool = False):
    """Cameras, rigs, frames, images, keypoints and the run record, written under a temporary name,
    then put into place (so a killed run never leaves a half-written database at ``path``); the
    block runs with the new database locked (:func:`database_lock`), from before it is visible.

    A new database (not ``overwrite``) is put into place with a hard link, which fails if another
    run created ``path`` meanwhile: two runs never write one database. Keypoints are read from
    ``store`` one image at a time.
    """
    pycolmap = require_pycolmap()
    remove_stale_partials(path)
    tmp = _partial_name(path, os.getpid())
    _remove_with_side_files(tmp)
    tmp.touch()
    try:
        with database_lock(tmp):  # the lock follows the file to its final name
            _fill(pycolmap, tmp, rec, views, store)
            write_run_record(tmp, record)
            _put_in_place(tmp, path, overwrite)
            yield
    finally:
        _remove_with_side_files(tmp)


def _put_in_place(tmp: Path, path: Path, overwrite: bool) -> None:
    if overwrite:
        os.replace(tmp, path)
        return
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise ValueError(f"database {str(path)!r} was created by another run meanwhile; nothing was replaced") \
            from None
    except OSError:  # no hard links on this filesystem: the check and the rename are not one step
        if path.exists():
            raise ValueError(f"database {str(path)!r} was created by another run meanwhile") from None
        os.replace(tmp, path)
        return
    tmp.unlink()


def _fill(pycolmap, tmp: Path, rec, views, store) -> None:
    db = pycolmap.Database.open(str(tmp))
    try:
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
    finally:
        db.close()


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _differences(stored: dict, wanted: dict) -> list:
    a, b = _flat(stored), _flat(wanted)
    return [f"{key} was {a.get(key)!r}, now {b.get(key)!r}" for key in sorted(set(a) | set(b)) if a.get(key) != b.get(key)]


def check_resumable(path: Path, views, record: dict, pair_list) -> set:
    """The pairs of ``pair_list`` already complete in ``path``.

    Refuses (``ValueError``, one line saying what changed) a database without a run record, or
    one written with other settings or from other image contents.
    """
    stored = read_run_record(path)
    if stored is None or "settings" not in stored:
        raise ValueError(f"database {str(path)!r} was not written by episeg colmap (no run record); "
                         "pass --overwrite to replace it")
    have, want = stored.get("images", {}), record["images"]
    if set(have) != set(want):
        extra = sorted(set(have) ^ set(want))
        raise ValueError(f"database {str(path)!r} holds other images than the model (e.g. {extra[0]!r}); "
                         "pass --overwrite to start again")
    changed = _differences(stored["settings"], record["settings"])
    if changed:
        raise ValueError(f"database {str(path)!r} was written with other settings ({'; '.join(changed[:3])}); "
                         "rerun with the same settings, or pass --overwrite to start again")
    modified = sorted(n for n in want if have[n] != want[n])
    if modified:
        raise ValueError(f"image {modified[0]!r} (or its features) changed since database {str(path)!r} was written"
                         + (f" (and {len(modified) - 1} more)" if len(modified) > 1 else "")
                         + "; its matches would no longer fit: pass --overwrite to start again")
    pycolmap = require_pycolmap()
    db = pycolmap.Database.open(str(path))
    try:
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


def _oriented(v1: View, v2: View, matches: np.ndarray, inliers: np.ndarray):
    if v1.image_id > v2.image_id:  # COLMAP stores (smaller id, larger id)
        return v2, v1, matches[:, ::-1], inliers[:, ::-1]
    return v1, v2, matches, inliers


def _sorted_rows(a) -> np.ndarray:
    a = np.asarray(a, dtype=np.uint32).reshape(-1, 2)
    return a[np.lexsort(a.T[::-1])]


def pair_unchanged(db, v1: View, v2: View, matches: np.ndarray, inliers: np.ndarray) -> bool:
    """Whether the open database ``db`` holds exactly these matches and inliers for the pair."""
    v1, v2, matches, inliers = _oriented(v1, v2, matches, inliers)
    a, b = v1.image_id, v2.image_id
    if not (db.exists_matches(a, b) and db.exists_two_view_geometry(a, b)):
        return False
    have_m = _sorted_rows(db.read_matches(a, b))
    have_i = _sorted_rows(db.read_two_view_geometry(a, b).inlier_matches)
    return np.array_equal(have_m, _sorted_rows(matches)) and np.array_equal(have_i, _sorted_rows(inliers))


#: The inverse of episeg_cv's pixels -> COLMAP's (``x_colmap = x + 0.5``), for moving ``F`` between them.
_TO_COLMAP_INV = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])


def write_pair(db, v1: View, v2: View, matches: np.ndarray, inliers: np.ndarray, replace: bool = False) -> None:
    """Write one pair's matches and CALIBRATED two-view geometry in one transaction (``replace``:
    delete what the database holds for the pair first, in the same transaction)."""
    write_pairs(db, [(v1, v2, matches, inliers, replace)])


def write_pairs(db, items) -> None:
    """:func:`write_pair` of every ``(v1, v2, matches, inliers, replace)`` of ``items``, in one transaction:
    an interrupted run keeps whole pairs only, and a transaction costs about 70 us (half of writing a
    pair of 250 keypoints, dinoSparseRing), so the track consensus writes its pairs in blocks."""
    pycolmap = require_pycolmap()
    calibrated = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
    normalisers = {}  # image id -> K^-1 from COLMAP's pixels, once per image of the block

    def normaliser(v):
        if v.image_id not in normalisers:
            normalisers[v.image_id] = _camera_inverse(v.K) @ _TO_COLMAP_INV
        return normalisers[v.image_id]

    rows = []
    for v1, v2, matches, inliers, replace in items:
        v1, v2, matches, inliers = _oriented(v1, v2, matches, inliers)
        n1, n2 = normaliser(v1), normaliser(v2)
        R, t = v1.pose_to(v2)
        E = _skew(t) @ R  # as TwoViewGeometry.essential_matrix, without making the geometry
        tvg = pycolmap.TwoViewGeometry()
        tvg.config = calibrated
        tvg.E = E
        tvg.F = n2.T @ E @ n1  # F = K2^-T E K1^-1, in COLMAP's pixels (centre at +0.5)
        tvg.cam2_from_cam1 = pycolmap.Rigid3d(pycolmap.Rotation3d(R), t)
        tvg.inlier_matches = np.ascontiguousarray(inliers, dtype=np.uint32)
        rows.append((v1.image_id, v2.image_id, np.ascontiguousarray(matches, dtype=np.uint32), tvg, replace))
    with interrupts_deferred(), pycolmap.DatabaseTransaction(db):
        for a, b, matches, tvg, replace in rows:
            if replace:
                if db.exists_matches(a, b):
                    db.delete_matches(a, b)
                if db.exists_two_view_geometry(a, b):
                    db.delete_two_view_geometry(a, b)
            db.write_matches(a, b, matches)
            db.write_two_view_geometry(a, b, tvg)


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
