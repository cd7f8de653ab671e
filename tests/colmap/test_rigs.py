"""Multi-camera rigs (pycolmap 4.x rigs and frames): matched, refined and triangulated with the rig kept."""

import dataclasses

import cv2
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

pycolmap = pytest.importorskip("pycolmap")

from episeg_cv import colmap, scenes  # noqa: E402
from episeg_cv.colmap.model import rig_consistent  # noqa: E402
from episeg_cv.colmap.triangulation import known_pose_reconstruction  # noqa: E402
from episeg_cv.colmap.views import camera_pose, poses_agree, rig_pose  # noqa: E402
from episeg_cv.scenes import make_room_scene, render  # noqa: E402
from episeg_cv.scenes.collection import collection_poses  # noqa: E402

pycolmap.logging.minloglevel = 2

SIZE = (320, 240)
K = np.array([[250.0, 0, 159.5], [0, 250.0, 119.5], [0, 0, 1]])
#: The second camera sits 0.3 to the right of the first (X_cam1 = X_cam0 + BASE), turned by 5 degrees.
BASE = np.array([-0.3, 0.0, 0.0])
TURN = cv2.Rodrigues(np.radians([0.0, 5.0, 0.0]))[0]


def _rig_model(folder, frames=3, noise_deg=0.0, seed=0):
    """A stereo rig's model (one rig of two cameras, ``frames`` frames), its images rendered at the true poses;
    ``noise_deg``: each frame's pose turned by that much (the rig's calibration stays exact)."""
    R0, t0 = collection_poses(frames)
    scene = make_room_scene(rng=7, keep_clear=[-R.T @ t for R, t in zip(R0, t0)], clearance=0.9)
    rec = pycolmap.Reconstruction()
    cams = []
    for cid in (1, 2):
        cam = pycolmap.Camera(model="PINHOLE", width=SIZE[0], height=SIZE[1], camera_id=cid,
                              params=[K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5])
        rec.add_camera(cam)
        cams.append(cam)
    rig = pycolmap.Rig(rig_id=1)
    rig.add_ref_sensor(cams[0].sensor_id)
    rig.add_sensor(cams[1].sensor_id, pycolmap.Rigid3d(pycolmap.Rotation3d(TURN), BASE))
    rec.add_rig(rig)
    rng = np.random.default_rng(seed)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    image_id = 1
    for f, (R, t) in enumerate(zip(R0, t0), 1):
        frame = pycolmap.Frame(frame_id=f, rig_id=1)
        given = cv2.Rodrigues(np.radians(noise_deg) * rng.normal(size=3) / np.sqrt(3))[0] @ R
        frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(given), t)
        images = []
        for s, cam in enumerate(cams):
            name = f"cam{s}/frame{f}.png"
            (folder / "images" / f"cam{s}").mkdir(exist_ok=True)
            Rc, tc = (R, t) if s == 0 else (TURN @ R, TURN @ t + BASE)
            cv2.imwrite(str(folder / "images" / name), render(scene, K, Rc, tc, SIZE, 2)[0])
            images.append(pycolmap.Image(name=name, camera_id=cam.camera_id, image_id=image_id))
            frame.add_data_id(images[-1].data_id)
            image_id += 1
        rec.add_frame(frame)
        for im in images:
            im.frame_id = f
            rec.add_image(im)
        rec.register_frame(f)
    (folder / "model").mkdir(exist_ok=True)
    rec.write(str(folder / "model"))
    return folder / "model", folder / "images"


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    return _rig_model(tmp_path_factory.mktemp("rig"))


def _sensor_from_rig(views):
    """``{frame: (R, t)}`` of the second camera relative to the first, from the views' poses."""
    by = {v.name: v for v in views}
    out = {}
    for name in by:
        if name.startswith("cam0/"):
            a, b = by[name], by[name.replace("cam0/", "cam1/")]
            out[name] = (b.R @ a.R.T, b.t - b.R @ a.R.T @ a.t)
    return out


# -- hand-computed and property -------------------------------------------------------------------------------
def test_rig_pose_by_hand():
    rig = pycolmap.Rig(rig_id=1)
    ref, other = pycolmap.sensor_t(pycolmap.SensorType.CAMERA, 1), pycolmap.sensor_t(pycolmap.SensorType.CAMERA, 2)
    rig.add_ref_sensor(ref)
    rig.add_sensor(other, pycolmap.Rigid3d(pycolmap.Rotation3d(np.eye(3)), BASE))
    # the reference camera's pose is the rig's; the other camera sees the world 0.3 to the left
    R, t = rig_pose(rig, ref, np.eye(3), [0.0, 0.0, 2.0])
    np.testing.assert_array_equal(t, [0.0, 0.0, 2.0])
    Rc, tc = camera_pose(rig, other, R, t)
    np.testing.assert_allclose(tc, [-0.3, 0.0, 2.0], atol=1e-15)
    np.testing.assert_allclose(rig_pose(rig, other, Rc, tc)[1], t, atol=1e-15)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=9, max_size=9))
def test_rig_pose_inverts_camera_pose(v):
    rig = pycolmap.Rig(rig_id=1)
    ref, other = pycolmap.sensor_t(pycolmap.SensorType.CAMERA, 1), pycolmap.sensor_t(pycolmap.SensorType.CAMERA, 2)
    rig.add_ref_sensor(ref)
    rig.add_sensor(other, pycolmap.Rigid3d(pycolmap.Rotation3d(cv2.Rodrigues(np.array(v[:3]))[0]), np.array(v[3:6])))
    R, t = cv2.Rodrigues(np.array(v[6:9]))[0], np.array(v[3:6][::-1])
    assert poses_agree(*rig_pose(rig, other, *camera_pose(rig, other, R, t)), R, t, tol=1e-12)


# -- synthetic scene ----------------------------------------------------------------------------------------
def test_a_rig_model_is_matched_and_triangulated_with_its_rig(rig, tmp_path):
    model, images = rig
    views, _ = colmap.load_model(model)
    for R, t in _sensor_from_rig(views).values():  # the model's poses are the rig's
        np.testing.assert_allclose(R, TURN, atol=1e-12)
        np.testing.assert_allclose(t, BASE, atol=1e-12)
    colmap.match_model(model, images, tmp_path / "db.db", log=lambda m: None)
    rec = colmap.triangulate(tmp_path / "db.db", model, images, tmp_path / "tri")
    assert rec.num_rigs() == 1 and rec.rig(1).num_sensors() == 2 and rec.num_frames() == 3
    assert rec.num_points3D() > 100 and rec.compute_mean_reprojection_error() < 0.5


def test_refined_poses_keep_the_rig(tmp_path, relative_error_deg):
    """Poses refined view by view are put back on the rig, and the CLI triangulates with them (before:
    pycolmap stopped on 'existing_rig.SensorIds() == rig.SensorIds()')."""
    model, images = _rig_model(tmp_path / "noisy", frames=4, noise_deg=0.3, seed=1)
    true_views, _ = colmap.load_model(_rig_model(tmp_path / "true", frames=4)[0])
    report = colmap.match_model(model, images, tmp_path / "r.db", refine_poses=True, log=lambda m: None)
    refined = report.poses.views
    assert report.poses.converged
    for R, t in _sensor_from_rig(refined).values():  # the rig's calibration holds exactly
        np.testing.assert_allclose(R, TURN, atol=1e-9)
        np.testing.assert_allclose(t, BASE, atol=1e-9)
    given, _ = colmap.load_model(model)

    assert relative_error_deg(refined, true_views) < relative_error_deg(given, true_views) / 3  # (0.59 -> 0.06 deg)
    rec = colmap.triangulate(tmp_path / "r.db", refined, images, tmp_path / "tri")
    assert rec.num_rigs() == 1 and rec.num_frames() == 4 and rec.num_points3D() > 100


def test_rig_consistent_leaves_single_cameras_alone(rig):
    views, rec = colmap.load_model(rig[0])
    moved = [dataclasses.replace(v, t=v.t + 0.01) for v in views]
    out = rig_consistent(moved, rec)
    by = {v.name: v for v in out}
    for v in moved:  # the reference cameras keep their (moved) pose, the others follow the rig
        if v.name.startswith("cam0/"):
            np.testing.assert_array_equal(by[v.name].t, v.t)
        else:
            assert not np.allclose(by[v.name].t, v.t)
    single, srec = colmap.load_model(colmap.save_collection(scenes.make_collection(2, image_size=(64, 48)),
                                                            rig[0].parent / "single")["model"])
    assert rig_consistent(single, srec) == single


# -- bad input ----------------------------------------------------------------------------------------------
def test_views_that_break_their_rig_are_refused(rig, tmp_path):
    model, images = rig
    colmap.match_model(model, images, tmp_path / "db.db", log=lambda m: None)
    views, _ = colmap.load_model(model)
    bad = [dataclasses.replace(v, t=v.t + [0.05, 0, 0]) if v.name == "cam1/frame2.png" else v for v in views]
    with pytest.raises(ValueError, match=r"cam1/frame2.png.*not its rig's"):
        colmap.triangulate(tmp_path / "db.db", bad, images, tmp_path / "tri")


def test_colmap_features_of_a_rig_configured_database(rig, tmp_path):
    """COLMAP's features with its rig configuration (``rig_configurator`` without poses: the database holds the
    rig's cameras but no ``sensor_from_rig``): matched and triangulated with the rig, its calibration taken from
    the model's poses (before this change such a database was refused; a first version of it crashed)."""
    model, images = rig
    db = tmp_path / "colmap.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = 1
    names = sorted(str(p.relative_to(images)) for p in images.rglob("*.png"))
    pycolmap.extract_features(str(db), str(images), image_names=names, camera_mode=pycolmap.CameraMode.PER_FOLDER,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    cfg = pycolmap.RigConfig()
    cams = [pycolmap.RigConfigCamera(), pycolmap.RigConfigCamera()]
    cams[0].ref_sensor, cams[0].image_prefix, cams[1].image_prefix = True, "cam0/", "cam1/"
    cfg.cameras = cams
    handle = pycolmap.Database.open(str(db))
    try:
        pycolmap.apply_rig_config([cfg], handle)
        assert [r.num_sensors() for r in handle.read_all_rigs()] == [2]
    finally:
        handle.close()
    colmap.match_model(model, images, db, features="database", log=lambda m: None)
    rec = colmap.triangulate(db, model, images, tmp_path / "tri")
    assert rec.num_rigs() == 1 and rec.num_points3D() > 100
    # what it was triangulated from: the model's poses on the database's rig (COLMAP's adjustment then moves it)
    start = known_pose_reconstruction(db, colmap.load_model(model)[0])
    (rid,) = start.rigs
    (sensor,) = start.rig(rid).non_ref_sensors
    S = np.asarray(start.rig(rid).sensor_from_rig(sensor).matrix())
    np.testing.assert_allclose(S[:, :3], TURN, atol=1e-9)
    np.testing.assert_allclose(S[:, 3], BASE, atol=1e-9)
