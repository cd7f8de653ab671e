"""episeg_cv: feature matching on the correct epipolar segment, for two views with a known pose.

Pose convention: ``X2 = R @ X1 + t``. Pixel centres at integer coordinates (OpenCV).
Start with :class:`TwoViewGeometry` and :class:`SegmentMatcher`.

Modules, in the direction the data flows: ``geometry`` (segments) ->
``candidates`` (spatial index) -> ``matching`` (arrays) -> ``opencv``
(the ``cv2.BFMatcher`` drop-in); ``collection`` -> ``colmap`` match posed
collections into a COLMAP database (``from episeg_cv import colmap``; needs
pycolmap); ``scenes`` and ``datasets`` make test data;
``calib``, ``drawing`` and ``cli`` are the edges.
"""

from . import datasets, scenes
from .calib import Calibration, load_calibration, save_calibration, undistort_points
from .candidates import CandidateIndex
from .drawing import draw_matches, draw_points, draw_segment_figure, draw_segments, save_image
from .geometry import EpipolarSegments, Rejection, TwoViewGeometry
from .matching import (GuidedMatches, explain_pairs, filter_pairs, guided_matches, knn_descriptors,
                       match_descriptors, radius_descriptors)
from .opencv import SegmentMatcher, keypoints_to_array
from .scenes import GroundTruth, ground_truth_matches

__version__ = "0.1.0"

__all__ = [
    "TwoViewGeometry",
    "EpipolarSegments",
    "Rejection",
    "CandidateIndex",
    "SegmentMatcher",
    "match_descriptors",
    "guided_matches",
    "GuidedMatches",
    "knn_descriptors",
    "radius_descriptors",
    "filter_pairs",
    "explain_pairs",
    "keypoints_to_array",
    "GroundTruth",
    "ground_truth_matches",
    "Calibration",
    "load_calibration",
    "save_calibration",
    "undistort_points",
    "draw_segments",
    "draw_points",
    "draw_segment_figure",
    "draw_matches",
    "save_image",
    "scenes",
    "datasets",
    "__version__",
]
