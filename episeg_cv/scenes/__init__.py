"""Synthetic two-view scenes and posed collections with exact ground truth.

:mod:`.model` (textured quads, the room) -> :mod:`.render` (ray casting: image
and depth) -> :mod:`.suite` (the named pose cases, :func:`make_pair`) and
:mod:`.collection` (many views of one room). Ground truth from the depth maps
is :func:`episeg_cv.evaluation.ground_truth_matches` (also re-exported here).

Conventions: world-to-camera poses ``X_cam = R @ X_world + t``; the relative
pose of a pair is ``X2 = R @ X1 + t``; pixel centres at integer coordinates;
depth is camera ``z`` in metres, ``inf`` where a pixel sees nothing.
"""

from ..evaluation import GroundTruth, ImagePair, disparity_ground_truth, ground_truth_matches
from .collection import PosedCollection, collection_poses, make_collection
from .model import TEXTURE_NAMES, Quad, Scene, box_quads, load_texture, look_at, make_room_scene
from .render import render
from .suite import PoseCase, make_pair, pose_suite

__all__ = ["Quad", "Scene", "load_texture", "box_quads", "make_room_scene", "look_at", "render", "PoseCase",
           "pose_suite", "ImagePair", "make_pair", "GroundTruth", "ground_truth_matches", "disparity_ground_truth",
           "PosedCollection", "collection_poses", "make_collection", "TEXTURE_NAMES"]
