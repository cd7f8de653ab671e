"""The driver: a posed collection in, a COLMAP database out, every pair matched on its segments.

COLMAP's "reconstruct from known poses" workflow is: extract features, match,
verify, then ``point_triangulator``. Its matching ignores the poses. Here the
poses drive the matching: :func:`match_model` reads a COLMAP model (or a
poses JSON), computes features once per image (:class:`.store.FeatureStore`),
matches every pair on its segments (:func:`.job.match_pair`, run by a
:class:`.runner.Runner`), and writes a COLMAP database (:mod:`.database`)
that ``colmap point_triangulator`` or :func:`pycolmap.triangulate_points`
uses unchanged (:func:`triangulate`).
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._validation import as_positive_int
from ..features import PRESETS, FeatureConfig
from ..matching.config import AcceptRule, SearchConfig, resolve
from .. import __version__
from .database import check_database_path, check_resumable, create_database, database_lock, write_pair
from ..interrupts import terminate_as_interrupt
from .job import PairJob, match_pair
from .model import auto_depth_ranges, load_model, reconstruction_from_views
from .pairs import exhaustive_pairs, index_pairs, neighbor_pairs, read_pairs
from .poses import load_poses
from .runner import Runner
from .store import FeatureStore
from .views import View, is_bounded, require_pycolmap

__all__ = ["MatchReport", "match_model", "triangulate", "load_views", "check_triangulation_folder",
           "EXHAUSTIVE_WARN"]

#: Above this many images, exhaustive pairing warns (pairs grow as n^2 / 2).
EXHAUSTIVE_WARN = 300


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


def load_views(model):
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


def match_model(model, image_dir, database, *, pairs=None, neighbors=None,
                features: FeatureConfig | str = "colmap", depth_range="auto", search: SearchConfig | None = None,
                rule: AcceptRule | None = None, workers: int = 1, scheduler: str | None = None, cache_dir=None,
                resume: bool = False, overwrite: bool = False, progress=None, log=None, **options) -> MatchReport:
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
        (:func:`~episeg_cv.colmap.neighbor_pairs`). Default (neither
        ``pairs`` nor ``neighbors``): every pair, with a warning above
        :data:`EXHAUSTIVE_WARN` images.
    features : FeatureConfig or str, optional
        How features are detected: a :class:`~episeg_cv.features.FeatureConfig`
        or the name of a preset of :data:`episeg_cv.features.PRESETS` (default
        ``"colmap"``: SIFT with COLMAP's threshold and RootSIFT, 8192 per image).
    depth_range : "auto", "none", None or (zmin, zmax), optional
        ``"auto"``: each image's range from the model's 3D points it sees
        (:func:`~episeg_cv.colmap.auto_depth_ranges`), or the poses JSON's
        ``depth_range``; ``(0, inf)`` where there is none.
    search : SearchConfig, optional
        ``constraint`` (``"segment"`` or ``"line"``) and ``tol`` (pixels, in
        the pinhole image). Its ``depth_range`` must be left at ``(0, inf)``:
        the collection's come from ``depth_range``, one per image.
    rule : AcceptRule, optional
        The acceptance rule of each pair (see :func:`~episeg_cv.match_descriptors`).
    **options
        Fields of ``search`` or ``rule`` as keywords (``tol=4``, ``ratio=0.8``).
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
    require_pycolmap()  # fail before any work when it is missing
    warn = log or (lambda msg: print(msg, file=sys.stderr))
    search, rule = resolve(search, rule, options)
    if search.constraint == "none":
        raise ValueError("constraint must be 'segment' or 'line' here ('none' has no geometry to use)")
    if search.bounded:
        raise ValueError("search.depth_range must be (0, inf) for a collection; give depth_range= instead")
    if search.auto is not None:
        raise ValueError("tol='auto' is not supported for collections (yet): give a number of pixels")
    features = _feature_config(features)
    workers = as_positive_int(workers, "workers")
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise ValueError(f"image folder {str(image_dir)!r} does not exist")

    views, rec = load_views(model)
    if len(views) < 2:
        raise ValueError(f"the collection has {len(views)} image; matching needs at least two")
    missing = [v.name for v in views if not (image_dir / v.name).is_file()]
    if missing:
        raise ValueError(f"image {missing[0]!r} of the model is missing in {str(image_dir)!r}"
                         + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
    views = _resolve_depth(views, rec, depth_range, warn)
    pair_list = _resolve_pairs(views, pairs, neighbors, warn)
    if not pair_list:
        raise ValueError("no pair to match: the pairs file lists none" if pairs is not None else
                         "no pair to match: no two images overlap")
    path = check_database_path(database, resume, overwrite)
    cache = Path(cache_dir) if cache_dir is not None else path.with_name(path.name + ".features")
    if cache.exists() and not cache.is_dir():
        raise ValueError(f"feature cache {str(cache)!r} is a file, expected a folder")
    store = FeatureStore(cache, image_dir, features)
    if rec is None:
        rec = reconstruction_from_views(views)
    report = MatchReport(path, len(views), len(pair_list),
                         depth_ranges={v.name: v.depth_range for v in views})

    settings = {"search": {"tol": search.tol, "constraint": search.constraint}, "rule": dataclasses.asdict(rule),
                "features": dataclasses.asdict(store.features),
                "depth_ranges": {v.name: [v.depth_range[0], str(v.depth_range[1])] for v in views}}
    with terminate_as_interrupt():
        runner = Runner(workers, scheduler)
        report.runner = runner.describe
        try:
            _run(runner, path, rec, views, store, pair_list, settings, search, rule, resume, report, progress)
        finally:
            runner.close()
    return report


def _run(runner, path, rec, views, store, pair_list, settings, search, rule, resume, report, progress):
    """Features, then the database (new or resumed), then every pair, written as it comes back."""
    pycolmap = require_pycolmap()
    t0 = time.perf_counter()
    tick = progress or (lambda stage, done, total: None)
    digests = {}
    for name, (n, digest) in runner.imap(_ensure_features, [(store, v) for v in views]):
        digests[name] = digest
        tick("features", len(digests), len(views))
    report.seconds_features = time.perf_counter() - t0
    record = {"settings": settings, "images": digests, "episeg_cv": __version__}

    if not resume:  # a new database, or (overwrite) one replaced atomically by the new one
        create_database(path, rec, views, store, record)
    with database_lock(path):
        done = check_resumable(path, views, record, pair_list) if resume else set()
        todo = [p for p in pair_list if p not in done]
        report.n_skipped = len(pair_list) - len(todo)
        jobs = [PairJob(k, views[i], views[j], store, search, rule) for k, (i, j) in enumerate(todo)]
        # a few consecutive pairs per task: less scheduling and pickling, and they share images
        chunks = (jobs[k:k + runner.chunk] for k in range(0, len(jobs), runner.chunk))
        t0 = time.perf_counter()
        lengths, samples = np.zeros(3), 0
        db = pycolmap.Database.open(str(path))
        try:
            for res in (r for chunk in runner.imap(_match_chunk, chunks) for r in chunk):
                i, j = todo[res.index]
                write_pair(db, views[i], views[j], res.matches, res.inliers)
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


def _feature_config(features) -> FeatureConfig:
    if isinstance(features, str):
        if features not in PRESETS:
            raise ValueError(f"features must be a FeatureConfig or one of {tuple(PRESETS)}, got {features!r}")
        return PRESETS[features]
    if not isinstance(features, FeatureConfig):
        raise TypeError(f"features must be a FeatureConfig or a preset name, got {type(features).__name__}")
    return features


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
        ``output_dir`` is created; the triangulated model is written there (into a temporary
        folder first, then moved file by file, so an interrupted run leaves no half-written model).
        It may not be the input model's folder.
    options : pycolmap.IncrementalPipelineOptions, optional
        COLMAP's defaults otherwise. Note that they ignore two-view tracks
        (``triangulation.ignore_two_view_tracks``): a point needs three views.

    Returns
    -------
    pycolmap.Reconstruction
    """
    pycolmap = require_pycolmap()
    out = check_triangulation_folder(output_dir, model)
    views, rec = load_views(model)
    if rec is None:
        rec = reconstruction_from_views(views)
    if options is None:
        options = pycolmap.IncrementalPipelineOptions()
    tmp = out.with_name(f".{out.name}.{os.getpid()}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        with terminate_as_interrupt():
            result = pycolmap.triangulate_points(rec, str(database), str(image_dir), str(tmp), options=options)
            out.mkdir(parents=True, exist_ok=True)
            for f in sorted(tmp.iterdir()):  # the model's files, each replaced at once
                os.replace(f, out / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return result


def check_triangulation_folder(output_dir, model) -> Path:
    """The folder a triangulated model goes to: not the input model's folder, and not a file."""
    out = Path(output_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"triangulation folder {str(out)!r} is a file, expected a folder")
    if not isinstance(model, (list, tuple)) and Path(model).is_dir() and out.is_dir() \
            and os.path.samefile(out, model):
        raise ValueError(f"triangulation folder {str(out)!r} is the input model's folder; its files would be "
                         "replaced: give another folder")
    parent = out.parent if str(out.parent) else Path(".")
    if not parent.is_dir():
        raise ValueError(f"triangulation folder {str(out)!r}: its parent folder does not exist")
    return out
