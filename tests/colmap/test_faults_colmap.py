"""Regression tests of issue 15 for the COLMAP path: faults lose nothing and leave nothing behind.

Each case failed before the fix (benchmarks/faults.py runs these and hundreds more as a user would).
"""

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")

from episeg_cv import colmap, scenes  # noqa: E402
from episeg_cv.colmap.database import create_database, database_lock  # noqa: E402

pycolmap.logging.minloglevel = 2


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    folder = tmp_path_factory.mktemp("faults")
    colmap.save_collection(scenes.make_collection(4, image_size=(240, 180)), folder)
    db = folder / "done.db"
    colmap.match_model(folder / "model", folder / "images", db, verify="pairs")
    return folder


@pytest.fixture
def work(source, tmp_path):
    for name in ("images", "model"):
        shutil.copytree(source / name, tmp_path / name)
    shutil.copy(source / "poses.json", tmp_path / "poses.json")
    shutil.copy(source / "done.db", tmp_path / "done.db")
    return tmp_path


def match(work, db, **kw):
    kw.setdefault("verify", "pairs")
    return colmap.match_model(work / "model", work / "images", db, **kw)


def leftovers(folder):
    return sorted(p.name for p in Path(folder).rglob("*")
                  if p.name.endswith((".partial", "-wal", "-shm", "-journal")) or ".tmp" in p.name)


def test_resume_refuses_other_settings_and_changed_images(work):
    db = work / "done.db"
    with pytest.raises(ValueError, match=r"search\.tol was 'auto', now 5\.0"):
        match(work, db, resume=True, tol=5.0)
    with pytest.raises(ValueError, match=r"rule\.ratio was 0\.68, now 0\.9"):
        match(work, db, resume=True, ratio=0.9)
    img = work / "images" / "view_001.png"
    import cv2
    cv2.imwrite(str(img), cv2.flip(cv2.imread(str(img)), 1))  # same size, other content
    with pytest.raises(ValueError, match="image 'view_001.png'.*changed"):
        match(work, db, resume=True)
    assert leftovers(work) == []  # reading the run record left no -wal/-shm beside the database


def test_resume_of_a_file_that_is_not_a_database(work):
    (work / "x.db").write_text("not sqlite")
    with pytest.raises(ValueError, match="not an SQLite file"):
        match(work, work / "x.db", resume=True)


def test_one_database_one_writer(work):
    db = work / "done.db"
    with database_lock(db):  # another run is writing it
        with pytest.raises(ValueError, match="being written by another run"):
            match(work, db, resume=True)
    store = colmap.FeatureStore(work / "cache", work / "images")
    views, rec = colmap.load_model(work / "model")
    for v in views:
        store.ensure(v)
    with pytest.raises(ValueError, match="created by another run meanwhile"):
        with create_database(db, rec, views, store, {"settings": {}, "images": {}}):
            pass  # the path appeared while this run prepared its database: it is not replaced
    assert leftovers(work) == []


def test_an_interrupted_preparation_leaves_nothing(work, monkeypatch):
    def interrupted(self, view):
        raise KeyboardInterrupt

    dead = work / ".new.db.999999999.partial"  # left by a run killed with SIGKILL
    dead.write_bytes(b"x")
    (work / ".new.db.999999999.partial-wal").write_bytes(b"x")
    monkeypatch.setattr(colmap.FeatureStore, "keypoints", interrupted)
    with pytest.raises(KeyboardInterrupt):
        match(work, work / "new.db")
    assert leftovers(work) == [] and not (work / "new.db").exists()


def test_outputs_are_not_inputs(work):
    with pytest.raises(ValueError, match="input of this run"):
        match(work, work / "images" / "view_000.png", overwrite=True)
    with pytest.raises(ValueError, match="input of this run"):
        colmap.match_model(work / "poses.json", work / "images", work / "poses.json", overwrite=True)
    for folder in ("model", "images"):
        with pytest.raises(ValueError, match="triangulation folder"):
            colmap.triangulate(work / "done.db", work / "model", work / "images", work / folder)
    assert leftovers(work) == []


def test_an_interrupted_triangulation_leaves_nothing(work, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pycolmap, "triangulate_points", interrupted)
    with pytest.raises(KeyboardInterrupt):
        colmap.triangulate(work / "done.db", work / "model", work / "images", work / "tri")
    assert not (work / "tri").exists() and leftovers(work) == []


def test_broken_cache_files_are_recomputed(work):
    store = colmap.FeatureStore(work / "cache", work / "images")
    views, _ = colmap.load_model(work / "model")
    n, _ = store.ensure(views[0])
    path = store.path(views[0])
    for damage in (b"", path.read_bytes()[:200]):
        path.write_bytes(damage)
        assert store.ensure(views[0])[0] == n
        assert len(store.load(views[0])[0]) == n


def test_a_cache_file_with_nan_descriptors_is_refused(work):
    """The matcher trusts the store's descriptors: a tampered file is refused when it is read."""
    store = colmap.FeatureStore(work / "cache", work / "images")
    views, _ = colmap.load_model(work / "model")
    store.ensure(views[0])
    path = store.path(views[0])
    with np.load(path) as z:
        arrays = dict(z)
    arrays["descriptors"][3, 5] = np.nan
    np.savez(path, **arrays)
    with pytest.raises(ValueError, match="holds descriptors that are NaN or inf"):
        store.load(views[0])


def test_broken_models_are_refused_at_once(work):
    (work / "model" / "points3D.bin").write_bytes(b"")
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match="points3D.bin' is empty"):
        colmap.load_model(work / "model")
    assert time.perf_counter() - t0 < 5  # it took minutes and gigabytes
    (work / "model" / "points3D.bin").write_bytes((2**62).to_bytes(8, "little") + b"\0" * 64)
    with pytest.raises(ValueError, match="truncated"):
        colmap.load_model(work / "model")


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin", "rigs.bin", "frames.bin"])
@pytest.mark.parametrize("cut", ["half", "last record"])
def test_a_truncated_model_file_is_named(work, name, cut):
    """pycolmap read a truncated cameras.bin silently, as garbage focal lengths, and named no file for
    a truncated frames.bin ("Rig with ID 2 does not exist")."""
    f = work / "model" / name
    data = f.read_bytes()
    f.write_bytes(data[:max(9, len(data) // 2)] if cut == "half" else data[:-5])
    with pytest.raises(ValueError, match=name.replace(".", r"\.")):
        colmap.load_model(work / "model")


def test_a_junk_line_in_a_text_model_is_named(work):
    text = work / "text"
    text.mkdir()
    pycolmap.Reconstruction(str(work / "model")).write_text(str(text))
    lines = (text / "images.txt").read_text().splitlines()
    lines.insert(6, "junk line here")
    (text / "images.txt").write_text("\n".join(lines))
    with pytest.raises(ValueError, match="images.txt is damaged"):
        colmap.load_model(text)


def test_nothing_to_match_is_an_error(work):
    (work / "pairs.txt").write_text("# nothing\n\n")
    with pytest.raises(ValueError, match="pairs file .*lists no pairs"):
        match(work, work / "p.db", pairs=work / "pairs.txt")
    poses = json.loads((work / "poses.json").read_text())
    (work / "one.json").write_text(json.dumps({"images": poses["images"][:1]}))
    with pytest.raises(ValueError, match="1 image; matching needs at least two"):
        colmap.match_model(work / "one.json", work / "images", work / "o.db")


def test_keypoints_where_the_distortion_folds_are_left_out(work):
    views, _ = colmap.load_model(work / "model")
    v = views[0]
    folded = colmap.View(v.name, v.image_id, v.camera_id, v.K, v.R, v.t, v.image_size, "SIMPLE_RADIAL",
                         (v.K[0, 0], v.K[0, 2] + 0.5, v.K[1, 2] + 0.5, -5.0))
    n_plain, _ = colmap.FeatureStore(work / "plain", work / "images").ensure(v)
    store = colmap.FeatureStore(work / "cache", work / "images")
    n, _ = store.ensure(folded)
    raw, pinhole, des = store.load(folded)
    assert 0 < n < n_plain  # the keypoints beyond the fold are gone, the others kept
    assert np.isfinite(pinhole).all() and folded.undistortable(raw).all() and len(des) == n


def test_sigterm_ends_a_run_cleanly_and_resume_completes(work):
    cmd = [sys.executable, "-m", "episeg_cv.cli", "colmap", "model", "images", "--database", "t.db", "-v",
           "--verify", "pairs"]
    with subprocess.Popen(cmd, cwd=work, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True) as p:
        for line in p.stderr:  # wait for the first pair, then ask it to stop
            if "pairs [" in line:
                p.send_signal(signal.SIGTERM)
                break
        err = p.stderr.read()
        p.wait(timeout=60)
    assert p.returncode in (0, 128 + signal.SIGTERM), err
    if p.returncode:
        assert "stopped by SIGTERM" in err and "Traceback" not in err and "@ 0x" not in err
    assert leftovers(work) == []
    r = subprocess.run(cmd + ["--resume"], cwd=work, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert len(colmap.read_database_matches(work / "t.db")) == 6
    assert os.path.getsize(work / "t.db") > 0


def test_the_dask_runner_quiets_tornado_only_while_it_runs():
    """SIGTERM inside a Dask call made distributed's cancel callback fail, and tornado printed its traceback."""
    pytest.importorskip("distributed")
    from episeg_cv.colmap.runner import Runner

    log = logging.getLogger("tornado.application")
    before = log.level
    runner = Runner(scheduler="local:1")
    try:
        assert log.level == logging.CRITICAL
    finally:
        runner.close()
    assert log.level == before
