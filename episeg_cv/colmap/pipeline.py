"""The driver: a posed collection in, a COLMAP database out, every pair matched on its segments.

COLMAP's "reconstruct from known poses" workflow is: extract features, match,
verify, then ``point_triangulator``. Its matching ignores the poses. Here the
poses drive the matching: :func:`match_model` reads a COLMAP model (or a
poses JSON, or a Middlebury ``*_par.txt``), computes features once per image
(:class:`.store.FeatureStore`) or reads COLMAP's from the database
(:mod:`.dbfeatures`), matches every pair on its segments
(:func:`.job.match_pairs`: the small pairs of a task in one compiled call, on every core; run by a
:class:`.runner.Runner`), verifies the
candidates of all pairs together with the known poses (:mod:`.consensus`),
and writes a COLMAP database (:mod:`.database`) that ``colmap
point_triangulator`` or :func:`pycolmap.triangulate_points` uses unchanged
(:func:`~.triangulation.triangulate`).
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
from threadpoolctl import threadpool_limits

from .. import __version__
from .._validation import as_positive_int
from ..features import PRESETS, FeatureConfig
from ..interrupts import terminate_as_interrupt
from ..matching import small
from ..matching.config import AcceptRule, AutoTol, SearchConfig, resolve
from .adjust import PoseAdjustment, adjust_poses
from .band import collection_band, sample_pairs
from . import completion
from .consensus import TrackConsensus, suspect_views, verify_and_complete, verify_tracks
from .database import (check_database_path, check_resumable, create_database, database_lock, pair_unchanged,
                       write_pair, write_pairs)
from .dbfeatures import SOURCE, DatabaseFeatureStore, check_feature_database, database_views, prepare_feature_database
from .job import PairJob, match_pairs
from .model import auto_depth_ranges, reconstruction_from_views, rig_consistent
from .pairs import exhaustive_pairs, index_pairs, neighbor_pairs, read_pairs
from .poses import load_views
from .runner import Runner
from .store import FeatureStore
from .triangulation import check_triangulation_folder, triangulate
from .views import is_bounded, require_pycolmap

__all__ = ["MatchReport", "match_model", "triangulate", "load_views", "check_triangulation_folder",
           "EXHAUSTIVE_WARN", "VERIFY", "COLLECTION_TOL"]

#: Above this many images, exhaustive pairing warns (pairs grow as n^2 / 2).
EXHAUSTIVE_WARN = 300

#: The default ``tol`` of a collection: one band from its confident matches (:mod:`.band`). With the
#: track consensus's looser edges (``TrackConsensus.loose = 1``) it gave more accurate 3D points than
#: ``tol=2`` on the real dinoSparseRing and two synthetic rooms, with COLMAP's features and with ours, at
#: a higher accurate fraction on the rooms (``benchmarks/colmap.py``).
COLLECTION_TOL = "auto"

#: Pairs, evenly spread over the pair list, whose search lengths are measured (:attr:`MatchReport.search_length`):
#: two more segment computations per pair cost 10 % of matching a pair of 250 keypoints (dinoSparseRing) on
#: the general path, as much as the pair itself on the small-pair path.
LENGTH_PAIRS = 16

#: Pairs per database transaction after the track consensus (:func:`.database.write_pairs`).
WRITE_BLOCK = 64

#: The values of ``verify``: the track consensus of the whole collection, or each pair on its own.
VERIFY = ("tracks", "pairs")


@dataclass
class MatchReport:
    """What :func:`match_model` did.

    Attributes
    ----------
    database : Path
    n_images, n_pairs : int
        Images in the collection, pairs to match.
    n_skipped : int
        Pairs already in the database (``resume``); with the track consensus,
        those whose written matches are the ones this run computes.
    n_pairs_done : int
        Pairs written in this run.
    n_matches, n_inliers : int
        Written in this run.
    seconds_features, seconds_matching : float
        Wall time of feature extraction (including cache hits), and of matching
        with writing.
    seconds_band, seconds_pairs, seconds_verify, seconds_write : float
        The stages of ``seconds_matching``: the band (``tol="auto"``), the pairs,
        the track consensus, the database writes (with ``verify="pairs"`` the
        writes come as the pairs do; ``seconds_pairs`` excludes them).
    pairs_per_second : float
        Pairs matched per second of ``seconds_matching``.
    runner : str
        Where the jobs ran.
    features : str
        ``"extract"`` (detected here, :class:`~episeg_cv.features.FeatureConfig`)
        or ``"database"`` (COLMAP's, read from the database).
    verify : dict
        ``{"mode": "tracks" | "pairs", ...}``; for the consensus, the counts of
        :func:`~episeg_cv.colmap.verify_tracks` (``edges``, ``kept``, ``groups``, ...) and
        ``suspect_views``: ``{name: share of its candidates kept}`` of the images whose poses look
        off (:func:`~episeg_cv.colmap.consensus.suspect_views`; a warning names them).
    depth_ranges : dict
        ``{name: (zmin, zmax)}`` used for each image.
    band : dict
        With ``tol="auto"``: the band found (:func:`~episeg_cv.colmap.band.collection_band`:
        ``tol``, ``sigma``, ``matches``, ``pairs``, ``fallback``, and ``tau``, the track
        consensus's reprojection tolerance); empty otherwise.
    search_length : dict
        Mean search length per sampled query in image 2, pixels (up to 256
        queries in each of up to :data:`LENGTH_PAIRS` pairs, evenly spread): ``"line"``
        (the whole epipolar line in the image), ``"segment"`` (the segment with depths in ``(0, inf)``) and
        ``"segment_in_depth_range"``. Empty when no pair was matched.
    poses : PoseAdjustment or None
        With ``refine_poses``: the refined views (``poses.views``, to triangulate with) and how
        the refinement went; None otherwise.
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
    seconds_band: float = 0.0
    seconds_pairs: float = 0.0
    seconds_verify: float = 0.0
    seconds_write: float = 0.0
    pairs_per_second: float = 0.0
    runner: str = "this process"
    features: str = "extract"
    verify: dict = field(default_factory=dict)
    depth_ranges: dict = field(default_factory=dict)
    band: dict = field(default_factory=dict)
    search_length: dict = field(default_factory=dict)
    poses: PoseAdjustment | None = None

    def summary(self) -> str:
        lines = [f"database: {self.database}",
                 f"images: {self.n_images}, pairs: {self.n_pairs} ({self.n_skipped} already written, skipped)",
                 f"matches written: {self.n_matches}, inliers: {self.n_inliers}",
                 f"features: {self.seconds_features:.1f} s ({'read from the database' if self.features == SOURCE else 'extracted'}); "
                 f"matching: {self.seconds_matching:.1f} s, {self.pairs_per_second:.1f} pairs/s on {self.runner} "
                 f"(band {self.seconds_band:.2f} s, pairs {self.seconds_pairs:.2f} s, consensus "
                 f"{self.seconds_verify:.2f} s, writes {self.seconds_write:.2f} s)"]
        b, v = self.band, self.verify
        if b:
            lines.append(f"band (tol auto): {b['tol']:.2f} px" + (
                f", too few confident matches ({b['matches']}): twice the smallest band" if b["fallback"] else
                f" from {b['matches']} confident matches of {b['pairs']} pairs (sigma {b['sigma']:.2f} px)")
                + (f"; track consensus within {b['tau']:.2f} px" if v.get("mode") == "tracks" else ""))
        if v.get("mode") == "tracks" and "edges" in v:
            lines.append(f"track consensus: {v['kept']} of {v['edges']} candidate matches kept, {v['groups']} "
                         f"tracks, {self.seconds_verify:.1f} s")
            if v.get("suspect_views"):
                lines.append("images whose poses look off (few candidates confirmed): "
                             + ", ".join(sorted(v["suspect_views"])))
        if self.poses is not None:
            lines.append(self.poses.summary())
        bounded = sum(is_bounded(z) for z in self.depth_ranges.values())
        lines.append(f"depth ranges: {bounded} of {self.n_images} images bounded")
        L = self.search_length
        if L and L["line"] > 0:
            lines.append(f"search length per query: line {L['line']:.0f} px, segment {L['segment']:.0f} px "
                         f"(-{100 * (1 - L['segment'] / L['line']):.0f} %), segment in depth range "
                         f"{L['segment_in_depth_range']:.0f} px (-{100 * (1 - L['segment_in_depth_range'] / L['line']):.0f} %)")
        return "\n".join(lines)


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
                     "poses JSON); using (0, inf). depth_range='none' (--depth-range none) says so without this "
                     "warning; (zmin, zmax) (--depth-range ZMIN ZMAX) bounds every image")
            return views
        out = auto_depth_ranges(views, rec)
        unseen = [v.name for v in out if not is_bounded(v.depth_range)]
        if unseen:
            warn(f"warning: {len(unseen)} image(s) observe too few 3D points for a depth range, using (0, inf): "
                 + ", ".join(unseen[:5]) + (" ..." if len(unseen) > 5 else ""))
        return out
    return [v.with_depth_range(depth_range) for v in views]


def match_model(model, image_dir, database, *, pairs=None, neighbors=None,
                features: FeatureConfig | str = "collection", depth_range="auto", search: SearchConfig | None = None,
                rule: AcceptRule | None = None, verify: str | TrackConsensus = "tracks", workers: int | None = None,
                scheduler: str | None = None, cache_dir=None, resume: bool = False, overwrite: bool = False,
                refine_poses: bool = False, progress=None, log=None, **options) -> MatchReport:
    """Match every pair of a posed collection on its epipolar segments; write a COLMAP database.

    Parameters
    ----------
    model : str, Path or list of View
        A COLMAP sparse model folder (binary or text), a poses JSON
        (:func:`~episeg_cv.colmap.load_poses`), a Middlebury multi-view ``*_par.txt``
        (:func:`~episeg_cv.colmap.load_par`), or views.
    image_dir : str or Path
        Folder of the images, named as in the model.
    database : str or Path
        The COLMAP database to write (with ``features="database"``: the one
        holding COLMAP's features, written into).
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
        ``"collection"``: SIFT at contrast threshold 0.01, sigma 1.4, RootSIFT,
        8192 per image); or ``"database"``: the keypoints and descriptors
        that ``colmap feature_extractor`` or ``pycolmap.extract_features`` wrote
        into ``database`` (:mod:`~episeg_cv.colmap.dbfeatures`). Its images are
        found by name; matches are written with its ids. A database that holds
        matches is refused unless ``resume`` or ``overwrite`` (which replaces
        matches and two-view geometries, never features).
    depth_range : "auto", "none", None or (zmin, zmax), optional
        ``"auto"``: each image's range from the model's 3D points it sees
        (:func:`~episeg_cv.colmap.auto_depth_ranges`), or the poses JSON's
        ``depth_range``; ``(0, inf)`` where there is none.
    search : SearchConfig, optional
        ``constraint`` (``"segment"`` or ``"line"``) and ``tol`` (pixels, in
        the pinhole image; ``"auto"`` or an :class:`~episeg_cv.AutoTol`: one
        band for the collection, from the confident matches of a few pairs
        around the given poses, which are never corrected:
        :mod:`~episeg_cv.colmap.band`). Its ``depth_range`` must be left at
        ``(0, inf)``: the collection's come from ``depth_range``, one per image.
        Default: ``constraint="segment"`` and ``tol=`` :data:`COLLECTION_TOL`
        (``"auto"``), unless ``search`` or ``tol=`` is given.
    rule : AcceptRule, optional
        The acceptance rule of each pair (see :func:`~episeg_cv.match_descriptors`);
        with the track consensus, its ratio is the consensus's strict ratio.
    verify : "tracks", "pairs" or TrackConsensus, optional
        ``"tracks"`` (default): the candidates of every pair, up to a looser
        ratio, verified together with the known poses before anything is
        written (:func:`~episeg_cv.colmap.verify_tracks`; a
        :class:`~episeg_cv.colmap.TrackConsensus` sets its parameters; with
        ``complete=True`` the groups of too few views are completed by
        projection and the new matches written too:
        :mod:`~episeg_cv.colmap.completion`).
        ``"pairs"``: each pair's matches under ``rule`` alone, written as they
        come back.
    **options
        Fields of ``search`` or ``rule`` as keywords (``tol=4``, ``ratio=0.8``).
    workers : int or None, optional
        Cores to use (None, the default: every core this process may run on,
        :func:`~episeg_cv.colmap.runner.available_cores`; 1: one core for
        everything). With N > 1, the features and the larger pairs run on a
        pool of N threads, one pair per thread (the compiled kernels and OpenCV
        release the GIL), and the small pairs, the band and the track consensus
        on N kernel threads of this one. Like COLMAP's ``num_threads``.
    scheduler : str, optional
        A Dask scheduler address (``tcp://host:8786``: workers started with
        ``dask worker``), or ``"local:N"`` for a new ``LocalCluster`` of N
        worker processes, which end with this process. The feature cache must
        be on a filesystem the workers share, and episeg_cv installed on them.
        Local processes are spawned: call from under ``if __name__ ==
        "__main__":`` in a script.
    cache_dir : str or Path, optional
        Feature cache; default ``<database>.features`` next to the database.
    resume, overwrite : bool, optional
        Continue an existing database (skipping the pairs it holds; with the
        track consensus every pair's candidates are computed again, and the
        pairs already written are kept when unchanged), or replace it.
    refine_poses : bool, optional
        Refine the poses from the collection's own matches first (rounds of
        matching with this call's settings, triangulation and bundle adjustment
        of the poses, intrinsics fixed: :mod:`~episeg_cv.colmap.adjust`), then
        match with the refined poses. For poses that are off by more than a
        pixel's worth (odometry, GPS/IMU); ``MatchReport.poses`` holds the
        refined views, for :func:`~episeg_cv.colmap.triangulate`. Default False.
    progress : callable, optional
        Called as ``progress(stage, done, total)`` after each round of ``refine_poses``
        (``stage="poses"``), each image
        (``stage="features"``), each pair matched (``"pairs"``) and, with the
        track consensus, each pair written (``"write"``).
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
    if not isinstance(refine_poses, bool):
        raise TypeError(f"refine_poses must be True or False, got {refine_poses!r}")
    warn = log or (lambda msg: print(msg, file=sys.stderr))
    if search is None and "tol" not in options:
        options = {**options, "tol": COLLECTION_TOL}
    search, rule = resolve(search, rule, options)
    if search.constraint == "none":
        raise ValueError("constraint must be 'segment' or 'line' here ('none' has no geometry to use)")
    if search.bounded:
        raise ValueError("search.depth_range must be (0, inf) for a collection; give depth_range= instead")
    from_database = isinstance(features, str) and features == SOURCE
    features = None if from_database else _feature_config(features)
    consensus = _consensus_config(verify)
    if consensus is not None and consensus.loose <= rule.ratio:
        raise ValueError(f"the track consensus's loose ratio ({consensus.loose}) must be above the pair rule's "
                         f"ratio ({rule.ratio}); use verify='pairs' for the pair rule alone")
    workers = None if workers is None else as_positive_int(workers, "workers")
    image_dir = Path(image_dir)
    if image_dir.exists() and not image_dir.is_dir():
        raise ValueError(f"image folder {str(image_dir)!r} is a file, expected the folder of the images")
    if not image_dir.is_dir():
        raise ValueError(f"image folder {str(image_dir)!r} does not exist")

    views, rec = load_views(model, image_dir)
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
    if from_database:
        path = check_feature_database(database, resume, overwrite)
        views = database_views(path, views)
    else:
        path = check_database_path(database, resume, overwrite)
        _not_an_input(path, model, image_dir, views)
    cache = Path(cache_dir) if cache_dir is not None else path.with_name(path.name + ".features")
    if cache.exists() and not cache.is_dir():
        raise ValueError(f"feature cache {str(cache)!r} is a file, expected a folder")
    store = DatabaseFeatureStore(cache, image_dir, path) if from_database else FeatureStore(cache, image_dir, features)
    # BLAS on one thread: the per-pair products are small, and idle BLAS threads spinning on a busy
    # machine made matching 3-5x slower (dinoSparseRing: 20 -> 95-108 pairs/s with one thread)
    with terminate_as_interrupt(), threadpool_limits(1, user_api="blas"):
        runner = Runner(workers, scheduler)
        try:
            adjustment = None
            if refine_poses:
                def run_round(round_views, round_db):  # on this run's Dask cluster, if any: a local one starts once
                    if from_database and not round_db.exists():  # a copy of COLMAP's features; rounds replace matches
                        shutil.copyfile(path, round_db)
                    match_model(round_views, image_dir, round_db,
                                pairs=[(views[i].name, views[j].name) for i, j in pair_list],
                                features=SOURCE if from_database else features, depth_range="auto", search=search,
                                rule=rule, verify="pairs" if consensus is None else consensus, workers=workers,
                                scheduler=runner.address, cache_dir=cache, overwrite=True, log=lambda msg: None)

                adjustment = adjust_poses(views, image_dir, run_round, warn=warn, progress=progress)
                if rec is not None:  # refined view by view: a multi-camera rig's calibration holds again
                    adjustment = dataclasses.replace(adjustment, views=rig_consistent(adjustment.views, rec))
                views = adjustment.views
            if rec is None or from_database:
                rec = reconstruction_from_views(views)
            report = MatchReport(path, len(views), len(pair_list), features=SOURCE if from_database else "extract",
                                 verify={"mode": "pairs" if consensus is None else "tracks"},
                                 depth_ranges={v.name: v.depth_range for v in views}, poses=adjustment)
            tol = search.tol if search.auto is None else "auto" if search.auto == AutoTol() else repr(search.auto)
            settings = {"search": {"tol": tol, "constraint": search.constraint}, "rule": dataclasses.asdict(rule),
                        "features": store.describe(),
                        "verify": {"mode": "pairs"} if consensus is None else {"mode": "tracks",
                                                                               **dataclasses.asdict(consensus)},
                        **({"refine_poses": True} if refine_poses else {}),  # absent otherwise: old databases resume
                        "depth_ranges": {v.name: [v.depth_range[0], str(v.depth_range[1])] for v in views}}
            run = _Run(path, rec, views, store, pair_list, settings, search, rule, consensus, resume, overwrite,
                       report, progress or (lambda stage, done, total: None), warn, from_database)
            report.runner = runner.describe
            with runner.limits():
                run(runner)
        finally:
            runner.close()
    return report


@dataclass
class _Run:
    """One run of :func:`match_model`, its inputs checked: features, the database, matching, writing."""

    path: Path
    rec: object
    views: list
    store: FeatureStore
    pair_list: list
    settings: dict
    search: SearchConfig
    rule: AcceptRule
    consensus: TrackConsensus | None
    resume: bool
    overwrite: bool
    report: MatchReport
    tick: object
    warn: object
    from_database: bool
    keypoints: dict = field(default_factory=dict)  # name -> stored keypoints, from the features step

    def __call__(self, runner: Runner) -> None:
        if self.from_database:  # the features are in the database: hold it from the first read
            with database_lock(self.path):
                record = self._features(map)  # read here, so that no worker opens the database
                resume = prepare_feature_database(self.path, self.views, record, self.resume, self.overwrite,
                                                  self.warn)
                self._match(runner, record, resume)
            return
        record = self._features(runner.imap)
        if self.resume:
            with database_lock(self.path):
                self._match(runner, record, True)
        else:  # a new database, or (overwrite) one replaced atomically by the new one
            with create_database(self.path, self.rec, self.views, self.store, record, self.overwrite):
                self._match(runner, record, False)

    def _features(self, imap) -> dict:
        """Every image's features into the cache; the run record (settings and image hashes)."""
        t0 = time.perf_counter()
        digests = {}
        for name, (n, digest) in imap(_ensure_features, [(self.store, v) for v in self.views]):
            digests[name] = digest
            self.keypoints[name] = n
            self.tick("features", len(digests), len(self.views))
        self.report.seconds_features = time.perf_counter() - t0
        return {"settings": self.settings, "images": digests, "episeg_cv": __version__}

    def _jobs(self, pair_list, loose):
        views, store = self.views, self.store
        measured = set(sample_pairs(range(len(pair_list)), LENGTH_PAIRS))
        return [PairJob(k, views[i], views[j], store, self.search, self.rule, samples=PairJob.samples if k in measured else 0,
                        loose=loose) for k, (i, j) in enumerate(pair_list)]

    def _results(self, runner, jobs):
        """Every job's result, in no particular order. The small pairs (:func:`~episeg_cv.matching.small.fits`)
        first, in this thread, many in one compiled call on the runner's cores; then the others on the
        runner's workers. A few consecutive pairs per task: less scheduling and pickling, and they share
        images."""
        n = self.keypoints
        tiny = [small.fits(n[j.view1.name], n[j.view2.name], j.search, j.rule) for j in jobs]
        for inline in (True, False):
            part = [j for j, t in zip(jobs, tiny) if t == inline]
            size = runner.chunk(len(part), inline)
            chunks = (part[k:k + size] for k in range(0, len(part), size))
            yield from (r for chunk in runner.imap(_match_chunk, chunks, inline) for r in chunk)

    def _match(self, runner, record, resume) -> None:
        pycolmap = require_pycolmap()
        report, views = self.report, self.views
        done = check_resumable(self.path, views, record, self.pair_list) if resume else set()
        t0 = time.perf_counter()
        if self.search.auto is not None:  # one band for every pair, found before any is matched
            band = collection_band(views, self.store, self.pair_list, self.search, self.rule, self.search.auto,
                                   imap=runner.imap_here, per_task=runner.spread)
            report.band = band.as_dict()
            if not band.fallback and band.tol >= 2 * self.search.auto.tol_min and "refine_poses" not in self.settings:
                self.warn(f"warning: the collection's band is {band.tol:.1f} px (sigma {band.sigma:.2f} px): the "
                          "poses look off by more than their keypoints' noise, and a wide band lets wrong matches "
                          "through; refine_poses=True (--refine-poses) corrects them first")
            self.search = self.search.replace(tol=band.tol)
            if self.consensus is not None and self.consensus.tau is None:
                self.consensus = self.consensus.replace(tau=band.tau)
        report.seconds_band = time.perf_counter() - t0
        lengths, samples = np.zeros(3), 0
        if self.consensus is None:  # each pair on its own: written as it comes back
            todo = [p for p in self.pair_list if p not in done]
            report.n_skipped = len(self.pair_list) - len(todo)
            db = pycolmap.Database.open(str(self.path))
            try:
                for res in self._results(runner, self._jobs(todo, None)):
                    i, j = todo[res.index]
                    tw = time.perf_counter()
                    write_pair(db, views[i], views[j], res.matches, res.inliers)
                    report.seconds_write += time.perf_counter() - tw
                    report.n_matches += len(res.matches)
                    report.n_inliers += len(res.inliers)
                    lengths += res.lengths
                    samples += res.samples
                    report.n_pairs_done += 1
                    self.tick("pairs", report.n_pairs_done, len(todo))
            finally:
                db.close()
        else:  # the candidates of every pair, then the consensus, then the writes
            todo = self.pair_list
            results = [None] * len(todo)
            for n, res in enumerate(self._results(runner, self._jobs(todo, self.consensus.loose)), 1):
                results[res.index] = res
                lengths += res.lengths
                samples += res.samples
                self.tick("pairs", n, len(todo))
            t1 = time.perf_counter()
            report.seconds_pairs = t1 - t0 - report.seconds_band
            candidates = [(i, j, r.inliers, r.ratios) for (i, j), r in zip(todo, results)]
            pinhole = (lambda k: self.store.pinhole(views[k]))
            if self.consensus.complete:
                keep, added, stats = verify_and_complete(views, candidates, pinhole,
                                                         lambda k: self.store.load(views[k])[2], self.rule.ratio,
                                                         self.search.tol, self.consensus, self.store.norm,
                                                         completion.pinhole_images(views, self.store.image_dir))
            else:
                keep, stats = verify_tracks(views, candidates, pinhole, self.rule.ratio, self.search.tol,
                                            self.consensus)
                added = [None] * len(keep)
            report.seconds_verify = time.perf_counter() - t1
            report.verify.update(stats)
            suspects = suspect_views(len(views), candidates, keep)
            report.verify["suspect_views"] = {views[k].name: share for k, share, _ in suspects}
            if suspects:
                median = suspects[0][2]
                named = ", ".join(f"{views[k].name!r} ({100 * share:.0f} %)" for k, share, _ in suspects[:5])
                self.warn(f"warning: the tracks confirm few of the candidate matches of {len(suspects)} image(s): "
                          f"{named}{', ...' if len(suspects) > 5 else ''}, against {100 * median:.0f} % for the "
                          f"median image; their poses look off by more than the band ({self.search.tol:.1f} px), "
                          "and their matches are left out: check them")
            tw = time.perf_counter()
            db = pycolmap.Database.open(str(self.path))
            try:
                block = []
                for n, ((i, j), res, k, new) in enumerate(zip(todo, results, keep, added), 1):
                    inliers, matches = res.inliers[k], res.matches
                    if new is not None and len(new):  # the completion's matches (:mod:`.completion`)
                        inliers = np.concatenate([inliers, new.astype(np.uint32)])
                        matches = np.concatenate([matches, new.astype(np.uint32)])
                    if (i, j) in done and pair_unchanged(db, views[i], views[j], matches, inliers):
                        report.n_skipped += 1
                    else:
                        block.append((views[i], views[j], matches, inliers, (i, j) in done))
                    if block and (len(block) == WRITE_BLOCK or n == len(todo)):
                        write_pairs(db, block)
                        for _, _, matches, inliers, _ in block:
                            report.n_matches += len(matches)
                            report.n_inliers += len(inliers)
                        report.n_pairs_done += len(block)
                        block = []
                    self.tick("write", n, len(todo))
            finally:
                db.close()
            report.seconds_write = time.perf_counter() - tw
        report.seconds_matching = time.perf_counter() - t0
        if self.consensus is None:
            report.seconds_pairs = report.seconds_matching - report.seconds_band - report.seconds_write
        matched = len(todo) if self.consensus is not None else report.n_pairs_done
        report.pairs_per_second = matched / report.seconds_matching if report.seconds_matching > 0 else 0.0
        if samples:
            report.search_length = dict(zip(("line", "segment", "segment_in_depth_range"), lengths / samples))


def _not_an_input(path: Path, model, image_dir: Path, views) -> None:
    """Refuse a database path that is one of the run's input files (an image, the poses file, a model file)."""
    if not path.exists():
        return
    inputs = [image_dir / v.name for v in views]
    if not isinstance(model, (list, tuple)):
        m = Path(model)
        inputs += sorted(m.iterdir()) if m.is_dir() else [m]
    for f in inputs:
        if f.exists() and os.path.samefile(f, path):
            raise ValueError(f"database {str(path)!r} is an input of this run ({str(f)!r}); writing it would replace "
                             "it: give another database path")


def _feature_config(features) -> FeatureConfig:
    if isinstance(features, str):
        if features not in PRESETS:
            raise ValueError(f"features must be a FeatureConfig, {SOURCE!r} or one of {tuple(PRESETS)}, "
                             f"got {features!r}")
        return PRESETS[features]
    if not isinstance(features, FeatureConfig):
        raise TypeError(f"features must be a FeatureConfig or a preset name, got {type(features).__name__}")
    return features


def _consensus_config(verify) -> TrackConsensus | None:
    if isinstance(verify, TrackConsensus):
        return verify
    if isinstance(verify, str) and verify in VERIFY:
        return TrackConsensus() if verify == "tracks" else None
    raise ValueError(f"verify must be one of {VERIFY} or a TrackConsensus, got {verify!r}")


def _match_chunk(jobs):
    return match_pairs(jobs)


def _ensure_features(item):
    store, view = item
    return view.name, store.ensure(view)
