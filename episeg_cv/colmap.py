"""Posed collections in, a COLMAP database out: every pair matched on its epipolar segment.

COLMAP's "reconstruct from known poses" workflow is: extract features, match,
verify, then ``point_triangulator``. Its matching ignores the poses. Here the
poses drive the matching: :func:`match_model` reads a COLMAP model (or a
poses JSON), computes features once per image (cached on disk), matches
every pair with :func:`~episeg_cv.matching.match_descriptors` on the
segment, and writes a COLMAP database that ``colmap point_triangulator`` or
:func:`pycolmap.triangulate_points` uses unchanged (:func:`triangulate`).

Requires ``pycolmap`` (``pip install "episeg_cv[colmap]"``); Dask only for
``scheduler`` (``pip install "episeg_cv[dask]"``).

Conventions
-----------
- Poses are world-to-camera, ``X_cam = R @ X_world + t``, as in COLMAP's
  ``cam_from_world`` and :meth:`TwoViewGeometry.from_world_poses`.
- Keypoints written to the database use COLMAP's pixel convention: the
  centre of the top-left pixel is ``(0.5, 0.5)``. Everything else in
  episeg_cv has it at ``(0, 0)``; a poses JSON's ``K`` uses episeg_cv's
  (OpenCV's) convention.
- Distortion: see :mod:`episeg_cv.collection` (keypoints are mapped to the
  pinhole image with COLMAP's own camera model before the constraint).

Database layout
---------------
Cameras, rigs, frames and images come from the model with its ids (COLMAP
checks that they agree). Keypoints are the raw detections. ``matches`` holds
the guided matches, and ``two_view_geometries`` the pair's inliers (matches
consistent with both cameras' segments) with configuration ``CALIBRATED``,
the essential matrix and ``cam2_from_cam1`` from the known poses.

Data safety: an existing database is never replaced without
``overwrite=True``. A new database is prepared (cameras, images, keypoints)
under a temporary name and renamed into place; then each pair's matches and
two-view geometry are written in one transaction, so an interrupted run
leaves a usable database with whole pairs only, and ``resume=True`` skips
the pairs already there. Only the driver process writes.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import json
import multiprocessing
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .collection import (DETECTORS, FeatureStore, PairJob, View, depth_range_from_depths, exhaustive_pairs,
                         index_pairs, is_bounded, match_pair, neighbor_pairs, read_pairs)
from .candidates import check_constraint
from .matching import DEFAULT_RATIO, check_ratio
from ._validation import as_nonnegative

__all__ = ["load_model", "load_poses", "save_poses", "auto_depth_ranges", "match_model", "MatchReport",
           "triangulate", "read_database_matches", "save_collection", "EXHAUSTIVE_WARN"]

#: Above this many images, exhaustive pairing warns (pairs grow as n^2 / 2).
EXHAUSTIVE_WARN = 300
#: Seconds to wait for a Dask scheduler before giving up.
CONNECT_TIMEOUT = 10.0


def _pycolmap():
    try:
        import pycolmap
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError('episeg_cv.colmap needs pycolmap: pip install "episeg_cv[colmap]"') from e
    return pycolmap


# --------------------------------------------------------------------------------------
# Inputs: a COLMAP model or a poses JSON -> views
# --------------------------------------------------------------------------------------
def _views_from_reconstruction(rec) -> list[View]:
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
    pycolmap = _pycolmap()
    path = Path(model_dir)
    if not path.is_dir():
        raise ValueError(f"model folder {str(path)!r} does not exist")
    if not any((path / f"images.{ext}").is_file() for ext in ("bin", "txt")):
        raise ValueError(f"model folder {str(path)!r} holds no COLMAP model (images.bin or images.txt)")
    try:
        rec = pycolmap.Reconstruction(str(path))
    except Exception as e:  # pycolmap raises several types for a broken model
        raise ValueError(f"model folder {str(path)!r} cannot be read: {e}") from e
    views = _views_from_reconstruction(rec)
    if not views:
        raise ValueError(f"model {str(path)!r} has no registered images")
    return views, rec


def _camera_of(K, size, dist):
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
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"poses file {str(path)!r} cannot be read: {e}") from e
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
        name = str(item["name"])
        if name in names:
            raise ValueError(f"{where}: image {name!r} is listed twice")
        names.add(name)
        try:
            K = np.asarray(item["K"], dtype=np.float64)
            size = (int(item["width"]), int(item["height"]))
            model, params = _camera_of(K, size, item.get("dist", ()))
            key = (model, params, size)
            cameras.setdefault(key, len(cameras) + 1)
            views.append(View(name, k + 1, cameras[key], K, item["R"], item["t"], size, model, params,
                              item.get("depth_range", (0.0, float("inf")))))
        except (TypeError, ValueError) as e:
            raise ValueError(f"{where} ({name!r}): {e}") from e
    return views


def save_poses(path, views) -> None:
    """Write ``views`` as a poses JSON (:func:`load_poses` reads it back; distortion is not written)."""
    items = [{"name": v.name, "width": v.image_size[0], "height": v.image_size[1], "K": v.K.tolist(),
              "R": v.R.tolist(), "t": v.t.tolist(),
              **({"depth_range": list(v.depth_range)} if is_bounded(v.depth_range) else {})} for v in views]
    Path(path).write_text(json.dumps({"images": items}, indent=1), encoding="utf-8")


def _reconstruction_from_views(views):
    """A pycolmap.Reconstruction with trivial rigs and frames for ``views`` (no points)."""
    pycolmap = _pycolmap()
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


# --------------------------------------------------------------------------------------
# Running jobs: in-process, local processes, or a Dask cluster
# --------------------------------------------------------------------------------------
_WORKER_LIMITED = False


def _single_thread():
    """One thread per worker process, for OpenCV and for BLAS (idle BLAS threads spin and steal the core).

    Without it, two workers on two cores ran slower than one process.
    """
    global _WORKER_LIMITED
    if not _WORKER_LIMITED:
        from threadpoolctl import threadpool_limits

        cv2.setNumThreads(1)
        threadpool_limits(1)
        _WORKER_LIMITED = True


def _run_in_worker(fn, item):
    _single_thread()
    return fn(item)


class _Runner:
    """Run ``fn`` over items with at most ``window`` in flight; yields results as they finish.

    ``chunk`` is the number of pairs the caller should put in one task for this runner.
    """

    def __init__(self, workers: int = 1, scheduler: str | None = None):
        self._pool = self._client = self._cluster = None
        if scheduler is not None:
            try:
                import distributed
            except ImportError as e:
                raise ImportError('scheduler needs Dask: pip install "episeg_cv[dask]"') from e
            if scheduler.startswith("local:"):
                n = _positive_int(scheduler[6:], "scheduler local:N")
                self._cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                                         dashboard_address=None)
                self._client = distributed.Client(self._cluster)
                self.describe = f"a local Dask cluster of {n} workers"
            else:
                try:
                    self._client = distributed.Client(scheduler, timeout=f"{CONNECT_TIMEOUT}s")
                except (OSError, TimeoutError) as e:
                    raise ConnectionError(f"cannot reach the Dask scheduler at {scheduler!r}: {e}") from e
                self.describe = f"the Dask cluster at {scheduler}"
            self.window = 4 * max(1, len(self._client.scheduler_info().get("workers", {})) or 1)
            self.chunk = 8
        elif workers > 1:
            self._pool = cf.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                                initializer=_single_thread)
            self.describe = f"{workers} local processes"
            self.window = 4 * workers
            self.chunk = 4
        else:
            self.describe = "this process"
            self.window = self.chunk = 1

    def imap(self, fn, items):
        items = iter(items)
        if self._client is None and self._pool is None:
            yield from map(fn, items)
            return
        if self._client is not None:
            import distributed

            submit = lambda it: self._client.submit(_run_in_worker, fn, it, pure=False)  # noqa: E731
            pending = [submit(it) for _, it in zip(range(self.window), items)]
            done = distributed.as_completed(pending)
            for fut in done:
                yield fut.result()
                nxt = next(items, None)
                if nxt is not None:
                    done.add(submit(nxt))
            return
        pending = {self._pool.submit(fn, it) for _, it in zip(range(self.window), items)}
        while pending:
            finished, pending = cf.wait(pending, return_when=cf.FIRST_COMPLETED)
            for fut in finished:
                yield fut.result()
                nxt = next(items, None)
                if nxt is not None:
                    pending.add(self._pool.submit(fn, nxt))

    def close(self):
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        if self._client is not None:
            self._client.close()
        if self._cluster is not None:
            self._cluster.close()


def _positive_int(value, name) -> int:
    ok = isinstance(value, (int, np.integer)) or (isinstance(value, str) and value.strip().isdigit())
    if isinstance(value, bool) or not ok or int(value) < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


# --------------------------------------------------------------------------------------
# The database (only the driver writes)
# --------------------------------------------------------------------------------------
def _check_database_path(database, resume: bool, overwrite: bool) -> Path:
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


def _create_database(path: Path, rec, views, store: FeatureStore) -> None:
    """Cameras, rigs, frames, images and keypoints, written under a temporary name, then renamed.

    Keypoints are read from ``store`` one image at a time.
    """
    pycolmap = _pycolmap()
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


def _check_resumable(path: Path, views, counts, pair_list) -> set:
    """The pairs of ``pair_list`` already complete in ``path``; refuses a database of other images or features."""
    pycolmap = _pycolmap()
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


def _write_pair(db, v1: View, v2: View, matches: np.ndarray, inliers: np.ndarray) -> None:
    pycolmap = _pycolmap()
    if v1.image_id > v2.image_id:  # COLMAP stores (smaller id, larger id)
        v1, v2, matches, inliers = v2, v1, matches[:, ::-1], inliers[:, ::-1]
    g = v1.geometry_to(v2)
    tvg = pycolmap.TwoViewGeometry()
    tvg.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
    tvg.E = g.essential_matrix
    tvg.F = g.fundamental_matrix
    tvg.cam2_from_cam1 = pycolmap.Rigid3d(pycolmap.Rotation3d(g.R), g.t)
    tvg.inlier_matches = np.ascontiguousarray(inliers, dtype=np.uint32)
    with _interrupts_deferred(), pycolmap.DatabaseTransaction(db):
        db.write_matches(v1.image_id, v2.image_id, np.ascontiguousarray(matches, dtype=np.uint32))
        db.write_two_view_geometry(v1.image_id, v2.image_id, tvg)


@contextlib.contextmanager
def _interrupts_deferred():
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
    pycolmap = _pycolmap()
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


# --------------------------------------------------------------------------------------
# The driver
# --------------------------------------------------------------------------------------
@dataclass
class MatchReport:
    """What :func:`match_model` did.

    Attributes
    ----------
    database : Path
    n_images, n_pairs : int
        Images in the collection, pairs to match.
    n_skipped : int
        Pairs already in the database (``resume``).
    n_pairs_done : int
        Pairs matched and written in this run.
    n_matches, n_inliers : int
        Written in this run.
    seconds_features, seconds_matching : float
        Wall time of feature extraction (including cache hits) and matching with writing.
    pairs_per_second : float
    runner : str
        Where the jobs ran.
    depth_ranges : dict
        ``{name: (zmin, zmax)}`` used for each image.
    search_length : dict
        Mean search length per sampled query in image 2, pixels (up to 256
        queries per pair): ``"line"`` (the whole epipolar line in the image),
        ``"segment"`` (the segment with depths in ``(0, inf)``) and
        ``"segment_in_depth_range"``. Empty when no pair was matched.
    """

    database: Path
    n_images: int
    n_pairs: int
    n_skipped: int = 0
    n_pairs_done: int = 0
    n_matches: int = 0
    n_inliers: int = 0
    seconds_features: float = 0.0
    seconds_matching: float = 0.0
    pairs_per_second: float = 0.0
    runner: str = "this process"
    depth_ranges: dict = field(default_factory=dict)
    search_length: dict = field(default_factory=dict)

    def summary(self) -> str:
        lines = [f"database: {self.database}",
                 f"images: {self.n_images}, pairs: {self.n_pairs} ({self.n_skipped} already written, skipped)",
                 f"matches written: {self.n_matches}, inliers: {self.n_inliers}",
                 f"features: {self.seconds_features:.1f} s; matching: {self.seconds_matching:.1f} s, "
                 f"{self.pairs_per_second:.1f} pairs/s on {self.runner}"]
        bounded = sum(is_bounded(z) for z in self.depth_ranges.values())
        lines.append(f"depth ranges: {bounded} of {self.n_images} images bounded")
        L = self.search_length
        if L and L["line"] > 0:
            lines.append(f"search length per query: line {L['line']:.0f} px, segment {L['segment']:.0f} px "
                         f"(-{100 * (1 - L['segment'] / L['line']):.0f} %), segment in depth range "
                         f"{L['segment_in_depth_range']:.0f} px (-{100 * (1 - L['segment_in_depth_range'] / L['line']):.0f} %)")
        return "\n".join(lines)


def _load_views(model):
    """``(views, reconstruction or None, source)`` from a model folder, a poses JSON or a list of View."""
    if isinstance(model, (list, tuple)):
        if not model or not all(isinstance(v, View) for v in model):
            raise ValueError("model must be a non-empty list of View, a model folder or a poses JSON")
        return list(model), None
    path = Path(model)
    if path.is_file():
        return load_poses(path), None
    return load_model(path)


def _resolve_pairs(views, pairs, neighbors, warn):
    names = [v.name for v in views]
    if pairs is not None and neighbors is not None:
        raise ValueError("give pairs or neighbors, not both")
    if isinstance(pairs, (str, os.PathLike)):
        return read_pairs(pairs, names)
    if pairs is not None:
        return index_pairs([(f"pairs[{k}]", a, b) for k, (a, b) in enumerate(pairs)], names)
    if neighbors is not None:
        return neighbor_pairs(views, neighbors)
    if len(views) > EXHAUSTIVE_WARN:
        warn(f"warning: exhaustive matching of {len(views)} images is {len(views) * (len(views) - 1) // 2} pairs; "
             "consider --neighbors K or --pairs FILE")
    return exhaustive_pairs(len(views))


def _resolve_depth(views, rec, depth_range, warn):
    if depth_range is None or (isinstance(depth_range, str) and depth_range == "none"):
        return [v.with_depth_range((0.0, float("inf"))) for v in views]
    if isinstance(depth_range, str):
        if depth_range != "auto":
            raise ValueError(f"depth_range must be 'auto', 'none', None or (zmin, zmax), got {depth_range!r}")
        if rec is None:
            if not any(is_bounded(v.depth_range) for v in views):
                warn("warning: depth_range 'auto' needs a COLMAP model with 3D points (or depth_range in the "
                     "poses JSON); using (0, inf)")
            return views
        out = auto_depth_ranges(views, rec)
        unseen = [v.name for v in out if not is_bounded(v.depth_range)]
        if unseen:
            warn(f"warning: {len(unseen)} image(s) observe too few 3D points for a depth range, using (0, inf): "
                 + ", ".join(unseen[:5]) + (" ..." if len(unseen) > 5 else ""))
        return out
    return [v.with_depth_range(depth_range) for v in views]


def match_model(model, image_dir, database, *, pairs=None, neighbors=None, detector: str = "sift",
                max_features: int = 8192, constraint: str = "segment", depth_range="auto", tol: float = 2.0,
                ratio: float = DEFAULT_RATIO, workers: int = 1, scheduler: str | None = None, cache_dir=None, resume: bool = False,
                overwrite: bool = False, progress=None, log=None) -> MatchReport:
    """Match every pair of a posed collection on its epipolar segments; write a COLMAP database.

    Parameters
    ----------
    model : str, Path or list of View
        A COLMAP sparse model folder (binary or text), a poses JSON
        (:func:`load_poses`), or views.
    image_dir : str or Path
        Folder of the images, named as in the model.
    database : str or Path
        The COLMAP database to write.
    pairs : str, Path or sequence of (str, str), optional
        A pairs file (one ``name1 name2`` per line) or name pairs.
    neighbors : int, optional
        Each image's ``neighbors`` best partners by view overlap
        (:func:`~episeg_cv.collection.neighbor_pairs`). Default (neither
        ``pairs`` nor ``neighbors``): every pair, with a warning above
        :data:`EXHAUSTIVE_WARN` images.
    detector : {"sift", "orb", "akaze"}, optional
    max_features : int, optional
        Strongest keypoints kept per image.
    constraint : {"segment", "line"}, optional
    depth_range : "auto", "none", None or (zmin, zmax), optional
        ``"auto"``: each image's range from the model's 3D points it sees
        (:func:`auto_depth_ranges`), or the poses JSON's ``depth_range``;
        ``(0, inf)`` where there is none.
    tol : float, optional
        Pixel tolerance to the segment, in the pinhole image.
    ratio : float in (0, 1], optional
        The ratio test of :func:`~episeg_cv.matching.match_descriptors`
        (with its mutual check and padding).
    workers : int, optional
        Local processes for features and pairs (1: in this process).
    scheduler : str, optional
        A Dask scheduler address, or ``"local:N"`` for a new ``LocalCluster``
        of N workers. The feature cache must be on a filesystem the workers
        share, and episeg_cv installed on them. Local processes are spawned:
        call from under ``if __name__ == "__main__":`` in a script.
    cache_dir : str or Path, optional
        Feature cache; default ``<database>.features`` next to the database.
    resume, overwrite : bool, optional
        Continue an existing database (skipping the pairs it holds), or replace it.
    progress : callable, optional
        Called as ``progress(stage, done, total)`` after each image
        (``stage="features"``) and each pair (``stage="pairs"``).
    log : callable, optional
        Receives warnings (default: print to stderr).

    Returns
    -------
    MatchReport

    Raises
    ------
    ValueError
        Bad input: no registered images, a missing image, an unknown image in
        ``pairs`` (with its line), an existing database without
        ``overwrite``/``resume``, an unwritable path, a bad option.
    ConnectionError
        The Dask scheduler cannot be reached.
    """
    pycolmap = _pycolmap()  # fail before any work when it is missing
    warn = log or (lambda msg: print(msg, file=sys.stderr))
    constraint = check_constraint(constraint)
    if constraint == "none":
        raise ValueError("constraint must be 'segment' or 'line' here ('none' has no geometry to use)")
    if detector not in DETECTORS:
        raise ValueError(f"detector must be one of {tuple(DETECTORS)}, got {detector!r}")
    tol = as_nonnegative(tol, "tol")
    ratio = check_ratio(ratio, "ratio")
    workers = _positive_int(workers, "workers")
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise ValueError(f"image folder {str(image_dir)!r} does not exist")

    views, rec = _load_views(model)
    missing = [v.name for v in views if not (image_dir / v.name).is_file()]
    if missing:
        raise ValueError(f"image {missing[0]!r} of the model is missing in {str(image_dir)!r}"
                         + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
    views = _resolve_depth(views, rec, depth_range, warn)
    pair_list = _resolve_pairs(views, pairs, neighbors, warn)
    path = _check_database_path(database, resume, overwrite)
    store = FeatureStore(Path(cache_dir) if cache_dir is not None else path.with_name(path.name + ".features"),
                         image_dir, detector, max_features)
    if rec is None:
        rec = _reconstruction_from_views(views)
    report = MatchReport(path, len(views), len(pair_list),
                         depth_ranges={v.name: v.depth_range for v in views})

    runner = _Runner(workers, scheduler)
    report.runner = runner.describe
    try:
        t0 = time.perf_counter()
        tick = progress or (lambda stage, done, total: None)
        counts = {}
        for name, n in runner.imap(_ensure_features, [(store, v) for v in views]):
            counts[name] = n
            tick("features", len(counts), len(views))
        report.seconds_features = time.perf_counter() - t0
        counts = [counts[v.name] for v in views]

        if resume:
            done = _check_resumable(path, views, counts, pair_list)
        else:  # a new database, or (overwrite) one replaced atomically by the new one
            _create_database(path, rec, views, store)
            done = set()
        todo = [p for p in pair_list if p not in done]
        report.n_skipped = len(pair_list) - len(todo)

        jobs = [PairJob(k, views[i], views[j], store, constraint, tol, ratio) for k, (i, j) in enumerate(todo)]
        # a few consecutive pairs per task: less scheduling and pickling, and they share images
        chunks = (jobs[k:k + runner.chunk] for k in range(0, len(jobs), runner.chunk))
        t0 = time.perf_counter()
        lengths, samples = np.zeros(3), 0
        db = pycolmap.Database.open(str(path))
        try:
            for res in (r for chunk in runner.imap(_match_chunk, chunks) for r in chunk):
                i, j = todo[res.index]
                _write_pair(db, views[i], views[j], res.matches, res.inliers)
                report.n_matches += len(res.matches)
                report.n_inliers += len(res.inliers)
                lengths += res.lengths
                samples += res.samples
                report.n_pairs_done += 1
                tick("pairs", report.n_pairs_done, len(todo))
        finally:
            db.close()
        report.seconds_matching = time.perf_counter() - t0
        report.pairs_per_second = report.n_pairs_done / report.seconds_matching if report.seconds_matching > 0 else 0.0
        if samples:
            report.search_length = dict(zip(("line", "segment", "segment_in_depth_range"), lengths / samples))
    finally:
        runner.close()
    return report


def _match_chunk(jobs):
    return [match_pair(job) for job in jobs]


def _ensure_features(item):
    store, view = item
    return view.name, store.ensure(view)


# --------------------------------------------------------------------------------------
# Triangulation
# --------------------------------------------------------------------------------------
def triangulate(database, model, image_dir, output_dir, options=None):
    """Run ``pycolmap.triangulate_points`` on a database from :func:`match_model`.

    Parameters
    ----------
    database : str or Path
    model : str, Path or list of View
        The same model given to :func:`match_model` (its 3D points are cleared).
    image_dir, output_dir : str or Path
        ``output_dir`` is created; the triangulated model is written there.
    options : pycolmap.IncrementalPipelineOptions, optional
        COLMAP's defaults otherwise. Note that they ignore two-view tracks
        (``triangulation.ignore_two_view_tracks``): a point needs three views.

    Returns
    -------
    pycolmap.Reconstruction
    """
    pycolmap = _pycolmap()
    views, rec = _load_views(model)
    if rec is None:
        rec = _reconstruction_from_views(views)
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    if options is None:
        options = pycolmap.IncrementalPipelineOptions()
    return pycolmap.triangulate_points(rec, str(database), str(image_dir), str(out), options=options)


# --------------------------------------------------------------------------------------
# A synthetic collection on disk (tests, benchmarks, trying the CLI)
# --------------------------------------------------------------------------------------
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
    pycolmap = _pycolmap()
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
    rec = _reconstruction_from_views(views)
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
