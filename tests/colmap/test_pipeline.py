"""Posed collections into a COLMAP database (issue 7), on a 4-view synthetic set built here."""

import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")

from episeg_cv import colmap, scenes  # noqa: E402
from episeg_cv.colmap import (FeatureStore, View, exhaustive_pairs,  # noqa: E402
                              )
from episeg_cv.colmap.poses import camera_of  # noqa: E402
from episeg_cv.colmap import pipeline as pipeline_module  # noqa: E402
from episeg_cv.colmap import runner as runner_module  # noqa: E402
from episeg_cv.features import PRESETS  # noqa: E402

pycolmap.logging.minloglevel = 2
SIZE = (480, 360)


# --------------------------------------------------------------------------------------
# Fixtures: one rendered set, one reference run
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def collection():
    return scenes.make_collection(4, image_size=SIZE)


@pytest.fixture(scope="module")
def folder(collection, tmp_path_factory):
    root = tmp_path_factory.mktemp("room")
    paths = colmap.save_collection(collection, root)
    return paths


@pytest.fixture(scope="module")
def reference(folder, tmp_path_factory):
    """One full run with the defaults (segment, depth_range auto, track consensus, every core)."""
    db = tmp_path_factory.mktemp("ref") / "ref.db"
    report = colmap.match_model(folder["model"], folder["images"], db)
    return db, report, colmap.read_database_matches(db)


@pytest.fixture(scope="module")
def reference_pairs(folder, tmp_path_factory):
    """The same with each pair verified on its own (``verify="pairs"``)."""
    db = tmp_path_factory.mktemp("ref_pairs") / "ref.db"
    report = colmap.match_model(folder["model"], folder["images"], db, verify="pairs")
    return db, report, colmap.read_database_matches(db)


def _same(a, b):
    assert a.keys() == b.keys()
    for k in a:
        assert np.array_equal(a[k][0], b[k][0]) and np.array_equal(a[k][1], b[k][1]), k


def _accuracy(rec, c):
    """Fraction of 3D points within 1 % of the rendered depth, in every image of their track."""
    ok = []
    for pt in rec.points3D.values():
        good = True
        for el in pt.track.elements:
            k = el.image_id - 1
            Xc = c.R[k] @ pt.xyz + c.t[k]
            x, y = np.clip(np.rint((c.K @ Xc)[:2] / Xc[2]).astype(int), 0, [SIZE[0] - 1, SIZE[1] - 1])
            good &= abs(c.depths[k][y, x] - Xc[2]) <= 0.01 * Xc[2]
        ok.append(good)
    return float(np.mean(ok))


# --------------------------------------------------------------------------------------
# The database and the triangulation
# --------------------------------------------------------------------------------------
def test_database_is_written(folder, reference, collection):
    db_path, report, matches = reference
    assert report.n_images == 4 and report.n_pairs == 6 and report.n_skipped == 0 and report.n_pairs_done == 6
    assert report.n_matches > 300 and 0 < report.n_inliers <= report.n_matches
    assert len(matches) == 6
    db = pycolmap.Database.open(str(db_path))
    try:
        assert db.num_cameras() == 1 and db.num_images() == 4 and db.num_rigs() == 1 and db.num_frames() == 4
        assert {im.name: im.image_id for im in db.read_all_images()} == {n: k + 1 for k, n in
                                                                          enumerate(collection.names)}
        store = FeatureStore(db_path.with_name(db_path.name + ".features"), folder["images"])
        views, _ = colmap.load_model(folder["model"])
        for v in views:  # COLMAP's convention: top-left pixel centre at (0.5, 0.5)
            kp = np.asarray(db.read_keypoints(v.image_id))[:, :2]
            np.testing.assert_allclose(kp, store.load(v)[0] + 0.5, atol=1e-4)
        tvg = db.read_two_view_geometry(1, 2)
        assert tvg.config == pycolmap.TwoViewGeometryConfiguration.CALIBRATED
        g = collection.geometry(0, 1)
        E = tvg.E / np.linalg.norm(tvg.E)
        np.testing.assert_allclose(E, g.essential_matrix / np.linalg.norm(g.essential_matrix), atol=1e-9)
        np.testing.assert_allclose(tvg.cam2_from_cam1.rotation.matrix(), g.R, atol=1e-9)
        np.testing.assert_allclose(tvg.cam2_from_cam1.translation, g.t, atol=1e-9)
        # F in COLMAP's pixels: x_colmap = x + 0.5, so F_colmap = T^-T F T^-1 with T the shift by +0.5
        shift = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])
        F = shift.T @ g.fundamental_matrix @ shift
        np.testing.assert_allclose(tvg.F / np.linalg.norm(tvg.F), F / np.linalg.norm(F), atol=1e-9)
    finally:
        db.close()


def test_matches_lie_on_their_segments(folder, reference):
    """Every written inlier satisfies the constraint in both directions (a cheap re-check)."""
    from episeg_cv import filter_pairs

    db_path, _, matches = reference
    views, rec = colmap.load_model(folder["model"])
    views = {v.name: v for v in colmap.auto_depth_ranges(views, rec)}
    store = FeatureStore(db_path.with_name(db_path.name + ".features"), folder["images"])
    for (a, b), (_, inl) in matches.items():
        va, vb = views[a], views[b]
        qa, qb = store.load(va)[1], store.load(vb)[1]
        pairs = inl.astype(np.intp)
        assert filter_pairs(pairs, qa, qb, va.geometry_to(vb), depth_range=va.depth_range).all()
        assert filter_pairs(pairs[:, ::-1], qb, qa, vb.geometry_to(va), depth_range=vb.depth_range).all()


def test_triangulation_is_accurate(folder, reference, collection, tmp_path):
    db_path, _, _ = reference
    rec = colmap.triangulate(db_path, folder["model"], folder["images"], tmp_path / "tri")
    assert rec.num_points3D() > 100
    assert rec.compute_mean_reprojection_error() < 1.0
    assert _accuracy(rec, collection) > 0.9
    assert (tmp_path / "tri" / "points3D.bin").is_file()


def test_track_consensus_keeps_more_true_matches_than_the_pair_rule(folder, reference, reference_pairs,
                                                                     collection, tmp_path):
    """Against ground truth from the rendered depth: more correct inliers at about the same precision."""
    db_t, rep_t, m_t = reference
    db_p, rep_p, m_p = reference_pairs
    assert rep_t.verify["mode"] == "tracks" and rep_t.verify["kept"] == rep_t.n_inliers
    assert rep_p.verify == {"mode": "pairs"} and "track consensus" not in rep_p.summary()
    assert "track consensus" in rep_t.summary()
    views, rec = colmap.load_model(folder["model"])
    index = {v.name: k for k, v in enumerate(views)}
    store = FeatureStore(db_t.with_name(db_t.name + ".features"), folder["images"])
    stats = {}
    for label, matches in (("tracks", m_t), ("pairs", m_p)):
        good = total = 0
        for (a, b), (_, inl) in matches.items():
            i, j = index[a], index[b]
            p1, p2 = store.load(views[i])[1], store.load(views[j])[1]
            gt = scenes.ground_truth_matches(p1, p2, collection.depths[i], collection.depths[j],
                                             collection.geometry(i, j))
            good += int(gt.is_correct(inl.astype(np.intp)).sum())
            total += len(inl)
        stats[label] = (good, good / total)
    assert stats["tracks"][0] > stats["pairs"][0]
    assert stats["tracks"][1] > stats["pairs"][1] - 0.03
    rec_t = colmap.triangulate(db_t, folder["model"], folder["images"], tmp_path / "t")
    rec_p = colmap.triangulate(db_p, folder["model"], folder["images"], tmp_path / "p")
    assert rec_t.num_points3D() >= rec_p.num_points3D() and _accuracy(rec_t, collection) > 0.9


def test_report_times_its_stages(reference, reference_pairs):
    """``seconds_matching`` splits into the band, the pairs, the consensus and the writes (the summary shows
    them); with ``verify="pairs"`` there is no consensus, and the writes come with the pairs."""
    for (_, rep, _), consensus in ((reference, True), (reference_pairs, False)):
        stages = [rep.seconds_band, rep.seconds_pairs, rep.seconds_verify, rep.seconds_write]
        assert all(t >= 0 for t in stages) and rep.seconds_band > 0 and rep.seconds_pairs > 0 and rep.seconds_write > 0
        assert (rep.seconds_verify > 0) == consensus
        assert sum(stages) <= rep.seconds_matching <= sum(stages) + 0.05 + 0.1 * rep.seconds_matching
        assert f"pairs {rep.seconds_pairs:.2f} s, consensus {rep.seconds_verify:.2f} s" in rep.summary()


def test_poses_json_gives_the_same_matches_as_the_model(folder, reference, tmp_path):
    db = tmp_path / "json.db"
    report = colmap.match_model(folder["poses"], folder["images"], db, depth_range="none")
    ref = colmap.match_model(folder["model"], folder["images"], tmp_path / "model.db", depth_range="none")
    assert report.n_matches == ref.n_matches
    _same(colmap.read_database_matches(db), colmap.read_database_matches(tmp_path / "model.db"))
    rec = colmap.triangulate(db, folder["poses"], folder["images"], tmp_path / "tri")
    assert rec.num_points3D() > 100


def test_text_model_reads_like_the_binary_one(folder, tmp_path):
    rec = pycolmap.Reconstruction(str(folder["model"]))
    (tmp_path / "text").mkdir()
    rec.write_text(str(tmp_path / "text"))
    assert (tmp_path / "text" / "images.txt").is_file()
    a, rec_a = colmap.load_model(folder["model"])
    b, rec_b = colmap.load_model(tmp_path / "text")
    assert [v.name for v in a] == [v.name for v in b]
    for va, vb in zip(a, b):
        np.testing.assert_allclose(va.R, vb.R, atol=1e-12)
        np.testing.assert_allclose(va.K, vb.K)
    assert [v.depth_range for v in colmap.auto_depth_ranges(a, rec_a)] == \
        [v.depth_range for v in colmap.auto_depth_ranges(b, rec_b)]


def test_line_constraint_keeps_at_least_the_segment_matches_count(folder, tmp_path):
    seg = colmap.match_model(folder["model"], folder["images"], tmp_path / "s.db", depth_range="none")
    line = colmap.match_model(folder["model"], folder["images"], tmp_path / "l.db", constraint="line",
                              depth_range="none")
    assert seg.n_matches > 0 and line.n_matches > 0
    L = seg.search_length
    assert L["segment_in_depth_range"] == pytest.approx(L["segment"])  # depth_range "none"
    assert 0 < L["segment"] < L["line"]


# --------------------------------------------------------------------------------------
# Resume, interruption, workers, Dask
# --------------------------------------------------------------------------------------
def test_resume_after_a_partial_run_gives_the_same_database(folder, reference, reference_pairs, tmp_path):
    pairs_file = tmp_path / "pairs.txt"
    pairs_file.write_text("view_000.png view_001.png\nview_002.png view_003.png\n")
    # pairs verified on their own: the pairs written are skipped
    db = tmp_path / "part.db"
    part = colmap.match_model(folder["model"], folder["images"], db, pairs=pairs_file, verify="pairs")
    assert part.n_pairs_done == 2
    rest = colmap.match_model(folder["model"], folder["images"], db, resume=True, verify="pairs")
    assert rest.n_skipped == 2 and rest.n_pairs_done == 4
    _same(colmap.read_database_matches(db), reference_pairs[2])
    again = colmap.match_model(folder["model"], folder["images"], db, resume=True, verify="pairs")
    assert again.n_pairs_done == 0 and again.n_skipped == 6
    # the track consensus sees every pair: the first two, verified on a smaller graph, are rewritten
    db = tmp_path / "part_tracks.db"
    colmap.match_model(folder["model"], folder["images"], db, pairs=pairs_file)
    rest = colmap.match_model(folder["model"], folder["images"], db, resume=True)
    assert rest.n_skipped + rest.n_pairs_done == 6 and rest.n_pairs_done >= 4
    _same(colmap.read_database_matches(db), reference[2])
    again = colmap.match_model(folder["model"], folder["images"], db, resume=True)
    assert again.n_pairs_done == 0 and again.n_skipped == 6


@pytest.mark.parametrize("verify, stage", [("pairs", "pairs"), ("tracks", "write"), ("tracks", "pairs")])
def test_interrupted_run_leaves_a_usable_database(folder, reference, reference_pairs, tmp_path, monkeypatch, verify,
                                                  stage):
    db = tmp_path / "int.db"
    monkeypatch.setattr(pipeline_module, "WRITE_BLOCK", 1)  # after the consensus: a transaction per pair

    def stop_after_two(s, done, total):
        if s == stage and done == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        colmap.match_model(folder["model"], folder["images"], db, progress=stop_after_two, verify=verify)
    written = colmap.read_database_matches(db)
    # whole pairs only; with the consensus nothing is written while the pairs are matched
    assert len(written) == (0 if (verify, stage) == ("tracks", "pairs") else 2)
    rest = colmap.match_model(folder["model"], folder["images"], db, resume=True, verify=verify)
    assert rest.n_skipped == len(written)
    _same(colmap.read_database_matches(db), (reference_pairs if verify == "pairs" else reference)[2])


@pytest.mark.parametrize("stop_at, written", [(2, 0), (4, 4), (5, 4)])
def test_consensus_writes_whole_blocks(folder, reference, tmp_path, monkeypatch, stop_at, written):
    """The consensus's pairs go to the database in transactions of WRITE_BLOCK pairs: an interrupt keeps
    whole blocks, and the resumed run gives the uninterrupted database."""
    monkeypatch.setattr(pipeline_module, "WRITE_BLOCK", 4)
    db = tmp_path / "blocks.db"

    def stop(s, done, total):
        if s == "write" and done == stop_at:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        colmap.match_model(folder["model"], folder["images"], db, progress=stop)
    assert len(colmap.read_database_matches(db)) == written
    rest = colmap.match_model(folder["model"], folder["images"], db, resume=True)
    assert rest.n_skipped == written and rest.n_pairs_done == 6 - written
    _same(colmap.read_database_matches(db), reference[2])


@pytest.mark.parametrize("verify", ["pairs", "tracks"])
def test_resume_redoes_a_pair_with_matches_but_no_geometry(folder, reference, reference_pairs, tmp_path, verify):
    """What an exception inside pycolmap's transaction (which commits on exit) would leave behind."""
    db_path = tmp_path / "orphan.db"
    colmap.match_model(folder["model"], folder["images"], db_path, pairs=[("view_000.png", "view_001.png")],
                       verify=verify)
    db = pycolmap.Database.open(str(db_path))
    db.write_matches(1, 3, np.array([[0, 0], [1, 1]], dtype=np.uint32))  # no two-view geometry
    db.close()
    rest = colmap.match_model(folder["model"], folder["images"], db_path, resume=True, verify=verify)
    if verify == "pairs":
        assert rest.n_skipped == 1 and rest.n_pairs_done == 5
    else:
        assert rest.n_skipped + rest.n_pairs_done == 6
    _same(colmap.read_database_matches(db_path), (reference_pairs if verify == "pairs" else reference)[2])


def test_two_workers_give_identical_matches(folder, reference, tmp_path):
    report = colmap.match_model(folder["model"], folder["images"], tmp_path / "w2.db", workers=2,
                                cache_dir=tmp_path / "cache")
    assert report.runner == "2 threads"
    _same(colmap.read_database_matches(tmp_path / "w2.db"), reference[2])


def test_one_worker_is_one_core_and_the_default_every_core(folder, reference, tmp_path):
    cores = runner_module.available_cores()
    assert reference[1].runner == (f"{cores} threads" if cores > 1 else "this process, one core")
    report = colmap.match_model(folder["model"], folder["images"], tmp_path / "w1.db", workers=1,
                                cache_dir=tmp_path / "cache")
    assert report.runner == "this process, one core"
    _same(colmap.read_database_matches(tmp_path / "w1.db"), reference[2])


def test_local_dask_cluster_gives_identical_matches(folder, reference, tmp_path):
    pytest.importorskip("distributed")
    report = colmap.match_model(folder["model"], folder["images"], tmp_path / "dask.db", scheduler="local:2")
    assert "Dask" in report.runner
    _same(colmap.read_database_matches(tmp_path / "dask.db"), reference[2])


def test_dask_cluster_of_separate_worker_processes(folder, reference, tmp_path):
    """The documented recipe, on loopback: ``dask scheduler`` and two ``dask worker ADDRESS`` processes.

    Bounded: the scheduler stops after 120 s idle and the workers after 300 s whatever happens, and
    every process started here is ended at the end of the test.
    """
    pytest.importorskip("distributed")
    import json
    import time

    dask = shutil.which("dask", path=str(Path(sys.executable).parent)) or shutil.which("dask")
    if dask is None:
        pytest.skip("the dask command is not installed")
    info = tmp_path / "scheduler.json"
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--dashboard-address", "127.0.0.1:0",
                               "--scheduler-file", str(info), "--idle-timeout", "120s"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        for _ in range(600):
            if info.is_file() and info.stat().st_size:
                break
            time.sleep(0.1)
        address = json.loads(info.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        for k in range(2):
            procs.append(subprocess.Popen([dask, "worker", address, "--host", "127.0.0.1", "--nworkers", "1",
                                           "--nthreads", "1", "--no-dashboard", "--lifetime", "300s",
                                           "--death-timeout", "60s", "--name", f"w{k}"],
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        import distributed

        with distributed.Client(address, timeout="30s") as client:
            client.wait_for_workers(2, timeout=120)
        report = colmap.match_model(folder["model"], folder["images"], tmp_path / "cluster.db", scheduler=address,
                                    cache_dir=tmp_path / "cache")
        assert report.runner == f"the Dask cluster at {address}"
        _same(colmap.read_database_matches(tmp_path / "cluster.db"), reference[2])
        # the workers serve other clients too: they outlive the run
        assert all(p.poll() is None for p in procs)
    finally:
        for p in procs[::-1]:
            p.terminate()
        for p in procs[::-1]:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()


def test_feature_cache_is_reused_and_refreshed(folder, tmp_path):
    shutil.copytree(folder["images"], tmp_path / "images")
    views, _ = colmap.load_model(folder["model"])
    store = FeatureStore(tmp_path / "cache", tmp_path / "images", PRESETS["collection"].replace(max_features=500))
    n = store.ensure(views[0])
    mtime = store.path(views[0]).stat().st_mtime_ns
    assert store.ensure(views[0]) == n and store.path(views[0]).stat().st_mtime_ns == mtime  # a cache hit
    img = cv2.imread(str(tmp_path / "images" / views[0].name), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(tmp_path / "images" / views[0].name), img[:, ::-1])  # a changed image is recomputed
    store.ensure(views[0])
    assert store.path(views[0]).stat().st_mtime_ns != mtime
    assert not list((tmp_path / "cache").glob("*.tmp.npz"))


def test_loaded_features_stay_in_memory_within_the_budget(folder, tmp_path, monkeypatch):
    """Each pair loads two images: with 8 images in memory at most, an exhaustive order over more than 8
    images read each file once per pair (dinoSparseRing: 139 reads for 16 images); now once per image,
    as long as the collection fits the byte budget, and least recently used first out beyond it."""
    from episeg_cv.colmap import store as store_module

    views, _ = colmap.load_model(folder["model"])
    store = FeatureStore(tmp_path / "cache", folder["images"], PRESETS["collection"].replace(max_features=300))
    for v in views:
        store.ensure(v)
    monkeypatch.setattr(store_module, "_loaded", store_module.collections.OrderedDict())
    reads = []
    real_load = np.load
    monkeypatch.setattr(store_module.np, "load", lambda *a, **k: reads.append(1) or real_load(*a, **k))
    for i, j in exhaustive_pairs(len(views)):
        store.load(views[i]), store.load(views[j])
    assert len(reads) == len(views)
    smallest = min(sum(a.nbytes for a in store.load(v)) for v in views)
    monkeypatch.setattr(store_module, "MEMORY_BUDGET", 2 * smallest)  # room for two images at most
    store_module._loaded.clear()
    reads.clear()
    for v in views + views:
        a = store.load(v)
        assert not a[2].flags.writeable
    assert len(reads) == 2 * len(views) and len(store_module._loaded) <= 2


def test_a_checked_cache_file_is_read_once(folder, tmp_path, monkeypatch):
    """ensure() reads a fresh cache file whole to check it: load() then takes those arrays (a Dask worker
    that checked an image in the features step matches it without reading it again)."""
    from episeg_cv.colmap import store as store_module

    views, _ = colmap.load_model(folder["model"])
    store = FeatureStore(tmp_path / "cache", folder["images"], PRESETS["collection"].replace(max_features=300))
    first = [store.ensure(v) for v in views]  # computed and written
    monkeypatch.setattr(store_module, "_loaded", store_module.collections.OrderedDict())
    reads = []
    real_load = np.load
    monkeypatch.setattr(store_module.np, "load", lambda *a, **k: reads.append(1) or real_load(*a, **k))
    assert [store.ensure(v) for v in views] == first and len(reads) == len(views)  # checked: one read each
    for v in views:
        kp, pin, des = store.load(v)
        assert len(kp) == first[views.index(v)][0] and not des.flags.writeable
    assert len(reads) == len(views)  # and no second read


# --------------------------------------------------------------------------------------
# Pairs, overlap, depth ranges (hand-made views)
# --------------------------------------------------------------------------------------
def test_auto_depth_ranges_keep_the_true_matches(folder, reference, collection):
    """The ranges shrink the segments, yet (nearly) every true match of every pair stays on its segment."""
    from episeg_cv import filter_pairs

    views, rec = colmap.load_model(folder["model"])
    ranged = colmap.auto_depth_ranges(views, rec)
    assert all(0 < v.depth_range[0] and np.isfinite(v.depth_range[1]) for v in ranged)
    store = FeatureStore(reference[0].with_name(reference[0].name + ".features"), folder["images"])
    kept = total = 0
    for i, j in exhaustive_pairs(len(ranged)):
        p1, p2 = store.load(ranged[i])[1], store.load(ranged[j])[1]
        gt = scenes.ground_truth_matches(p1, p2, collection.depths[i], collection.depths[j],
                                         collection.geometry(i, j))
        true = np.flatnonzero(gt.matchable)
        pairs = np.column_stack([true, gt.match[true]])
        g = ranged[i].geometry_to(ranged[j])
        kept += filter_pairs(pairs, p1, p2, g, depth_range=ranged[i].depth_range, tol=3.0).sum()
        total += len(pairs)
    assert total > 1000 and kept / total > 0.98
    L = reference[1].search_length
    assert L["segment_in_depth_range"] < 0.8 * L["segment"] < 0.8 * L["line"]


def test_undistort_inverts_opencv_distortion():
    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    dist = np.array([-0.2, 0.05, 0.001, -0.002])
    model, params = camera_of(K, (320, 240), dist)
    v = View("d", 1, 1, K, np.eye(3), [0, 0, 0], (320, 240), model, params)
    rng = np.random.default_rng(1)
    pin = rng.uniform([20, 20], [300, 220], (50, 2))
    rays = np.column_stack([(pin - K[:2, 2]) / [K[0, 0], K[1, 1]], np.ones(50)])
    raw, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, dist)
    np.testing.assert_allclose(v.undistort(raw.reshape(-1, 2)), pin, atol=1e-3)
    assert model == "OPENCV" and np.array_equal(View("p", 1, 1, K, np.eye(3), [0, 0, 0], (320, 240))
                                                 .undistort(pin), pin)


# --------------------------------------------------------------------------------------
# Bad input: a clear error, nothing half-written
# --------------------------------------------------------------------------------------
def test_missing_image_is_refused(folder, tmp_path):
    shutil.copytree(folder["images"], tmp_path / "images")
    (tmp_path / "images" / "view_002.png").unlink()
    with pytest.raises(ValueError, match="image 'view_002.png' of the model is missing"):
        colmap.match_model(folder["model"], tmp_path / "images", tmp_path / "x.db")
    assert not (tmp_path / "x.db").exists()


def test_unknown_image_in_pairs_file_names_the_line(folder, tmp_path):
    f = tmp_path / "pairs.txt"
    f.write_text("view_000.png view_001.png\n\nview_000.png ghost.png\n")
    with pytest.raises(ValueError, match=r"pairs.txt:3: unknown image 'ghost.png'"):
        colmap.match_model(folder["model"], folder["images"], tmp_path / "x.db", pairs=f)
    assert not (tmp_path / "x.db").exists()


def test_model_without_registered_images_is_refused(tmp_path):
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=10, height=10, params=[5, 5, 5, 5],
                                                    camera_id=1))
    (tmp_path / "model").mkdir()
    rec.write(str(tmp_path / "model"))
    with pytest.raises(ValueError, match="no registered images"):
        colmap.match_model(tmp_path / "model", tmp_path, tmp_path / "x.db")
    with pytest.raises(ValueError, match="holds no COLMAP model"):
        colmap.load_model(tmp_path)


@pytest.mark.parametrize("name", ["nope", "nope.txt", "poses.json"])
def test_missing_model_is_named_as_any_model_kind(tmp_path, name):
    # a missing *_par.txt or JSON is not called a "model folder"
    with pytest.raises(ValueError, match=r"model '.*" + name.replace(".", r"\.") + r"' does not exist \(expected a "
                                         r"COLMAP model folder, a poses JSON or a Middlebury \*_par\.txt\)"):
        colmap.match_model(tmp_path / name, tmp_path, tmp_path / "x.db")
    assert not (tmp_path / "x.db").exists()


def test_database_path_problems(folder, reference, tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        colmap.match_model(folder["model"], folder["images"], tmp_path / "nowhere" / "x.db")
    with pytest.raises(ValueError, match="is a folder"):
        colmap.match_model(folder["model"], folder["images"], tmp_path)
    existing = tmp_path / "old.db"
    existing.write_bytes(b"keep me")
    with pytest.raises(ValueError, match="exists; pass --overwrite"):
        colmap.match_model(folder["model"], folder["images"], existing)
    assert existing.read_bytes() == b"keep me"
    with pytest.raises(ValueError, match="nothing to resume"):
        colmap.match_model(folder["model"], folder["images"], tmp_path / "new.db", resume=True)
    with pytest.raises(ValueError, match="exclude each other"):
        colmap.match_model(folder["model"], folder["images"], existing, resume=True, overwrite=True)
    colmap.match_model(folder["model"], folder["images"], existing, overwrite=True)
    _same(colmap.read_database_matches(existing), reference[2])


def test_unwritable_database_path_is_refused(folder, tmp_path, monkeypatch):
    import os

    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if mode == os.W_OK else real(p, mode))
    with pytest.raises(ValueError, match="is not writable"):
        colmap.match_model(folder["model"], folder["images"], tmp_path / "x.db")
    assert not (tmp_path / "x.db").exists()


def test_resume_refuses_a_database_of_other_features(folder, reference, tmp_path):
    db = tmp_path / "r.db"
    shutil.copy(reference[0], db)
    with pytest.raises(ValueError, match="features.max_features was 8192, now 100"):
        colmap.match_model(folder["model"], folder["images"], db, resume=True,
                           features=PRESETS["collection"].replace(max_features=100))


def test_unreachable_scheduler_fails_fast(folder, tmp_path, monkeypatch):
    pytest.importorskip("distributed")
    monkeypatch.setattr(runner_module, "CONNECT_TIMEOUT", 1.0)
    with pytest.raises(ConnectionError, match="cannot reach the Dask scheduler at 'tcp://127.0.0.1:9'"):
        colmap.match_model(folder["model"], folder["images"], tmp_path / "x.db", scheduler="tcp://127.0.0.1:9")
    assert not (tmp_path / "x.db").exists()


@pytest.mark.parametrize("kwargs, match", [
    ({"constraint": "none"}, "constraint"), ({"constraint": "arc"}, "constraint"), ({"features": "surf"}, "features"),
    ({"tol": -1}, "tol"), ({"tol": float("inf")}, "tol"), ({"workers": 0}, "workers"),
    ({"depth_range": "near"}, "depth_range"),
    ({"depth_range": (5, 1)}, "zmin < zmax"), ({"pairs": [("view_000.png", "x")]}, "unknown image 'x'"),
    ({"pairs": [("view_000.png", "view_001.png")], "neighbors": 2}, "not both"),
    ({"scheduler": "local:zero"}, "local:N"),
])
def test_bad_options(folder, tmp_path, kwargs, match):
    with pytest.raises(ValueError, match=match):
        colmap.match_model(folder["model"], folder["images"], tmp_path / "x.db", **kwargs)
    assert not (tmp_path / "x.db").exists()


def test_exhaustive_pairing_warns_for_large_collections(folder, tmp_path, monkeypatch):
    monkeypatch.setattr(pipeline_module, "EXHAUSTIVE_WARN", 3)
    notes = []
    colmap.match_model(folder["model"], folder["images"], tmp_path / "x.db", log=notes.append)
    assert any("exhaustive matching of 4 images" in n for n in notes)


def test_auto_depth_range_without_points_warns_and_says_how_to_choose(folder, tmp_path):
    """A poses JSON has no 3D points: 'auto' falls back to (0, inf) and says which settings choose that (or
    bounds) without the warning; depth_range='none' gives no warning."""
    notes = []
    colmap.match_model(folder["poses"], folder["images"], tmp_path / "a.db", log=notes.append)
    warned = [n for n in notes if "depth_range 'auto' needs" in n]
    assert len(warned) == 1 and "--depth-range none" in warned[0] and "ZMIN ZMAX" in warned[0]
    notes.clear()
    colmap.match_model(folder["poses"], folder["images"], tmp_path / "b.db", depth_range="none", log=notes.append)
    assert not any("depth_range" in n for n in notes)


def test_neighbors_option_matches_fewer_pairs(folder, tmp_path):
    report = colmap.match_model(folder["model"], folder["images"], tmp_path / "n.db", neighbors=1)
    assert 2 <= report.n_pairs < 6


# --------------------------------------------------------------------------------------
# The CLI
# --------------------------------------------------------------------------------------
def run(*args):
    return subprocess.run([sys.executable, "-m", "episeg_cv.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300)


def test_cli_colmap_and_triangulate(folder, tmp_path):
    r = run("colmap", folder["model"], folder["images"], "--database", tmp_path / "c.db", "--triangulate",
            tmp_path / "tri", "--neighbors", "2")
    assert r.returncode == 0, r.stderr
    assert "matches written" in r.stdout and "triangulated model" in r.stdout and "mean reprojection error" in r.stdout
    assert (tmp_path / "tri" / "points3D.bin").is_file()
    r = run("colmap", folder["model"], folder["images"], "--database", tmp_path / "c.db")
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and "--overwrite" in r.stderr


@pytest.mark.parametrize("extra, match", [
    (["--depth-range", "1"], "--depth-range"),
    (["--pairs", "PAIRS"], "unknown image 'ghost.png'"),
    (["--scheduler", "tcp://127.0.0.1:9"], "cannot reach the Dask scheduler"),
    (["--features", "database"], "does not exist; --features database reads the features from it"),
    (["--features", "database", "--detector", "orb"], "--detector and --max-features apply to --features extract"),
    (["--verify", "pairs", "--loose-ratio", "0.8"], "--loose-ratio applies to --verify tracks"),
    (["--verify", "pairs", "--complete-tracks"], "--complete-tracks applies to --verify tracks"),
    (["--ratio", "0.95", "--loose-ratio", "0.9"], "loose ratio (0.9) must be above the pair rule's ratio (0.95)"),
])
def test_cli_errors_are_one_line(folder, tmp_path, extra, match):
    (tmp_path / "pairs.txt").write_text("view_000.png ghost.png\n")
    extra = [str(tmp_path / "pairs.txt") if e == "PAIRS" else e for e in extra]
    r = run("colmap", folder["model"], folder["images"], "--database", tmp_path / "c.db", *extra)
    assert r.returncode == 1, r.stderr
    assert match in r.stderr and "Traceback" not in r.stderr and r.stderr.count("\n") == 1
    assert not (tmp_path / "c.db").exists()


def test_cli_complete_tracks_adds_to_the_default_matches(folder, tmp_path):
    for name, extra in (("d.db", []), ("c.db", ["--complete-tracks"])):
        r = run("colmap", folder["model"], folder["images"], "--database", tmp_path / name, "--neighbors", "2", *extra)
        assert r.returncode == 0, r.stderr
    plain, completed = colmap.read_database_matches(tmp_path / "d.db"), colmap.read_database_matches(tmp_path / "c.db")
    assert plain.keys() == completed.keys()
    assert sum(len(v[1]) for v in completed.values()) >= sum(len(v[1]) for v in plain.values()) > 0


def test_cli_synthetic(tmp_path):
    r = run("synthetic", tmp_path / "s", "--views", "2", "--size", "64", "48")
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in (tmp_path / "s" / "images").iterdir()) == ["view_000.png", "view_001.png"]
    views, _ = colmap.load_model(tmp_path / "s" / "model")
    assert [v.name for v in views] == ["view_000.png", "view_001.png"]
    assert len(colmap.load_poses(tmp_path / "s" / "poses.json")) == 2


def test_readme_colmap_example_runs(tmp_path, monkeypatch, capsys):
    import re
    from pathlib import Path

    readme = Path(__file__).resolve().parents[2] / "README.md"
    if not readme.exists():
        pytest.skip("README.md not present")
    blocks = [b for b in re.findall(r"```python\n(.*?)```", readme.read_text(), flags=re.S) if "colmap." in b]
    assert len(blocks) == 1
    monkeypatch.chdir(tmp_path)
    colmap.save_collection(scenes.make_collection(4, image_size=(320, 240)), "room")
    exec(compile(blocks[0], str(readme), "exec"), {})  # noqa: S102 - our own README
    out = capsys.readouterr().out
    assert "matches written" in out
    n_points, error = out.strip().splitlines()[-1].split()
    assert int(n_points) > 20 and float(error) < 1.0


