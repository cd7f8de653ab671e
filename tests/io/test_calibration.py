"""Calibration files (episeg_cv.io.calibration, episeg_cv.distortion): every layout, errors that name file, key and shape; undistortion."""

import json

import cv2
import numpy as np
import pytest

from episeg_cv import Calibration, load_calibration, save_calibration, undistort_points
from episeg_cv.datasets import data_dir

ATOL = 1e-9  # float64 round trips

DEFAULT = data_dir() / "default" / "calib.json"


@pytest.fixture(scope="module")
def ref():
    return json.loads(DEFAULT.read_text())


def _write(tmp_path, name, data):
    p = tmp_path / name
    p.write_text(json.dumps(data))
    return p


def _same_pose(c, ref):
    np.testing.assert_allclose(c.K1, ref["K1"], atol=ATOL)
    np.testing.assert_allclose(c.K2, ref["K2"], atol=ATOL)
    np.testing.assert_allclose(c.R, ref["R"], atol=1e-9)
    np.testing.assert_allclose(c.t, ref["t"], atol=1e-9)


def _rot(rvec):
    return cv2.Rodrigues(np.asarray(rvec, np.float64))[0]


# --- JSON layouts ------------------------------------------------------------------------
def test_relative_layout_is_the_bundled_file(ref):
    c = load_calibration(DEFAULT)
    _same_pose(c, ref)
    assert c.image_size1 == (640, 480) and c.image_size2 == (640, 480)
    assert c.dist1 is None and c.dist2 is None and not c.has_distortion
    g = c.geometry
    assert g.image_size1 == (640, 480)
    np.testing.assert_allclose(g.t, ref["t"])


def test_world_pose_layouts_give_the_relative_pose(tmp_path, ref):
    # world-to-camera poses with X2 = R X1 + t: camera 1 at an arbitrary pose, camera 2 composed with it
    R1, t1 = _rot([0.1, -0.2, 0.05]), np.array([0.3, -1.0, 2.0])
    R, t = np.array(ref["R"]), np.array(ref["t"])
    R2, t2 = R @ R1, R @ t1 + t
    cams = {"cameras": [{"K": ref["K1"], "R": R1.tolist(), "t": t1.tolist(), "image_size": [640, 480]},
                        {"K": ref["K2"], "R": R2.tolist(), "t": [[v] for v in t2], "width": 640, "height": 480,
                         "dist": [0.01, 0, 0, 0, 0]}]}
    c = load_calibration(_write(tmp_path, "cams.json", cams))
    _same_pose(c, ref)
    assert c.image_size2 == (640, 480) and c.dist1 is None and c.dist2.shape == (5,)
    flat = {"K1": ref["K1"], "K2": ref["K2"], "R1": R1.tolist(), "t1": t1.tolist(), "R2": R2.tolist(),
            "t2": t2.tolist(), "image_size": [640, 480]}
    c = load_calibration(_write(tmp_path, "flat.json", flat))
    _same_pose(c, ref)
    assert c.image_size1 == c.image_size2 == (640, 480)


def test_projection_matrix_layout(tmp_path, ref):
    K1, K2, R, t = (np.array(ref[k]) for k in ("K1", "K2", "R", "t"))
    P1 = 2.0 * K1 @ np.hstack([np.eye(3), np.zeros((3, 1))])  # any scale
    P2 = -K2 @ np.hstack([R, t[:, None]])  # either sign
    c = load_calibration(_write(tmp_path, "p.json", {"P1": P1.tolist(), "P2": P2.tolist(),
                                                     "image_size1": [640, 480], "image_size2": [640, 480]}))
    np.testing.assert_allclose(c.K1, K1, atol=1e-8)
    np.testing.assert_allclose(c.K2, K2, atol=1e-8)
    np.testing.assert_allclose(c.R, R, atol=1e-9)
    np.testing.assert_allclose(c.t, t, atol=1e-9)


def test_shared_K_and_opencv_names_in_json(tmp_path, ref):
    c = load_calibration(_write(tmp_path, "k.json", {"K": ref["K1"], "R": ref["R"], "t": ref["t"]}))
    np.testing.assert_allclose(c.K2, ref["K1"])
    assert c.image_size1 is None
    with pytest.raises(ValueError, match="image sizes unknown"):
        c.geometry
    c = c.with_image_sizes((640, 480), (640, 480))
    assert c.geometry.image_size2 == (640, 480)
    c = load_calibration(_write(tmp_path, "m.json", {"M1": ref["K1"], "M2": ref["K2"], "R": ref["R"],
                                                     "T": ref["t"], "D1": [0, 0, 0, 0, 0], "D2": [0.1, 0, 0, 0]}))
    _same_pose(c, ref)
    assert c.dist1 is None and c.dist2.tolist() == [0.1, 0, 0, 0]


def test_image_size_arguments_fill_in_and_check(tmp_path, ref):
    p = _write(tmp_path, "nosize.json", {"K1": ref["K1"], "K2": ref["K2"], "R": ref["R"], "t": ref["t"]})
    assert load_calibration(p, (640, 480), (320, 240)).image_size2 == (320, 240)
    with pytest.raises(ValueError, match=r"calib.json: image_size1 is 640x480 but the image is 320x240"):
        load_calibration(DEFAULT, (320, 240), (640, 480))


# --- FileStorage (what cv2.stereoCalibrate users save) -------------------------------------
@pytest.mark.parametrize("suffix", [".yml", ".xml"])
@pytest.mark.parametrize("distortion", [False, True])
def test_filestorage_stereo_calibrate_names(tmp_path, ref, suffix, distortion):
    p = tmp_path / f"stereo{suffix}"
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    D1 = np.array([[-0.2, 0.05, 0.001, -0.002, 0.0]]) if distortion else np.zeros((1, 5))
    fs.write("M1", np.array(ref["K1"]))
    fs.write("D1", D1)
    fs.write("M2", np.array(ref["K2"]))
    fs.write("D2", np.zeros((1, 5)))
    fs.write("R", np.array(ref["R"]))
    fs.write("T", np.array(ref["t"]).reshape(3, 1))
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.release()
    c = load_calibration(p)
    _same_pose(c, ref)
    assert c.image_size1 == c.image_size2 == (640, 480)
    assert c.has_distortion == distortion
    if distortion:
        np.testing.assert_allclose(c.dist1, D1.ravel())
    assert c.dist2 is None


def test_filestorage_without_sizes_takes_them_from_the_caller(tmp_path, ref):
    p = tmp_path / "intrinsics_extrinsics.yaml"
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    for k, v in (("M1", ref["K1"]), ("M2", ref["K2"]), ("R", ref["R"]), ("T", ref["t"])):
        fs.write(k, np.array(v))
    fs.release()
    c = load_calibration(p)
    assert c.image_size1 is None
    assert load_calibration(p, (640, 480), (640, 480)).geometry.image_size1 == (640, 480)


@pytest.mark.parametrize("suffix", [".json", ".yml", ".xml"])
def test_save_and_load_round_trip(tmp_path, suffix):
    c = load_calibration(DEFAULT)
    c = Calibration(c.K1, c.K2, c.R, c.t, c.image_size1, (320, 240), [0.1, -0.01, 0, 0, 0.001], None)
    back = load_calibration(save_calibration(tmp_path / f"c{suffix}", c))
    for k in ("K1", "K2", "R", "t", "dist1"):
        np.testing.assert_allclose(getattr(back, k), getattr(c, k), atol=1e-12)
    assert back.dist2 is None and back.image_size1 == (640, 480) and back.image_size2 == (320, 240)


# --- errors -------------------------------------------------------------------------------
@pytest.mark.parametrize("data, message", [
    ({"K1": [[1, 0, 0], [0, 1, 0]], "K2": np.eye(3).tolist(), "R": np.eye(3).tolist(), "t": [1, 0, 0]},
     r"calib.json: key 'K1' must be a 3x3 matrix, got shape \(2, 3\)"),
    ({"K1": np.eye(3).tolist(), "K2": np.eye(3).tolist(), "R": np.eye(3).tolist()},
     r"calib.json: missing key 't' \(a vector of 3 numbers\)"),
    ({"K2": np.eye(3).tolist(), "R": np.eye(3).tolist(), "t": [1, 0, 0]},
     r"calib.json: missing key 'K1' \(a 3x3 matrix\)"),
    ({"K": np.eye(3).tolist(), "R": np.eye(3).tolist(), "t": [1, 0]},
     r"calib.json: key 't' must be a vector of 3 numbers, got shape \(2,\)"),
    ({"K": np.eye(3).tolist(), "R": (2 * np.eye(3)).tolist(), "t": [1, 0, 0]},
     r"calib.json: R must be a rotation matrix"),
    ({"K": np.eye(3).tolist(), "R": np.eye(3).tolist(), "t": [1, 0, 0], "image_size1": [640]},
     r"calib.json: key 'image_size1' must be \[width, height\]"),
    ({"K": np.eye(3).tolist(), "R": np.eye(3).tolist(), "t": [1, 0, 0], "dist1": [0.1, 0.2, 0.3]},
     r"calib.json: key 'dist1' must hold 4, 5, 8, 12 or 14"),
    ({"K": "eye", "R": np.eye(3).tolist(), "t": [1, 0, 0]}, r"calib.json: key 'K' must be a 3x3 matrix"),
    ({"P1": np.zeros((3, 4)).tolist(), "P2": np.zeros((3, 3)).tolist()},
     r"calib.json: key 'P2' must be a 3x4 matrix, got shape \(3, 3\)"),
    ({"cameras": [{"K": np.eye(3).tolist(), "R": np.eye(3).tolist(), "t": [0, 0, 0]}]},
     r"calib.json: key 'cameras' must be a list of two"),
    ({"cameras": [{"K": np.eye(3).tolist(), "R": np.eye(3).tolist(), "t": [0, 0, 0]},
                  {"K": np.eye(3).tolist(), "t": [0, 0, 0]}]},
     r"calib.json: cameras\[1\]: missing key 'R'"),
])
def test_wrong_or_missing_keys_name_file_key_and_shape(tmp_path, data, message):
    with pytest.raises(ValueError, match=message):
        load_calibration(_write(tmp_path, "calib.json", data))


def test_unreadable_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="calibration file not found"):
        load_calibration(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"K1": [1, 2,')
    with pytest.raises(ValueError, match=r"bad.json'?: invalid JSON at line 1"):
        load_calibration(bad)
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"list.json: the top level must be a JSON object"):
        load_calibration(tmp_path / "list.json")
    (tmp_path / "bad.yml").write_text("M1: [1, 2\n")
    with pytest.raises(ValueError, match=r"bad.yml: cannot (parse|open)"):
        load_calibration(tmp_path / "bad.yml")
    (tmp_path / "bin.json").write_bytes(b"\xff\xfe\x00\x01")
    with pytest.raises(ValueError, match=r"bin.json"):
        load_calibration(tmp_path / "bin.json")


# --- undistortion ---------------------------------------------------------------------------
K = np.array([[500.0, 0, 319.5], [0, 480.0, 239.5], [0, 0, 1]])


def test_undistort_hand_checked_radial():
    # k1 = 0.1 only: the undistorted point u maps back as x_d = x_u (1 + k1 r^2), in normalised units
    u = undistort_points([[600.0, 400.0]], K, [0.1, 0, 0, 0])[0]
    x, y = (u[0] - 319.5) / 500.0, (u[1] - 239.5) / 480.0
    f = 1 + 0.1 * (x * x + y * y)
    np.testing.assert_allclose([x * f * 500.0 + 319.5, y * f * 480.0 + 239.5], [600.0, 400.0], atol=1e-6)


def test_undistort_inverts_cv2_project_points():
    rng = np.random.default_rng(0)
    dist = np.array([-0.25, 0.08, 0.001, -0.0015, -0.01])
    n = rng.uniform([-0.5, -0.4], [0.5, 0.4], (50, 2))  # normalised pinhole points
    ideal = n * [500.0, 480.0] + [319.5, 239.5]
    # the distorted pixels a real camera sees: cv2.projectPoints(X, 0, 0, K, dist)
    X = np.column_stack([n, np.ones(len(n))])
    distorted = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
    np.testing.assert_allclose(undistort_points(distorted, K, dist), ideal, atol=1e-6)
    # and agrees with a plain cv2.undistortPoints(P=K) call (5 iterations) to its accuracy
    plain = cv2.undistortPoints(distorted.reshape(-1, 1, 2), K, dist, P=K).reshape(-1, 2)
    np.testing.assert_allclose(undistort_points(distorted, K, dist), plain, atol=0.05)


def test_undistort_no_distortion_and_empty():
    p = np.array([[1.0, 2.0], [3.0, 4.0]])
    assert np.array_equal(undistort_points(p, K, None), p)
    assert np.array_equal(undistort_points(p, K, [0, 0, 0, 0, 0]), p)
    assert undistort_points(np.zeros((0, 2)), K, [0.1, 0, 0, 0]).shape == (0, 2)
    with pytest.raises(ValueError, match="points must have shape"):
        undistort_points([1.0, 2.0], K, None)
    with pytest.raises(ValueError, match="4, 5, 8, 12 or 14"):
        undistort_points(p, K, [0.1, 0.2])


# --- the intrinsics only: the pose is estimated from the images -----------------------------------------
@pytest.mark.parametrize("layout", [
    lambda r: {"K1": r["K1"], "K2": r["K2"], "image_size1": r["image_size1"], "image_size2": r["image_size2"]},
    lambda r: {"K": r["K1"], "image_size": r["image_size1"]},
    lambda r: {"M1": r["K1"], "M2": r["K2"], "D1": [0, 0, 0, 0, 0], "D2": [0, 0, 0, 0, 0]},
    lambda r: {"cameras": [{"K": r["K1"]}, {"K": r["K2"]}]},
])
def test_intrinsics_without_a_pose(tmp_path, ref, layout):
    c = load_calibration(_write(tmp_path, "k.json", layout(ref)), image_size1=(640, 480), image_size2=(640, 480))
    assert not c.has_pose and c.R is None and c.t is None
    np.testing.assert_allclose(c.K1, ref["K1"])
    with pytest.raises(ValueError, match="k.json: no pose"):
        c.geometry
    back = load_calibration(save_calibration(tmp_path / "back.json", c))
    assert not back.has_pose and back.image_size1 == (640, 480)
    yml = load_calibration(save_calibration(tmp_path / "back.yml", c))
    assert not yml.has_pose and np.allclose(yml.K2, ref["K2"])


@pytest.mark.parametrize("data, message", [
    ({"K": np.eye(3).tolist(), "t": [1, 0, 0]}, r"calib.json: missing key 'R' \(a 3x3 matrix\): a partial pose"),
    ({"M1": np.eye(3).tolist(), "M2": np.eye(3).tolist(), "R": np.eye(3).tolist()}, r"missing key 'T'"),
    ({"K": np.eye(3).tolist(), "R1": np.eye(3).tolist(), "t1": [0, 0, 0], "R2": np.eye(3).tolist()},
     r"missing key 't2'"),
    ({"cameras": [{"K": np.eye(3).tolist(), "R": np.eye(3).tolist(), "t": [0, 0, 0]}, {"K": np.eye(3).tolist()}]},
     r"one camera has a pose"),
])
def test_partial_pose_is_an_error(tmp_path, data, message):
    with pytest.raises(ValueError, match=message):
        load_calibration(_write(tmp_path, "calib.json", data))


def test_partial_pose_in_the_constructor():
    with pytest.raises(ValueError, match="the pose has R but no t"):
        Calibration(np.eye(3), np.eye(3), np.eye(3), None)
