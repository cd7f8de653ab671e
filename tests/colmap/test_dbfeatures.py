"""COLMAP's own features reused (issue 14): ``match_model(..., features="database")`` and ``--features database``.

The database is made here by ``pycolmap.extract_features``, in two calls so that its image ids are not the
model's, with COLMAP's default camera (SIMPLE_RADIAL, a guessed focal length), as a user would make it.
"""

import shutil
import subprocess
import sys

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")

from episeg_cv import colmap, filter_pairs, scenes  # noqa: E402
from episeg_cv.colmap import pipeline as pipeline_module  # noqa: E402
from episeg_cv.colmap.dbfeatures import read_database_features  # noqa: E402

pycolmap.logging.minloglevel = 2
SIZE = (400, 300)


@pytest.fixture(scope="module")
def collection():
    return scenes.make_collection(4, image_size=SIZE, seed=2)


@pytest.fixture(scope="module")
def folder(collection, tmp_path_factory):
    return colmap.save_collection(collection, tmp_path_factory.mktemp("room"))


@pytest.fixture(scope="module")
def features_db(folder, tmp_path_factory):
    """Features only; images 2 and 3 first, so that the ids differ from the model's."""
    db = tmp_path_factory.mktemp("features") / "features.db"
    options = pycolmap.FeatureExtractionOptions()
    options.num_threads = 1
    for names in (["view_002.png", "view_003.png"], ["view_000.png", "view_001.png"]):
        pycolmap.extract_features(str(db), str(folder["images"]), image_names=names, extraction_options=options,
                                  device=pycolmap.Device.cpu)
    return db


@pytest.fixture(scope="module")
def matched(folder, features_db, tmp_path_factory):
    """One run with the defaults on a copy of the features database."""
    db = tmp_path_factory.mktemp("matched") / "db.db"
    shutil.copyfile(features_db, db)
    notes = []
    report = colmap.match_model(folder["model"], folder["images"], db, features="database", log=notes.append)
    return db, report, notes


def _ids(db_path):
    db = pycolmap.Database.open(str(db_path))
    try:
        return {im.name: im.image_id for im in db.read_all_images()}
    finally:
        db.close()


def _features(db_path):
    db = pycolmap.Database.open(str(db_path))
    try:
        return {im.name: (np.asarray(db.read_keypoints(im.image_id)).copy(),
                          np.asarray(db.read_descriptors(im.image_id).data).copy()) for im in db.read_all_images()}
    finally:
        db.close()


def _same(a, b):
    assert a.keys() == b.keys()
    for k in a:
        assert np.array_equal(a[k][0], b[k][0]) and np.array_equal(a[k][1], b[k][1]), k


def test_features_are_read_in_episeg_conventions(features_db):
    db = pycolmap.Database.open(str(features_db))
    try:
        raw = np.asarray(db.read_keypoints(1))
        raw_des = np.asarray(db.read_descriptors(1).data)
    finally:
        db.close()
    kp, des = read_database_features(features_db, 1)
    np.testing.assert_array_equal(des * 512, raw_des)
    np.testing.assert_allclose(kp, raw[:, :2] - 0.5)  # COLMAP's (0.5, 0.5) pixel centre -> (0, 0)
    assert des.dtype == np.float32 and des.shape == (len(kp), 128)
    np.testing.assert_allclose(np.linalg.norm(des, axis=1), 1.0, atol=0.01)  # uint8 / 512: unit-norm RootSIFT


def test_matches_are_written_with_the_database_ids(folder, features_db, matched):
    db_path, report, notes = matched
    assert _ids(db_path) == {"view_002.png": 1, "view_003.png": 2, "view_000.png": 3, "view_001.png": 4}
    assert report.features == "database" and report.n_pairs_done == 6 and report.n_inliers > 200
    assert "read from the database" in report.summary()
    _same(_features(db_path), _features(features_db))  # features untouched
    # the camera is set to the model's (the known calibration), with a note
    assert any("set to the model's" in n for n in notes)
    db = pycolmap.Database.open(str(db_path))
    try:
        cams = {c.camera_id: c for c in db.read_all_cameras()}
        assert all(c.model_name == "PINHOLE" for c in cams.values())
        tvg = db.read_two_view_geometry(3, 4)  # view_000 - view_001
        assert tvg.config == pycolmap.TwoViewGeometryConfiguration.CALIBRATED
    finally:
        db.close()
    # every inlier lies on its segment, with the database's keypoints
    views = {v.name: v for v in colmap.load_model(folder["model"])[0]}
    feats = {n: k[:, :2].astype(np.float64) - 0.5 for n, (k, _) in _features(db_path).items()}
    for (a, b), (_, inl) in colmap.read_database_matches(db_path).items():
        pairs = inl.astype(np.intp)
        assert filter_pairs(pairs, feats[a], feats[b], views[a].geometry_to(views[b])).all()


def test_triangulation_uses_the_database_ids(folder, matched, collection, tmp_path):
    db_path, _, _ = matched
    rec = colmap.triangulate(db_path, folder["model"], folder["images"], tmp_path / "tri")
    assert rec.num_points3D() > 50 and rec.compute_mean_reprojection_error() < 1.0
    assert {im.name: iid for iid, im in rec.images.items()} == _ids(db_path)
    good = 0
    for pt in rec.points3D.values():
        k = int(rec.image(pt.track.elements[0].image_id).name[5:8])
        Xc = collection.R[k] @ pt.xyz + collection.t[k]
        x, y = np.clip(np.rint((collection.K @ Xc)[:2] / Xc[2]).astype(int), 0, [SIZE[0] - 1, SIZE[1] - 1])
        good += abs(collection.depths[k][y, x] - Xc[2]) <= 0.01 * Xc[2]
    assert good / rec.num_points3D() > 0.85


def test_a_database_with_matches_needs_resume_or_overwrite(folder, features_db, matched, tmp_path):
    db_path, _, _ = matched
    db = tmp_path / "again.db"
    shutil.copyfile(db_path, db)
    with pytest.raises(ValueError, match="already holds matches.*--overwrite"):
        colmap.match_model(folder["model"], folder["images"], db, features="database")
    again = colmap.match_model(folder["model"], folder["images"], db, features="database", resume=True)
    assert again.n_skipped == 6 and again.n_pairs_done == 0
    # overwrite: matches and geometries replaced, features kept
    ref = colmap.read_database_matches(db_path)
    over = colmap.match_model(folder["model"], folder["images"], db, features="database", overwrite=True,
                              verify="pairs")
    assert over.n_pairs_done == 6
    assert colmap.read_database_matches(db).keys() == ref.keys()
    _same(_features(db), _features(features_db))
    # COLMAP's own matches (no run record of ours) cannot be resumed
    theirs = tmp_path / "theirs.db"
    shutil.copyfile(features_db, theirs)
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = 1
    pycolmap.match_exhaustive(str(theirs), matching_options=options, device=pycolmap.Device.cpu)
    with pytest.raises(ValueError, match="no run record"):
        colmap.match_model(folder["model"], folder["images"], theirs, features="database", resume=True)
    colmap.match_model(folder["model"], folder["images"], theirs, features="database", overwrite=True)
    _same(colmap.read_database_matches(theirs), ref)


def test_interrupted_run_resumes_to_the_same_database(folder, features_db, matched, tmp_path, monkeypatch):
    db = tmp_path / "int.db"
    shutil.copyfile(features_db, db)
    monkeypatch.setattr(pipeline_module, "WRITE_BLOCK", 1)  # a transaction per pair (blocks: test_pipeline.py)

    def stop(stage, done, total):
        if stage == "write" and done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        colmap.match_model(folder["model"], folder["images"], db, features="database", progress=stop)
    assert len(colmap.read_database_matches(db)) == 3
    rest = colmap.match_model(folder["model"], folder["images"], db, features="database", resume=True)
    assert rest.n_skipped == 3 and rest.n_pairs_done == 3
    _same(colmap.read_database_matches(db), colmap.read_database_matches(matched[0]))


@pytest.mark.parametrize("problem, match", [
    ("missing", "does not exist; --features database reads"),
    ("not sqlite", "not an SQLite file"),
    ("image not in database", "image 'view_002.png' of the model is not in database"),
    ("folder", "is a folder"),
])
def test_bad_databases_are_refused(folder, features_db, tmp_path, problem, match):
    db = tmp_path / "x.db"
    if problem == "not sqlite":
        db.write_bytes(b"not a database")
    elif problem == "image not in database":
        options = pycolmap.FeatureExtractionOptions()
        options.num_threads = 1
        pycolmap.extract_features(str(db), str(folder["images"]), image_names=["view_000.png", "view_001.png"],
                                  extraction_options=options, device=pycolmap.Device.cpu)
    elif problem == "folder":
        db = tmp_path
    before = db.read_bytes() if db.is_file() else None
    with pytest.raises(ValueError, match=match):
        colmap.match_model(folder["model"], folder["images"], db, features="database")
    if before is not None:
        assert db.read_bytes() == before  # nothing written


def test_cli_features_database_and_triangulate(folder, features_db, tmp_path):
    db = tmp_path / "c.db"
    shutil.copyfile(features_db, db)
    r = subprocess.run([sys.executable, "-m", "episeg_cv.cli", "colmap", str(folder["model"]), str(folder["images"]),
                        "--database", str(db), "--features", "database", "--triangulate", str(tmp_path / "tri")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "read from the database" in r.stdout and "track consensus" in r.stdout and "triangulated model" in r.stdout
    r = subprocess.run([sys.executable, "-m", "episeg_cv.cli", "colmap", str(folder["model"]), str(folder["images"]),
                        "--database", str(db), "--features", "database"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 1 and "already holds matches" in r.stderr and r.stderr.count("\n") == 1
