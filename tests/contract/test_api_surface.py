"""The public API surface: the names of the contract must not disappear (kornia ``test_api_surface``)."""

import inspect

import cv2
import numpy as np
import pytest

import episeg_cv

#: The contract of issue 3 (and the geometry issue). Removing one of these is a breaking change.
CONTRACT_NAMES = [
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
    "SearchConfig",
    "AcceptRule",
    "Neighbors",
    "set_num_threads",
    "get_num_threads",
    "__version__",
]

#: Issue 16: poses that are off (tol="auto", a covariance) and no pose at all.
UNCERTAIN_NAMES = ["AutoTol", "estimate_band", "BandEstimate", "refine_pose", "PoseRefinement", "pose_covariance",
                   "EpipolarBands", "EpipolarGeometry", "FundamentalGeometry", "estimate_geometry", "EstimatedGeometry",
                   "GeometryEstimationError", "match_without_pose"]

#: Methods of the cv2.BFMatcher drop-in, plus the after-matching mode.
MATCHER_METHODS = ["match", "knnMatch", "radiusMatch", "filter", "explain"]

#: The labels of Rejection, as the issue lists the reasons.
REJECTION_NAMES = ("on_segment", "beyond_infinity", "beyond_epipole", "off_line", "empty_segment")

_K = [[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]]
GEOMETRY = episeg_cv.TwoViewGeometry(_K, _K, np.eye(3), [-1, 0, 0], image_size1=(100, 100), image_size2=(100, 100))


def test_all_names_exist():
    missing = [name for name in episeg_cv.__all__ if not hasattr(episeg_cv, name)]
    assert missing == []


def test_all_has_no_duplicates():
    assert len(set(episeg_cv.__all__)) == len(episeg_cv.__all__)


@pytest.mark.parametrize("name", CONTRACT_NAMES + UNCERTAIN_NAMES)
def test_contract_name_is_public(name):
    assert name in episeg_cv.__all__, f"{name} was removed from episeg_cv.__all__"
    assert hasattr(episeg_cv, name)


def test_version_is_a_string():
    assert isinstance(episeg_cv.__version__, str) and episeg_cv.__version__


def test_segment_matcher_signature():
    sig = inspect.signature(episeg_cv.SegmentMatcher)
    params = list(sig.parameters.values())
    P = inspect.Parameter
    # positional (or keyword) first three, as cv2.BFMatcher(normType, crossCheck) plus the geometry
    assert [p.name for p in params[:3]] == ["geometry", "normType", "crossCheck"]
    assert all(p.kind is P.POSITIONAL_OR_KEYWORD for p in params[:3])
    assert params[0].default is P.empty
    assert params[1].default == cv2.NORM_L2
    assert params[2].default is False
    # the settings, keyword-only and passed whole; their defaults live in the config objects only
    kw = {p.name: p for p in params if p.kind is P.KEYWORD_ONLY}
    assert set(kw) == {"search", "rule"} and kw["search"].default is None and kw["rule"].default is None
    m = episeg_cv.SegmentMatcher(GEOMETRY)
    assert (m.tol, tuple(m.depth_range), m.constraint) == (2.0, (0.0, np.inf), "segment")
    assert (m.ratio, m.mutual, m.pad, m.crossCheck) == (0.68, True, 128, False)
    assert m.search == episeg_cv.SearchConfig() and m.rule == episeg_cv.AcceptRule()
    # no positional parameter beyond the first three
    assert all(p.kind is not P.POSITIONAL_OR_KEYWORD for p in params[3:])
    # the fields may also be given as keywords; anything else is refused, never swallowed
    assert episeg_cv.SegmentMatcher(GEOMETRY, tol=4, ratio=0.8).search.tol == 4.0
    with pytest.raises(TypeError, match="unknown option 'tolerance'"):
        episeg_cv.SegmentMatcher(GEOMETRY, tolerance=4)


@pytest.mark.parametrize("method", MATCHER_METHODS)
def test_segment_matcher_methods(method):
    assert callable(getattr(episeg_cv.SegmentMatcher, method, None))


@pytest.mark.parametrize("method, args", [
    ("match", ["queryDescriptors", "trainDescriptors", "queryKeypoints", "trainKeypoints"]),
    ("knnMatch", ["queryDescriptors", "trainDescriptors", "queryKeypoints", "trainKeypoints", "k"]),
    ("radiusMatch", ["queryDescriptors", "trainDescriptors", "queryKeypoints", "trainKeypoints", "maxDistance"]),
    ("filter", ["matches", "queryKeypoints", "trainKeypoints"]),
])
def test_segment_matcher_method_signatures(method, args):
    sig = inspect.signature(getattr(episeg_cv.SegmentMatcher, method))
    assert list(sig.parameters)[1:len(args) + 1] == args


def test_segment_matcher_rejects_unknown_option():
    g = episeg_cv.TwoViewGeometry(np.eye(3), np.eye(3), np.eye(3), [1, 0, 0], image_size1=(10, 10), image_size2=(10, 10))
    with pytest.raises(TypeError):
        episeg_cv.SegmentMatcher(g, cv2.NORM_L2, tolerance=3.0)


def test_rejection_labels():
    R = episeg_cv.Rejection
    for name in REJECTION_NAMES:
        assert name in R.NAMES
        assert R.NAMES.index(name) == getattr(R, name.upper())
    assert R.ON_SEGMENT == 0
    assert len(set(R.NAMES)) == len(R.NAMES)
