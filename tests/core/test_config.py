"""The settings objects (SearchConfig, AcceptRule): checked once, defaults in one place, unknown keys refused."""

import numpy as np
import pytest

from episeg_cv import (AcceptRule, SearchConfig, TwoViewGeometry, filter_pairs, guided_matches, knn_descriptors,
                       match_descriptors)

K = [[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]]
G = TwoViewGeometry(K, K, np.eye(3), [-1, 0, 0], image_size1=(100, 100), image_size2=(100, 100))


def test_defaults():
    s, r = SearchConfig(), AcceptRule()
    assert (s.tol, s.depth_range, s.constraint) == (2.0, (0.0, np.inf), "segment")
    assert (r.ratio, r.mutual, r.pad, r.cross_check) == (0.68, True, 128, False)
    assert not s.bounded and SearchConfig(depth_range=(1, 5)).bounded


@pytest.mark.parametrize("kwargs, exc, match", [
    ({"tol": -1}, ValueError, "tol"), ({"tol": np.nan}, ValueError, "tol"), ({"tol": "2"}, TypeError, "tol"),
    ({"constraint": "arc"}, ValueError, "constraint"), ({"depth_range": (5, 1)}, ValueError, "zmin < zmax"),
    ({"depth_range": "near"}, ValueError, "depth_range"), ({"tolerance": 2}, TypeError, "tolerance"),
])
def test_search_config_is_checked_when_made(kwargs, exc, match):
    with pytest.raises(exc, match=match):
        SearchConfig(**kwargs)


@pytest.mark.parametrize("kwargs, match", [
    ({"ratio": 0}, "ratio"), ({"ratio": 1.5}, "ratio"), ({"pad": -1}, "pad"), ({"pad": 2.5}, "pad"),
])
def test_accept_rule_is_checked_when_made(kwargs, match):
    with pytest.raises(ValueError, match=match):
        AcceptRule(**kwargs)


def test_frozen_and_replace_checks_again():
    s = SearchConfig()
    with pytest.raises(AttributeError):
        s.tol = 3.0
    assert s.replace(tol=3).tol == 3.0 and s.tol == 2.0
    with pytest.raises(ValueError, match="tol"):
        s.replace(tol=-3)
    assert AcceptRule().replace(ratio=0.8) == AcceptRule(ratio=0.8)


def test_equality_and_per_point_depth_ranges():
    assert SearchConfig(tol=2) == SearchConfig(tol=2.0) and hash(SearchConfig()) == hash(SearchConfig())
    a = SearchConfig(depth_range=(np.ones(3), np.full(3, 5.0)))
    assert a == SearchConfig(depth_range=(np.ones(3), np.full(3, 5.0))) and a != SearchConfig()
    assert "array of 3" in repr(a)


def _problem():
    p1 = np.array([[60.0, 20.0], [60.0, 70.0]])
    p2 = np.array([[40.0, 20.0], [40.0, 70.0]])
    d = np.eye(2, 8, dtype=np.float32)
    return d, d, p1, p2


def test_keywords_and_objects_are_the_same_settings():
    d1, d2, p1, p2 = _problem()
    a = match_descriptors(d1, d2, p1, p2, G, tol=3.0, ratio=0.9, pad=0)
    b = match_descriptors(d1, d2, p1, p2, G, search=SearchConfig(tol=3.0), rule=AcceptRule(ratio=0.9, pad=0))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    # a keyword overrides the object's field
    gm = guided_matches(d1, d2, p1, p2, G, rule=AcceptRule(pad=0), ratio=0.5)
    assert gm.rule == AcceptRule(pad=0, ratio=0.5)


@pytest.mark.parametrize("call", [
    lambda d1, d2, p1, p2: match_descriptors(d1, d2, p1, p2, G, tolerance=2),
    lambda d1, d2, p1, p2: knn_descriptors(d1, d2, p1, p2, G, ratio=0.5),   # knn has no acceptance rule
    lambda d1, d2, p1, p2: filter_pairs([[0, 0]], p1, p2, G, pad=3),
    lambda d1, d2, p1, p2: match_descriptors(d1, d2, p1, p2, G, search=AcceptRule()),
])
def test_unknown_or_misplaced_options_are_refused(call):
    with pytest.raises(TypeError):
        call(*_problem())
