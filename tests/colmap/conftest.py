"""Ground-truth checks shared by the collection tests: written inliers against the true poses, and the error of
refined poses' relative rotations."""

import numpy as np
import pytest

from episeg_cv import colmap, filter_pairs
from episeg_cv.refinement import rotation_angle_deg


def _true_inliers(db, views_true, tol=1.0):
    """``(right, all)``: the written inliers within ``tol`` px of their segment under the true poses (raw keypoints
    are the pinhole ones in these collections), and all of them."""
    pycolmap = pytest.importorskip("pycolmap")
    by_name = {v.name: v for v in views_true}
    con = pycolmap.Database.open(str(db))
    try:
        kp = {im.name: np.asarray(con.read_keypoints(im.image_id))[:, :2] - 0.5 for im in con.read_all_images()}
    finally:
        con.close()
    right = every = 0
    for (a, b), (_, inl) in colmap.read_database_matches(db).items():
        g = by_name[a].geometry_to(by_name[b])
        right += int(filter_pairs(inl.astype(np.intp), kp[a], kp[b], g, tol=tol).sum())
        every += len(inl)
    return right, every


def _relative_error_deg(views, truth):
    """Largest error of the relative rotations over all pairs of ``views`` against ``truth`` (by name), degrees."""
    true = {v.name: v for v in truth}
    return max(rotation_angle_deg((views[j].R @ views[i].R.T) @ (true[views[j].name].R @ true[views[i].name].R.T).T)
               for i in range(len(views)) for j in range(i + 1, len(views)))


@pytest.fixture
def true_inliers():
    return _true_inliers


@pytest.fixture
def relative_error_deg():
    return _relative_error_deg
