"""benchmarks/noisy_poses.py's helpers: pose noise of the requested pixel effect, and goals computed from the rows.

The benchmark itself renders rooms and runs pycolmap (minutes); these checks run in a second.
"""

import dataclasses
import importlib.util
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from episeg_cv.colmap import View

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"
pytestmark = pytest.mark.skipif(not (BENCH / "noisy_poses.py").exists(),
                                reason="benchmarks/ not present (installed from a wheel)")


def _load(name):
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location(f"benchmarks_{name}", BENCH / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod
    finally:
        sys.path.remove(str(BENCH))


@pytest.fixture(scope="module")
def noise():
    return _load("_noisy_poses")


@pytest.fixture(scope="module")
def bench():
    return _load("noisy_poses")


def _views(n=5, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        f = 400.0 + 300.0 * i  # a different lens per view
        K = np.array([[f, 0, 320.0], [0, f, 240.0], [0, 0, 1]])
        R = cv2.Rodrigues(rng.normal(size=3))[0]
        out.append(View(f"v{i}.png", i + 1, i + 1, K, R, rng.normal(size=3), (640, 480)))
    return out


@pytest.mark.parametrize("pixels", [0.5, 2.0, 8.0])
def test_the_errors_have_the_requested_pixel_effect_on_every_lens(noise, pixels):
    views = _views()
    depths = np.array([1.0, 2.5, 4.0, 0.3, 10.0])
    noisy = noise.perturb_views(views, pixels, depths, seed=[3, 1])
    for v, w, z in zip(views, noisy, depths):
        f = v.K[0, 0]
        assert f * noise.rotation_angle(w.R @ v.R.T) == pytest.approx(pixels, rel=1e-9)
        assert f * np.linalg.norm(w.center - v.center) / z == pytest.approx(pixels, rel=1e-9)
        # a point on the optical axis at depth z moves by f tan(theta) (the rotation) plus at most the centre's p
        X = v.R.T @ (np.array([0, 0, z]) - v.t)
        x0, x1 = ((u.K @ (u.R @ X + u.t)) for u in (v, w))
        moved = np.linalg.norm(x1[:2] / x1[2] - x0[:2] / x0[2])
        assert moved <= 2 * pixels * 1.01
        assert (w.K == v.K).all() and w.name == v.name and w.image_size == v.image_size


def test_seeds_repeat_and_differ_and_zero_is_exact(noise):
    views, z = _views(), np.ones(5)
    a, b, c = (noise.perturb_views(views, 1.0, z, s) for s in ([1000, 0], [1000, 0], [1000, 1]))
    assert all(np.array_equal(x.R, y.R) and np.array_equal(x.t, y.t) for x, y in zip(a, b))
    assert not any(np.allclose(x.R, y.R) for x, y in zip(a, c))
    exact = noise.perturb_views(views, 0, z, 0)
    assert all(np.allclose(x.R, v.R) and np.allclose(x.t, v.t) for x, v in zip(exact, views))
    with pytest.raises(ValueError, match="pixels"):
        noise.perturb_views(views, -1.0, z, 0)
    with pytest.raises(ValueError, match="depths"):
        noise.perturb_views(views, 1.0, np.ones(4), 0)


def test_relative_rotation_errors_ignore_the_world_frame_and_see_one_bad_view(noise):
    views = _views()
    G = cv2.Rodrigues(np.array([0.3, -0.2, 0.5]))[0]  # another world frame: X_w' = G X_w
    moved = [dataclasses.replace(v, R=v.R @ G.T) for v in views]
    assert np.allclose(noise.relative_rotation_errors(moved, views), 0, atol=1e-6)
    bad = list(views)
    bad[2] = dataclasses.replace(views[2], R=cv2.Rodrigues(np.array([0, 0.01, 0]))[0] @ views[2].R)
    e = noise.relative_rotation_errors(bad, views)  # pairs (0,1) (0,2) (0,3) (0,4) (1,2) (1,3) (1,4) (2,3) ...
    touched = [1, 4, 7, 8]
    assert np.allclose(e[touched], np.degrees(0.01)) and np.allclose(np.delete(e, touched), 0, atol=1e-6)


def test_the_goals_come_from_the_rows(bench):
    def q(accurate, fraction):
        return {"accurate": accurate, "accurate_fraction": fraction, "points": round(accurate / fraction)}

    pyc, same = bench.PYCOLMAP, next(iter(bench.OURS))
    rows = [{"method": pyc, "level": 0, "seed": [0, 0], "true": q(100, 0.9), "used": q(100, 0.9)},
            {"method": same, "level": 0, "seed": [0, 0], "true": q(120, 0.897), "used": q(120, 0.897)}]
    for s, (ours_true, ours_used) in enumerate([(q(130, 0.95), q(90, 0.62)), (q(99, 0.95), q(80, 0.6))]):
        rows += [{"method": pyc, "level": 1, "seed": [1000, s], "true": q(100, 0.9), "used": q(70 + 10 * s, 0.6)},
                 {"method": same, "level": 1, "seed": [1000, s], "true": ours_true, "used": ours_used}]
    s = {"rows": rows}
    assert bench.meets(s, same, 0, "true") and not bench.meets(s, same, 1, "true")  # seed 1: 99 < 100
    assert bench.meets(s, same, 1, "used")  # each seed against pycolmap with the same noisy poses
    assert bench.meets(s, "(z) not run", 1, "true") is None
    res = {"config": {"levels": [0, 1]}, "sets": {"a": s}}
    G = {(m, tri): (per, upto) for m, tri, per, every, upto in bench.goals(res)}
    assert G[(same, "true")] == ({"a": [0]}, 0) and G[(same, "used")] == ({"a": [0, 1]}, 1)
    assert G[(list(bench.OURS)[1], "true")] == (None, None)
