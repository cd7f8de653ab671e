"""episeg_cv: feature matching on the correct epipolar segment, for two views with a known pose.

Pose convention: ``X2 = R @ X1 + t``. Pixel centres at integer coordinates (OpenCV).
Start with :class:`TwoViewGeometry` and :class:`SegmentMatcher`.

The package, in the direction the data flows:

- :mod:`.geometry`: the pair and its segments; :mod:`.uncertainty` (a pose
  covariance and its bands), :mod:`.refinement` (the pose from matches);
- :mod:`.matching`: settings (:class:`SearchConfig`, :class:`AcceptRule`),
  the candidate index, distances, guided matching and filtering on arrays;
- :mod:`.opencv`: :class:`SegmentMatcher`, the ``cv2.BFMatcher`` drop-in;
- :mod:`.fundamental` and :mod:`.estimation`: no pose (an oriented
  fundamental matrix, or ``E`` with the intrinsics) estimated from the images;
- :mod:`.features`, :mod:`.distortion`, :mod:`.io` (calibration and matches
  files), :mod:`.evaluation` (ground truth), :mod:`.drawing`: the edges;
- :mod:`.scenes` and :mod:`.datasets`: synthetic and real test data;
- :mod:`.colmap`: posed collections into a COLMAP database
  (``from episeg_cv import colmap``; needs pycolmap);
- :mod:`.cli`: the ``episeg`` command;
- :func:`set_num_threads` / :func:`get_num_threads` (:mod:`.threads`): how many
  threads the compiled kernels use, like ``cv2.setNumThreads``; every core by
  default, and the same results for every count.
"""

__version__ = "0.1.0"

from . import datasets, scenes  # noqa: E402
from .distortion import undistort_points  # noqa: E402
from .drawing import draw_matches, draw_points, draw_segment_figure, draw_segments, save_image  # noqa: E402
from .evaluation import GroundTruth, ground_truth_matches  # noqa: E402
from .geometry import EpipolarGeometry, EpipolarSegments, Rejection, TwoViewGeometry  # noqa: E402
from .io import Calibration, load_calibration, save_calibration  # noqa: E402
from .matching import (AcceptRule, AutoTol, BandEstimate, CandidateIndex, GuidedMatches, Neighbors,  # noqa: E402
                       SearchConfig, consistent_pairs, estimate_band, explain_pairs, filter_pairs, guided_matches,
                       knn_descriptors, match_descriptors, radius_descriptors)
from .opencv import SegmentMatcher, keypoints_to_array  # noqa: E402
from .estimation import EstimatedGeometry, GeometryEstimationError, estimate_geometry, match_without_pose  # noqa: E402
from .fundamental import FundamentalGeometry  # noqa: E402
from .refinement import PoseRefinement, refine_pose  # noqa: E402
from .threads import get_num_threads, set_num_threads  # noqa: E402
from .uncertainty import EpipolarBands, pose_covariance  # noqa: E402

__all__ = [
    "TwoViewGeometry",
    "EpipolarGeometry",
    "EpipolarSegments",
    "Rejection",
    "SearchConfig",
    "AcceptRule",
    "AutoTol",
    "estimate_band",
    "BandEstimate",
    "refine_pose",
    "PoseRefinement",
    "pose_covariance",
    "EpipolarBands",
    "FundamentalGeometry",
    "estimate_geometry",
    "EstimatedGeometry",
    "GeometryEstimationError",
    "match_without_pose",
    "CandidateIndex",
    "SegmentMatcher",
    "match_descriptors",
    "guided_matches",
    "GuidedMatches",
    "knn_descriptors",
    "Neighbors",
    "radius_descriptors",
    "filter_pairs",
    "explain_pairs",
    "consistent_pairs",
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
    "set_num_threads",
    "get_num_threads",
    "scenes",
    "datasets",
    "__version__",
]
