"""``episeg colmap``: match a posed collection into a COLMAP database, and optionally triangulate it."""

from __future__ import annotations

import argparse
import sys
import time

from ..colmap.consensus import TrackConsensus
from ..colmap.pipeline import COLLECTION_TOL, VERIFY
from ..features import PRESETS
from ..matching import AcceptRule, SearchConfig
from .args import Formatter, max_features_arg, depth, positive_int, ratio_arg, tol_arg
from .console import PROG, Console, UserError


def add_parser(sub, parents) -> None:
    p = sub.add_parser("colmap", parents=parents, formatter_class=Formatter,
                       help="match a posed collection into a COLMAP database",
                       description="Compute features once per image (cached on disk), match every pair on its "
                                   "epipolar segments from the known poses, and write a COLMAP database (cameras, "
                                   "rigs, frames, images, keypoints, matches, CALIBRATED two-view geometries) that "
                                   "'colmap point_triangulator' or pycolmap.triangulate_points uses unchanged. "
                                   "By default the candidates of every pair are verified together with the known "
                                   "poses (the track consensus) before anything is written. MODEL is a COLMAP "
                                   "sparse model folder, a poses JSON (see episeg_cv.colmap.load_poses) or a "
                                   "Middlebury multi-view *_par.txt.",
                       epilog="examples:\n  episeg colmap sparse/0 images --database out.db --neighbors 10 "
                              "--triangulate tri\n  episeg colmap poses.json images --database out.db --workers 2\n"
                              "  episeg colmap dinoSR_par.txt dinoSparseRing --database dino.db --triangulate tri\n"
                              "  colmap feature_extractor --database_path colmap.db --image_path images && \\\n"
                              "    episeg colmap sparse/0 images --database colmap.db --features database\n"
                              "  # a Dask cluster: 'dask scheduler' on 10.0.0.5, 'dask worker tcp://10.0.0.5:8786' on "
                              "each machine, then:\n"
                              "  episeg colmap sparse/0 images --database out.db --cache /shared/cache "
                              "--scheduler tcp://10.0.0.5:8786")
    p.add_argument("model", help="COLMAP model folder (cameras, images, points3D; .bin or .txt), poses JSON, or "
                                 "Middlebury *_par.txt")
    p.add_argument("image_dir", help="folder of the images, named as in the model")
    p.add_argument("--database", required=True, metavar="DB", help="COLMAP database to write")
    pg = p.add_mutually_exclusive_group()
    pg.add_argument("--pairs", metavar="FILE", help="pairs file, one 'name1 name2' per line (COLMAP/hloc)")
    pg.add_argument("--neighbors", type=positive_int, metavar="K",
                    help="each image's K best partners by view overlap (default, without --pairs: every pair)")
    p.add_argument("--features", choices=("extract", "database"), default="extract",
                   help="extract: detect features here (SIFT set up for collections: contrast threshold 0.01, "
                        "sigma 1.4, RootSIFT); database: match the keypoints and descriptors that colmap "
                        "feature_extractor or pycolmap.extract_features wrote into DB, and write the matches there "
                        "(images found by name)")
    p.add_argument("--detector", choices=("sift", "orb", "akaze"), default=None,
                   help="keypoint detector, with --features extract (default: sift)")
    p.add_argument("--max-features", type=max_features_arg, default=None, metavar="N",
                   help=f"keypoints per image, with --features extract (default: "
                        f"{PRESETS['collection'].max_features})")
    p.add_argument("--constraint", choices=("segment", "line"), default="segment",
                   help="search the correct segment or the whole epipolar line")
    p.add_argument("--depth-range", nargs="+", default=["auto"], metavar="SPEC",
                   help="'auto': each image's depth range from the model's 3D points it sees; 'none': (0, inf); "
                        "or 'ZMIN ZMAX' for every image, in the unit of the poses (default: auto)")
    p.add_argument("--tol", type=tol_arg, default=COLLECTION_TOL, metavar="PX|auto",
                   help="pixel tolerance of the constraint, or 'auto' (default): one band for the collection, from "
                        "the confident matches of a few pairs around the given poses (which it does not correct: "
                        "see --refine-poses)")
    p.add_argument("--ratio", type=ratio_arg, default=None,
                   help=f"ratio test of the guided matcher, with its mutual check (default: the matcher's, "
                        f"{AcceptRule().ratio})")
    p.add_argument("--verify", choices=VERIFY, default="tracks",
                   help="tracks: verify the candidates of all pairs together with the known poses (a match with a "
                        "ratio between --ratio and --loose-ratio needs a track of 3 views); pairs: each pair's "
                        "matches under --ratio alone, written as they come")
    p.add_argument("--loose-ratio", type=ratio_arg, default=None, metavar="R",
                   help=f"candidates below this ratio are edges of the track consensus (default: "
                        f"{TrackConsensus().loose}, every mutual candidate)")
    p.add_argument("--complete-tracks", action="store_true",
                   help="after the track consensus, project each two-view track into the other views with the known "
                        "poses and add the keypoint found there if the image patches agree (off by default: "
                        "3-7 %% more accurate points, but a slower verification)")
    p.add_argument("--refine-poses", action="store_true",
                   help="first refine the poses from the collection's own matches (rounds of matching, "
                        "triangulation and bundle adjustment, intrinsics fixed), then match with them; "
                        "--triangulate uses the refined poses. For poses off by more than a pixel's worth "
                        "(odometry, GPS/IMU); poses the matches do not determine better are kept, with a warning")
    p.add_argument("--workers", type=positive_int, default=None, metavar="N",
                   help="cores to use (default: every core): N threads for features and pairs, one pair per "
                        "thread; 1 runs everything on one core")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="Dask scheduler address (workers started with 'dask worker ADDRESS'), or local:N for a new "
                        "LocalCluster of N processes (needs episeg_cv[dask])")
    p.add_argument("--cache", default=None, metavar="DIR",
                   help="feature cache folder (default: DB.features, next to the database)")
    p.add_argument("--triangulate", default=None, metavar="OUT_DIR",
                   help="then run pycolmap.triangulate_points and write the model to OUT_DIR")
    rg = p.add_mutually_exclusive_group()
    rg.add_argument("--resume", action="store_true", help="continue DB, skipping the pairs it holds")
    rg.add_argument("--overwrite", action="store_true",
                    help="replace an existing DB (with --features database: its matches and two-view geometries "
                         "only)")
    p.set_defaults(func=run)


#: What each progress stage counts.
UNITS = {"features": "images", "poses": "rounds"}


def colmap_depth(values):
    """``--depth-range``: ``auto``, ``none`` or ``ZMIN ZMAX``."""
    if len(values) == 1 and values[0] in ("auto", "none"):
        return values[0]
    if len(values) == 2:
        try:
            return (depth(values[0]), depth(values[1]))
        except argparse.ArgumentTypeError as e:
            raise UserError(f"--depth-range: {e}") from e
    raise UserError(f"--depth-range takes 'auto', 'none' or ZMIN ZMAX, got {' '.join(values)!r}")


def run(args, console: Console) -> int:
    try:
        import pycolmap
    except ImportError as e:
        raise UserError('episeg colmap needs pycolmap: pip install "episeg_cv[colmap]"') from e
    from .. import colmap

    if not console.verbose:
        pycolmap.logging.minloglevel = 2  # COLMAP's INFO and WARNING lines only with --verbose
    bars = {}

    def progress(stage, done, total):
        bar = bars.get(stage) or bars.setdefault(stage, console.progress(total, stage))
        dt = time.perf_counter() - bar.t0
        bar.step(f"{done / dt:.1f} {UNITS.get(stage, 'pairs')}/s" if dt > 0 else "")

    search = SearchConfig(tol=args.tol, constraint=args.constraint)
    rule = AcceptRule(**({} if args.ratio is None else {"ratio": args.ratio}))
    if args.features == "database":
        if args.detector is not None or args.max_features is not None:
            raise UserError("--detector and --max-features apply to --features extract, not to --features database")
        features = "database"
    else:
        features = PRESETS["collection"].replace(detector=args.detector or "sift",
                                                 max_features=args.max_features or PRESETS["collection"].max_features)
    if args.verify == "pairs" and (args.loose_ratio is not None or args.complete_tracks):
        raise UserError(f"{'--loose-ratio' if args.loose_ratio is not None else '--complete-tracks'} applies to "
                        "--verify tracks")
    options = {**({} if args.loose_ratio is None else {"loose": args.loose_ratio}),
               **({"complete": True} if args.complete_tracks else {})}
    verify = TrackConsensus(**options) if options else args.verify
    t0 = time.perf_counter()
    try:
        report = colmap.match_model(
            args.model, args.image_dir, args.database, pairs=args.pairs, neighbors=args.neighbors,
            features=features, depth_range=colmap_depth(args.depth_range), search=search, rule=rule, verify=verify,
            workers=args.workers, scheduler=args.scheduler, cache_dir=args.cache, resume=args.resume,
            overwrite=args.overwrite, refine_poses=args.refine_poses, progress=progress,
            log=lambda msg: print(f"{PROG}: {msg}", file=sys.stderr, flush=True))
    finally:
        for bar in bars.values():
            bar.close()
    console.print(report.summary())
    if args.triangulate:
        model = args.model if report.poses is None else report.poses.views
        rec = colmap.triangulate(args.database, model, args.image_dir, args.triangulate)
        console.print(f"triangulated model in {args.triangulate}: {rec.num_points3D()} points, "
                      f"mean track length {rec.compute_mean_track_length():.2f}, "
                      f"mean reprojection error {rec.compute_mean_reprojection_error():.3f} px")
    console.info(f"done in {time.perf_counter() - t0:.1f} s")
    return 0
