"""No pose, with K: the estimated pose carries its covariance, and the matching runs in its posterior's bands."""

import cv2
import numpy as np
import pytest

from episeg_cv import estimate_geometry, match_without_pose, scenes
from episeg_cv.matching import MatchInputs, SearchConfig, banded
from episeg_cv.matching.config import AcceptRule


@pytest.fixture(scope="module")
def forward():
    p = scenes.make_pair("forward")
    sift = cv2.SIFT_create(nfeatures=3000, contrastThreshold=0.02)
    (k1, d1), (k2, d2) = (sift.detectAndCompute(im, None) for im in (p.image1, p.image2))
    p1, p2 = (np.array([k.pt for k in kk], dtype=np.float64) for kk in (k1, k2))
    return p, d1, d2, p1, p2


def test_the_essential_path_returns_the_posterior_pose_with_its_covariance(forward):
    p, d1, d2, p1, p2 = forward
    g = p.geometry
    size = dict(image_size1=g.image_size1, image_size2=g.image_size2, K1=g.K1, K2=g.K2)
    est = estimate_geometry(d1, d2, p1, p2, **size)
    C = est.geometry.covariance
    assert C is not None and C.shape == (6, 6) and np.allclose(C, C.T) and np.all(np.linalg.eigvalsh(C) > 0)
    # hundreds of matches pin the rotation to hundredths of a degree; the estimate is that close
    sd_rot = np.degrees(np.sqrt(np.diag(C)[:3]))
    R_err = np.degrees(np.arccos(np.clip((np.trace(est.geometry.R @ g.R.T) - 1) / 2, -1, 1)))
    assert sd_rot.max() < 0.05 and R_err < 0.2 and est.tol >= 2.0
    # the guided matches are those of the posterior's bands, with the default rule
    pairs, _, _ = match_without_pose(d1, d2, p1, p2, **size)
    s = SearchConfig(tol=est.tol)
    inputs = MatchInputs.check(d1, d2, p1, p2, "l2")
    guided, _ = banded.match(inputs, est.geometry, banded.bands_for(est.geometry, p1, s), s, AcceptRule())
    assert set(map(tuple, guided)) <= set(map(tuple, pairs))


def test_the_fundamental_path_has_no_covariance(forward):
    p, d1, d2, p1, p2 = forward
    est = estimate_geometry(d1, d2, p1, p2, image_size1=p.geometry.image_size1, image_size2=p.geometry.image_size2)
    assert getattr(est.geometry, "covariance", None) is None
