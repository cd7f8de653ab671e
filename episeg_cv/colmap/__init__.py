"""Posed collections in, a COLMAP database out: every pair matched on its epipolar segments.

The data flows one way: :mod:`.views` (posed images) and :mod:`.pairs`
(which pairs) -> :mod:`.store` (features, cached on disk) -> :mod:`.job`
(one pair, in a worker of :mod:`.runner`) -> :mod:`.consensus` (the
candidates of all pairs verified with the poses) -> :mod:`.database` (one
writer), driven by :mod:`.pipeline` (:func:`match_model`), then
:mod:`.triangulation` (:func:`triangulate`); :mod:`.adjust` refines poses
that are off before the final matching (``refine_poses=True``). :mod:`.model` and :mod:`.poses`
read the inputs (a COLMAP model, a poses JSON, a Middlebury ``*_par.txt``);
:mod:`.dbfeatures` reads COLMAP's own features from a database;
:mod:`.synthetic` writes a rendered collection to try it on.

Requires ``pycolmap`` (``pip install "episeg_cv[colmap]"``) for the model, the
database and distorted cameras, Dask only for ``scheduler``
(``pip install "episeg_cv[dask]"``); importing this package needs neither.

Conventions
-----------
- Poses are world-to-camera, ``X_cam = R @ X_world + t``, as in COLMAP's
  ``cam_from_world`` and :meth:`~episeg_cv.TwoViewGeometry.from_world_poses`.
- Keypoints written to the database use COLMAP's pixel convention: the
  centre of the top-left pixel is ``(0.5, 0.5)``. Everything else in
  episeg_cv has it at ``(0, 0)``; a poses JSON's ``K`` uses episeg_cv's
  (OpenCV's) convention.
- Images are read in their stored pixel grid, as COLMAP reads them: the
  EXIF orientation tag is ignored (:mod:`.images`).
- Distortion: keypoints are mapped to the pinhole image with COLMAP's own
  camera model before the constraint (:meth:`View.undistort`).

Database layout
---------------
Cameras, rigs, frames and images come from the model with its ids (COLMAP
checks that they agree). Keypoints are the raw detections. ``matches`` holds
the guided matches (with the track consensus: the candidates up to its loose
ratio), and ``two_view_geometries`` the pair's inliers (matches consistent
with both cameras' segments and, by default, with the tracks of the whole
collection) with configuration ``CALIBRATED``, the essential matrix and
``cam2_from_cam1`` from the known poses. With ``features="database"`` the
database is COLMAP's own (its cameras, images, keypoints and descriptors,
with its ids); only matches, two-view geometries, the run record and the
cameras of the model's images (set to the model's) are written.

Data safety: an existing database is never replaced without
``overwrite=True``. A new database is prepared (cameras, images, keypoints)
under a temporary name and renamed into place; then each pair's matches and
two-view geometry are written in one transaction, so an interrupted run
leaves a usable database with whole pairs only, and ``resume=True`` skips
the pairs already there (with the track consensus, which needs every pair's
candidates, it recomputes them and keeps the pairs already written when they
are unchanged). Only the driver process writes.
"""

from .consensus import TrackConsensus, verify_tracks
from .database import read_database_matches
from .dbfeatures import DatabaseFeatureStore
from .job import PairJob, PairResult, match_pair
from .model import auto_depth_ranges, load_model
from .pairs import exhaustive_pairs, index_pairs, neighbor_pairs, overlap_scores, read_pairs
from .adjust import PoseAdjustment
from .pipeline import EXHAUSTIVE_WARN, MatchReport, match_model
from .poses import load_par, load_poses, save_poses
from .triangulation import triangulate
from .store import FeatureStore
from .synthetic import save_collection
from .views import View, depth_range_from_depths, is_bounded

__all__ = ["load_model", "load_poses", "save_poses", "auto_depth_ranges", "match_model", "MatchReport",
           "triangulate", "read_database_matches", "save_collection", "EXHAUSTIVE_WARN", "View", "read_pairs",
           "index_pairs", "exhaustive_pairs", "overlap_scores", "neighbor_pairs", "depth_range_from_depths",
           "is_bounded", "FeatureStore", "PairJob", "PairResult", "match_pair", "TrackConsensus", "verify_tracks",
           "DatabaseFeatureStore", "load_par", "PoseAdjustment"]
