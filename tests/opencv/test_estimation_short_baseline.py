"""No pose, with K: the inliers of the essential path on a short baseline (points farther than 50 baselines)."""

import numpy as np

from episeg_cv import TwoViewGeometry, estimate_geometry

K = np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]])
SIZE = dict(image_size1=(640, 480), image_size2=(640, 480))


def test_far_points_stay_inliers_of_the_recovered_pose():
    # a 1 cm baseline and points at 1-3 m: 100-300 baselines away, where recoverPose's default overload
    # (distanceThresh 50) counts every point as behind a camera and returns no inlier
    rng = np.random.default_rng(3)
    g = TwoViewGeometry(K, K, np.eye(3), [-0.01, 0.0, 0.002], **SIZE)
    x1 = rng.uniform([20, 20], [620, 460], (300, 2))
    x2, _ = g.transfer(x1, rng.uniform(1.0, 3.0, 300))
    keep = (x2[:, 0] > 0) & (x2[:, 0] < 639) & (x2[:, 1] > 0) & (x2[:, 1] < 479)
    x1, x2 = x1[keep], x2[keep] + rng.normal(0, 0.1, (keep.sum(), 2))
    d = rng.normal(0, 10, (len(x1), 32)).astype(np.float32)  # distinct descriptors: the first pass keeps them all
    est = estimate_geometry(d, d, x1, x2, K1=K, K2=K, **SIZE)
    assert len(est.first_pass) == len(x1)
    assert len(est.inliers) >= 0.95 * len(x1)
    u = est.geometry.t / np.linalg.norm(est.geometry.t)
    assert np.degrees(np.arccos(np.clip(u @ g.t / np.linalg.norm(g.t), -1, 1))) < 5.0
