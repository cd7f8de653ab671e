"""episeg_cv: feature matching on the correct epipolar segment, for two views with a known pose.

Pose convention: ``X2 = R @ X1 + t``. Pixel centres at integer coordinates (OpenCV).
See :class:`TwoViewGeometry` and :class:`SegmentMatcher`.
"""

from .geometry import EpipolarSegments, Rejection, TwoViewGeometry

__version__ = "0.1.0"

__all__ = ["TwoViewGeometry", "EpipolarSegments", "Rejection", "__version__"]
