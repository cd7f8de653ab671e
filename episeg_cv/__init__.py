"""episeg_cv: feature matching on the correct epipolar segment, for two views with a known pose.

Pose convention: ``X2 = R @ X1 + t``. Pixel centres at integer coordinates (OpenCV).
See :class:`TwoViewGeometry` and :class:`SegmentMatcher`.
"""

from .candidates import CandidateIndex
from .geometry import EpipolarSegments, Rejection, TwoViewGeometry
from .matching import explain_pairs, filter_pairs, knn_descriptors, match_descriptors, radius_descriptors
from .opencv import SegmentMatcher, keypoints_to_array

__version__ = "0.1.0"

__all__ = [
    "TwoViewGeometry",
    "EpipolarSegments",
    "Rejection",
    "CandidateIndex",
    "SegmentMatcher",
    "match_descriptors",
    "knn_descriptors",
    "radius_descriptors",
    "filter_pairs",
    "explain_pairs",
    "keypoints_to_array",
    "__version__",
]
