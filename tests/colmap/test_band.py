"""``tol="auto"`` for a collection (:mod:`episeg_cv.colmap.band`): one band, from a few pairs' confident matches."""

import dataclasses
import subprocess
import sys

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")

from episeg_cv import AutoTol, SearchConfig, colmap, scenes  # noqa: E402
from episeg_cv.colmap import TrackConsensus  # noqa: E402
from episeg_cv.colmap import exhaustive_pairs  # noqa: E402
from episeg_cv.colmap.band import TAU_MIN, band_pairs, sample_pairs  # noqa: E402

pycolmap.logging.minloglevel = 2


@pytest.fixture(scope="module")
def collection():
    return scenes.make_collection(4, image_size=(480, 360))


@pytest.fixture(scope="module")
def folder(collection, tmp_path_factory):
    return colmap.save_collection(collection, tmp_path_factory.mktemp("band"))


def _rotation(axis, deg):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    th = np.radians(deg)
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def _same(a, b):
    assert a.keys() == b.keys()
    assert all(np.array_equal(a[k][0], b[k][0]) and np.array_equal(a[k][1], b[k][1]) for k in a)


def test_exact_poses_give_the_fixed_band_and_a_tighter_consensus(folder, tmp_path):
    m, im = folder["model"], folder["images"]
    read = colmap.read_database_matches
    ref = colmap.match_model(m, im, tmp_path / "ref.db", tol=2.0, verify="pairs")
    auto = colmap.match_model(m, im, tmp_path / "auto.db", tol="auto", verify="pairs")
    b = auto.band
    views, _ = colmap.load_model(m)
    sampled = band_pairs(views, exhaustive_pairs(4))
    assert b["tol"] == 2.0 and b["sigma"] < 0.5 and b["matches"] >= 40 and not b["fallback"]
    assert b["pairs"] == len(sampled) and 2 <= len(sampled) <= 3
    assert b["tau"] == TAU_MIN and ref.band == {}
    _same(read(tmp_path / "auto.db"), read(tmp_path / "ref.db"))  # the pair rule: the band alone
    assert "band (tol auto): 2.00 px from" in auto.summary() and "consensus within" not in auto.summary()
    # the track consensus checks reprojections within k sigma, at least TAU_MIN, instead of the band
    tracks = colmap.match_model(m, im, tmp_path / "tracks.db", tol="auto")
    assert "; track consensus within 1.00 px" in tracks.summary()
    colmap.match_model(m, im, tmp_path / "tau1.db", verify=TrackConsensus(tau=TAU_MIN))
    _same(read(tmp_path / "tracks.db"), read(tmp_path / "tau1.db"))
    # a tolerance the caller gives is kept
    colmap.match_model(m, im, tmp_path / "given.db", tol="auto", verify=TrackConsensus(tau=2.0))
    colmap.match_model(m, im, tmp_path / "fixed.db", tol=2.0)
    _same(read(tmp_path / "given.db"), read(tmp_path / "fixed.db"))
    # tol="auto" is the collection's default
    default = colmap.match_model(m, im, tmp_path / "default.db")
    assert default.band == tracks.band
    _same(read(tmp_path / "default.db"), read(tmp_path / "tracks.db"))


def test_noisy_poses_widen_the_band_and_keep_more_true_matches(folder, tmp_path, true_inliers):
    views, _ = colmap.load_model(folder["model"])
    rng = np.random.default_rng(3)
    noisy = [dataclasses.replace(v, R=_rotation(rng.normal(size=3), 0.4) @ v.R) for v in views]
    fixed = colmap.match_model(noisy, folder["images"], tmp_path / "fixed.db", tol=2.0, log=lambda m: None)
    auto = colmap.match_model(noisy, folder["images"], tmp_path / "auto.db", tol="auto", log=lambda m: None)
    assert fixed.band == {} and auto.band["tol"] > 3.0
    assert true_inliers(tmp_path / "auto.db", views)[0] > 1.2 * true_inliers(tmp_path / "fixed.db", views)[0]


def test_too_few_confident_matches_fall_back_to_twice_the_smallest_band(folder, tmp_path):
    r = colmap.match_model(folder["model"], folder["images"], tmp_path / "f.db",
                           search=SearchConfig(tol=AutoTol(min_matches=10**7, tol_min=1.5)))
    assert r.band["fallback"] and r.band["tol"] == 3.0 and np.isnan(r.band["sigma"])
    assert "too few confident matches" in r.summary()


def test_a_run_with_auto_resumes(folder, tmp_path):
    db = tmp_path / "r.db"
    first = colmap.match_model(folder["model"], folder["images"], db, tol="auto", verify="pairs")
    again = colmap.match_model(folder["model"], folder["images"], db, tol="auto", verify="pairs", resume=True)
    assert first.n_pairs_done == 6 and again.n_skipped == 6 and again.n_pairs_done == 0
    with pytest.raises(ValueError, match="search.tol was 'auto', now 2.0"):
        colmap.match_model(folder["model"], folder["images"], db, tol=2.0, verify="pairs", resume=True)


@pytest.mark.parametrize("n, k", [(0, 16), (3, 16), (16, 16), (17, 16), (120, 16), (120, 1)])
def test_sampled_pairs_spread_over_the_list(n, k):
    pairs = [(i, i + 1) for i in range(n)]
    got = sample_pairs(pairs, k)
    assert len(got) == min(n, k) and len(set(got)) == len(got) and all(p in pairs for p in got)
    if n > k > 1:
        assert got[0] == pairs[0] and got[-1] == pairs[-1]
        gaps = np.diff([pairs.index(p) for p in got])
        assert gaps.max() - gaps.min() <= 1


def test_cli_tol_auto(folder, tmp_path):
    for name, tol in (("c.db", ["--tol", "auto"]), ("default.db", [])):  # auto is the default
        r = subprocess.run([sys.executable, "-m", "episeg_cv.cli", "colmap", str(folder["model"]),
                            str(folder["images"]), "--database", str(tmp_path / name), *tol], capture_output=True,
                           text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        assert "band (tol auto): 2.00 px" in r.stdout
    r = subprocess.run([sys.executable, "-m", "episeg_cv.cli", "colmap", str(folder["model"]), str(folder["images"]),
                        "--database", str(tmp_path / "e.db"), "--tol", "2"], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert "band (tol auto)" not in r.stdout
    r = subprocess.run([sys.executable, "-m", "episeg_cv.cli", "colmap", str(folder["model"]), str(folder["images"]),
                        "--database", str(tmp_path / "d.db"), "--tol", "wide"], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 2 and "--tol" in r.stderr and "'auto'" in r.stderr


def test_the_band_uses_a_spread_subset_of_queries(folder, tmp_path, monkeypatch):
    """At most MAX_QUERIES queries a pair: the wide pass on every keypoint cost more than the matching."""
    from episeg_cv.colmap import band as band_module

    full = colmap.match_model(folder["model"], folder["images"], tmp_path / "a.db", tol="auto", verify="pairs").band
    monkeypatch.setattr(band_module, "MAX_QUERIES", 120)
    few = colmap.match_model(folder["model"], folder["images"], tmp_path / "b.db", tol="auto", verify="pairs").band
    assert few["matches"] <= 120 * few["pairs"] and few["matches"] < full["matches"]
    assert few["tol"] == full["tol"] == 2.0 and abs(few["sigma"] - full["sigma"]) < 0.2


@pytest.mark.parametrize("max_queries", [90, 120])
def test_small_sample_pairs_in_one_call_give_the_band_of_pair_by_pair(folder, tmp_path, monkeypatch, max_queries):
    """The sampled pairs that are small (:func:`episeg_cv.matching.small.fits`) are matched together by
    ``small.many``; forcing every one through the general path (one compiled call a pair) gives the same band."""
    from episeg_cv.colmap import band as band_module

    monkeypatch.setattr(band_module, "MAX_QUERIES", max_queries)
    calls = []
    real_many = band_module.small.many
    monkeypatch.setattr(band_module.small, "many", lambda items, *a: calls.append(len(items)) or real_many(items, *a))
    batched = colmap.match_model(folder["model"], folder["images"], tmp_path / "a.db", tol="auto", verify="pairs").band
    assert calls and calls[0] > 0  # some sample pairs were small
    monkeypatch.setattr(band_module.small, "fits", lambda *a: False)
    one_by_one = colmap.match_model(folder["model"], folder["images"], tmp_path / "b.db", tol="auto",
                                    verify="pairs").band
    assert batched == one_by_one and batched["matches"] > 0


@pytest.mark.parametrize("max_queries", [120, 10_000])
def test_large_sample_pairs_give_the_matches_of_guided_match(folder, tmp_path, monkeypatch, max_queries):
    """The general path matches each sampled pair in one compiled call (``fused.match_pair``); stage by
    stage (``guided.match`` from view 1, each view's depth range) gives the same confident matches, so
    the same count and the same sigma to the bit. 10_000 queries: all of them (the store's read-only
    arrays, not a copy)."""
    from episeg_cv.colmap import band as band_module
    from episeg_cv.matching import guided
    from episeg_cv.refinement import spread_subset

    def stage_by_stage(task):
        out = []
        for k, view1, view2, store, wide, strict in task:
            inputs, g, _, _ = band_module.pair_inputs(view1, view2, store)
            inputs = band_module._queries(inputs, spread_subset(inputs.points1, band_module.MAX_QUERIES))
            conf = guided.match(inputs, g, wide, strict)[0]
            out.append((k, band_module._residuals(g, inputs.points1[conf[:, 0]], inputs.points2[conf[:, 1]])))
        return out

    monkeypatch.setattr(band_module, "MAX_QUERIES", max_queries)
    monkeypatch.setattr(band_module.small, "fits", lambda *a: False)
    fused = colmap.match_model(folder["model"], folder["images"], tmp_path / "a.db", tol="auto", verify="pairs").band
    monkeypatch.setattr(band_module, "_confident", stage_by_stage)
    staged = colmap.match_model(folder["model"], folder["images"], tmp_path / "b.db", tol="auto", verify="pairs").band
    assert fused == staged and fused["matches"] > 0 and fused["pairs"] > 0


def _look(center, direction, name="v.png", k=1):
    """A View at ``center`` looking along ``direction`` (world-to-camera ``X_cam = R X + t``)."""
    z = np.asarray(direction, float) / np.linalg.norm(direction)
    up = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return colmap.View(name, k, 1, np.diag([500.0, 500.0, 1.0]), R, -R @ np.asarray(center, float), (640, 480))


@pytest.mark.parametrize("n", [3, 6, 16, 40])
def test_band_pairs_on_a_ring_are_neighbours_covering_every_image(n):
    """Cameras on a ring looking at its centre: every pair taken is two neighbours (the smallest angle and
    distance), every image is in one, and each pair brings an image not taken before (a greedy edge
    cover), at most ``n - 1`` pairs; beyond SAMPLE_PAIRS images, SAMPLE_PAIRS pairs."""
    views = []
    for k in range(n):
        a = 2 * np.pi * k / n
        c = 3 * np.array([np.cos(a), 0.0, np.sin(a)])
        views.append(_look(c, -c, f"{k}.png", k + 1))
    pairs = exhaustive_pairs(n)
    got = band_pairs(views, pairs)
    assert got == sorted(got) and len(set(got)) == len(got) and all(p in pairs for p in got)
    assert all((j - i) % n in (1, n - 1) for i, j in got)
    covered = {v for p in got for v in p}
    if n <= 2 * 16:
        assert covered == set(range(n)) and -(-n // 2) <= len(got) <= n - 1
    else:
        assert len(got) == 16
    first = band_pairs(views, pairs, n=1)  # the best-scored pair, always the first one taken
    assert len(first) == 1 and first[0] in got


def test_band_pairs_on_an_aerial_grid_take_neighbours_not_a_far_camera_looking_alike():
    """A nadir grid (every camera looks down, so their angles differ by noise only): the distance between
    the centres keeps the pairs to neighbours. Two cameras at one place looking opposite ways (a rig) are not a pair
    while a camera nearby looks the same way."""
    rng = np.random.default_rng(3)
    views = []
    for r in range(4):
        for c in range(4):
            d = np.array([0.0, 1.0, 0.0]) + rng.normal(0, 0.02, 3)
            views.append(_look([10.0 * c, -50.0, 10.0 * r], d, f"{r}{c}.png", len(views) + 1))
    got = band_pairs(views, exhaustive_pairs(16))
    step = [np.linalg.norm(views[i].center - views[j].center) for i, j in got]
    assert {v for p in got for v in p} == set(range(16)) and max(step) <= 10.0 * np.sqrt(2) + 1e-9
    # a rig: cameras 0 and 1 at the origin, back to back; camera 2 beside 0, looking its way
    rig = [_look([0, 0, 0], [0, 0, 1], "a.png", 1), _look([0, 0, 0], [0, 0, -1], "b.png", 2),
           _look([0.5, 0, 0], [0, 0, 1], "c.png", 3), _look([0.5, 0, 0], [0, 0, -1], "d.png", 4)]
    assert band_pairs(rig, exhaustive_pairs(4)) == [(0, 2), (1, 3)]


def test_band_pairs_edge_cases():
    views = [_look([k, 0, 0], [0, 0, 1], f"{k}.png", k + 1) for k in range(5)]
    assert band_pairs(views, []) == [] and band_pairs(views, exhaustive_pairs(5), n=0) == []
    assert band_pairs(views, [(3, 4)]) == [(3, 4)]
    assert band_pairs(views, [(0, 4), (1, 2)]) == [(0, 4), (1, 2)]  # every image of the list, whatever the rank
