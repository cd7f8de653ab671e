"""Poses that are off (:mod:`episeg_cv.colmap.adjust`): ``match_model(..., refine_poses=True)``."""

import dataclasses

import cv2
import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")

from episeg_cv import colmap, scenes  # noqa: E402
from episeg_cv.colmap import adjust  # noqa: E402
from episeg_cv.colmap.views import View  # noqa: E402

pycolmap.logging.minloglevel = 2

K = np.array([[500.0, 0, 240], [0, 500, 180], [0, 0, 1]])


@pytest.fixture(scope="module")
def collection():
    return scenes.make_collection(6, image_size=(480, 360))


@pytest.fixture(scope="module")
def folder(collection, tmp_path_factory):
    return colmap.save_collection(collection, tmp_path_factory.mktemp("adjust"))


def _rotation(axis, deg):
    return cv2.Rodrigues(np.radians(deg) * np.asarray(axis, float) / np.linalg.norm(axis))[0]


def _perturbed(views, deg, dist, seed=3):
    """Each view turned by ``deg`` about a random axis and its centre moved by ``dist`` (world units)."""
    rng = np.random.default_rng(seed)
    out = []
    for v in views:
        R = _rotation(rng.normal(size=3), deg) @ v.R
        u = rng.normal(size=3)
        c = v.center + dist * u / np.linalg.norm(u)
        out.append(dataclasses.replace(v, R=R, t=-R @ c))
    return out


# -- hand-computed ------------------------------------------------------------------------------------------
def test_change_px_by_hand():
    a = View("a.png", 1, 1, K, np.eye(3), [0, 0, 0], (480, 360))
    moved = dataclasses.replace(a, t=np.array([0.0, 0.02, 0.0]))  # 2 cm down: 1 px at 10 m, 2 px at 5 m
    X = np.array([[0.0, 0.0, 10.0]] * 9 + [[0.0, 0.0, 5.0]])
    assert adjust.change_px(a, moved, X[:9]) == pytest.approx(1.0, rel=1e-12)
    # the 90th percentile of 9 moves of 1 px and one of 2 px
    assert adjust.change_px(a, moved, X) == pytest.approx(np.percentile([1.0] * 9 + [2.0], 90), rel=1e-12)
    assert adjust.change_px(a, moved, np.zeros((0, 3))) == 0.0


# -- property -----------------------------------------------------------------------------------------------
def _random_similarity(rng):
    return rng.uniform(0.2, 5), _rotation(rng.normal(size=3), rng.uniform(0, 180)), rng.normal(size=3) * 10


@pytest.mark.parametrize("seed", range(5))
def test_similarity_recovers_any_similarity(seed):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(20, 3))
    s, R, t = _random_similarity(rng)
    s2, R2, t2 = adjust.similarity(X, s * X @ R.T + t)
    assert s2 == pytest.approx(s, rel=1e-12)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-10)


@pytest.mark.parametrize("seed", range(5))
def test_in_frame_keeps_every_projection(seed):
    rng = np.random.default_rng(seed)
    views = [View(f"{k}.png", k + 1, 1, K, _rotation(rng.normal(size=3), rng.uniform(0, 30)), rng.normal(size=3),
                  (480, 360)) for k in range(3)]
    X = rng.normal(size=(10, 3)) + [0, 0, 8]
    s, R, t = _random_similarity(rng)
    moved = adjust.in_frame(views, s, R, t)
    for v, m in zip(views, moved):  # the same image points, seen from the cameras moved with the world
        np.testing.assert_allclose(adjust._project(m, s * X @ R.T + t), adjust._project(v, X), atol=1e-8)
        assert adjust.change_px(v, v, X) == 0.0


# -- synthetic scene -----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def true_views(folder):
    return colmap.load_model(folder["model"])[0]


def test_poses_off_by_half_a_degree_are_refined(folder, true_views, tmp_path, relative_error_deg, true_inliers):
    noisy = _perturbed(true_views, 0.5, 0.02)
    assert relative_error_deg(noisy, true_views) > 0.4
    stages = []
    report = colmap.match_model(noisy, folder["images"], tmp_path / "r.db", refine_poses=True,
                                progress=lambda stage, done, total: stages.append(stage))
    p = report.poses
    assert p.converged and 1 <= p.rounds <= adjust.MAX_ROUNDS and len(p.changes_px) == p.rounds
    assert p.changes_px[-1] < adjust.MIN_CHANGE_PX < p.changes_px[0]
    assert relative_error_deg(p.views, true_views) < 0.05
    assert [v.name for v in p.views] == [v.name for v in noisy]
    assert [v.depth_range for v in p.views] == [v.depth_range for v in noisy]
    assert stages.count("poses") == p.rounds
    assert "poses refined in" in report.summary()
    # the written two-view geometries are the refined poses'
    db = pycolmap.Database.open(str(tmp_path / "r.db"))
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        by_name = {v.name: v for v in p.views}
        a, b = true_views[0].name, true_views[1].name
        tvg = db.read_two_view_geometry(ids[a], ids[b])
        np.testing.assert_allclose(tvg.cam2_from_cam1.rotation.matrix(), by_name[a].geometry_to(by_name[b]).R,
                                   atol=1e-9)
    finally:
        db.close()
    # far fewer wrong matches than matching with the poses as given, and no fewer right ones
    plain = colmap.match_model(noisy, folder["images"], tmp_path / "p.db", cache_dir=tmp_path / "r.db.features")
    assert plain.poses is None
    right_r, all_r = true_inliers(tmp_path / "r.db", true_views)
    right_p, all_p = true_inliers(tmp_path / "p.db", true_views)
    assert right_r >= right_p and right_r / all_r > 0.98 and right_r / all_r > right_p / all_p + 0.05


def test_exact_poses_stay_put(folder, true_views, tmp_path, relative_error_deg):
    report = colmap.match_model(folder["model"], folder["images"], tmp_path / "e.db", refine_poses=True)
    assert report.poses.converged and report.poses.rounds <= 2
    f = true_views[0].K[0, 0]
    assert np.radians(relative_error_deg(report.poses.views, true_views)) * f < 0.5  # under half a pixel


def test_no_convergence_keeps_the_given_poses(folder, true_views, tmp_path, monkeypatch):
    monkeypatch.setattr(adjust, "MAX_ROUNDS", 1)
    monkeypatch.setattr(adjust, "MIN_CHANGE_PX", 0.0)  # nothing converges
    noisy = _perturbed(true_views, 0.5, 0.02)
    warnings = []
    report = colmap.match_model(noisy, folder["images"], tmp_path / "n.db", refine_poses=True, log=warnings.append)
    p = report.poses
    assert not p.converged and p.rounds == 1
    assert all(np.array_equal(a.R, b.R) and np.array_equal(a.t, b.t) for a, b in zip(p.views, noisy))
    assert any("did not converge" in w for w in warnings)
    assert "poses kept as given" in report.summary()


def test_rounds_share_the_run_s_dask_cluster(folder, true_views, tmp_path, monkeypatch):
    """A local cluster starts once for all rounds and the final matching (each start cost 1.3-1.9 s here),
    and the rounds give the poses that threads give."""
    pytest.importorskip("distributed")
    import distributed

    started = []
    real = distributed.LocalCluster

    def counted(*args, **kwargs):
        started.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(distributed, "LocalCluster", counted)
    noisy = _perturbed(true_views, 0.5, 0.02)
    dask = colmap.match_model(noisy, folder["images"], tmp_path / "d.db", refine_poses=True, scheduler="local:1",
                              workers=1)
    threads = colmap.match_model(noisy, folder["images"], tmp_path / "t.db", refine_poses=True,
                                 cache_dir=tmp_path / "d.db.features")
    assert len(started) == 1 and dask.poses.rounds >= 2 and "Dask" in dask.runner
    assert dask.poses.rounds == threads.poses.rounds and dask.poses.converged
    for a, b in zip(dask.poses.views, threads.poses.views):
        np.testing.assert_allclose(a.R, b.R, atol=1e-9)
        np.testing.assert_allclose(a.t, b.t, atol=1e-9)


def test_a_wide_band_suggests_refining_the_poses(folder, true_views, tmp_path):
    notes = []
    report = colmap.match_model(_perturbed(true_views, 0.5, 0.02), folder["images"], tmp_path / "w.db",
                                log=notes.append)
    assert report.band["tol"] >= 4.0 and any("refine_poses=True" in n for n in notes)
    notes.clear()
    report = colmap.match_model(folder["model"], folder["images"], tmp_path / "x.db", log=notes.append,
                                cache_dir=tmp_path / "w.db.features")
    assert report.band["tol"] < 4.0 and not any("refine_poses" in n for n in notes)


def test_a_view_whose_pose_is_off_is_named(folder, true_views, tmp_path):
    """Synthetic scene: one view turned by 16 px (the others exact) loses its matches to the tracks; the
    report and a warning name it. With exact poses nothing is named."""
    notes = []
    exact = colmap.match_model(folder["model"], folder["images"], tmp_path / "e.db", log=notes.append)
    assert exact.verify["suspect_views"] == {} and not any("look off" in n for n in notes)
    f, k = true_views[0].K[0, 0], 2
    turned = list(true_views)
    v = turned[k]
    R = _rotation([0.3, 1.0, 0.2], np.degrees(16 / f)) @ v.R
    turned[k] = dataclasses.replace(v, R=R, t=R @ (v.R.T @ v.t))  # the same centre
    notes = []
    report = colmap.match_model(turned, folder["images"], tmp_path / "t.db", log=notes.append,
                                cache_dir=tmp_path / "e.db.features")
    assert list(report.verify["suspect_views"]) == [v.name]
    assert report.verify["suspect_views"][v.name] < 0.1
    warning = [n for n in notes if "look off" in n]
    assert len(warning) == 1 and repr(v.name) in warning[0]
    assert f"images whose poses look off (few candidates confirmed): {v.name}" in report.summary()
    # the pair rule alone has no tracks to judge with
    assert "suspect_views" not in colmap.match_model(turned, folder["images"], tmp_path / "p.db", verify="pairs",
                                                      cache_dir=tmp_path / "e.db.features").verify


def test_two_views_have_no_points_to_refine_with(tmp_path):
    folder = colmap.save_collection(scenes.make_collection(2, image_size=(480, 360)), tmp_path / "two")
    notes = []
    report = colmap.match_model(folder["model"], folder["images"], tmp_path / "t.db", refine_poses=True,
                                log=notes.append)
    given = colmap.load_model(folder["model"])[0]
    assert not report.poses.converged and report.poses.changes_px == [] and report.poses.points == [0]
    assert all(np.array_equal(a.R, b.R) for a, b in zip(report.poses.views, given))
    assert any("only 0 image(s)" in n for n in notes) and "poses kept as given: fewer than 3" in report.summary()
    assert report.n_inliers > 0  # matched anyway, with the given poses


# -- bad input -----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad", ["yes", 1, None])
def test_refine_poses_must_be_a_bool(folder, tmp_path, bad):
    with pytest.raises(TypeError, match="refine_poses"):
        colmap.match_model(folder["model"], folder["images"], tmp_path / "b.db", refine_poses=bad)


# -- the CLI -------------------------------------------------------------------------------------------------
def test_cli_refine_poses_then_triangulate_with_them(folder, true_views, tmp_path, relative_error_deg):
    import subprocess
    import sys

    noisy = tmp_path / "noisy.json"
    colmap.save_poses(noisy, _perturbed(true_views, 0.5, 0.02))
    r = subprocess.run([sys.executable, "-m", "episeg_cv.cli", "colmap", str(noisy), str(folder["images"]),
                        "--database", str(tmp_path / "c.db"), "--refine-poses", "--triangulate", str(tmp_path / "tri")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "poses refined in" in r.stdout and "triangulated model" in r.stdout
    rec = pycolmap.Reconstruction(str(tmp_path / "tri"))
    by_name = {im.name: im.cam_from_world().matrix() for im in rec.images.values()}
    tri = [dataclasses.replace(v, R=by_name[v.name][:, :3], t=by_name[v.name][:, 3]) for v in true_views]
    assert relative_error_deg(tri, true_views) < 0.05  # the model holds the refined poses, not the noisy ones


def test_resume_needs_the_same_refine_poses(folder, tmp_path):
    db = tmp_path / "r.db"
    colmap.match_model(folder["model"], folder["images"], db, refine_poses=True)
    with pytest.raises(ValueError, match="refine_poses"):
        colmap.match_model(folder["model"], folder["images"], db, resume=True)
    again = colmap.match_model(folder["model"], folder["images"], db, resume=True, refine_poses=True)
    assert again.poses.converged and again.n_pairs_done + again.n_skipped == again.n_pairs
