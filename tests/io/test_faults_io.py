"""Regression tests of issue 15 for the file readers and writers: one clear line, nothing lost.

Each case failed before the fix (benchmarks/faults.py runs them, and hundreds more, as a user would).
"""

import json
from pathlib import Path

import numpy as np
import pytest

from episeg_cv import load_calibration, save_image, undistort_points
from episeg_cv.io import read_matches, write_matches
from episeg_cv.io.paths import output_file, written_atomically

K = [[250.0, 0, 159.5], [0, 250.0, 119.5], [0, 0, 1]]
CALIB = {"K1": K, "K2": K, "R": np.eye(3).tolist(), "t": [-1.0, 0, 0], "image_size1": [320, 240],
         "image_size2": [320, 240]}


def one_line(exc) -> str:
    text = str(exc.value)
    assert "\n" not in text, text
    return text


@pytest.mark.parametrize("suffix, content", [
    (".yml", "%YAML:1.0\n---\nM1: " + "[" * 100000 + "\n"),
    (".xml", '<?xml version="1.0"?>\n<opencv_storage>' + "<a>" * 100000 + "</opencv_storage>\n"),
    (".json", "[" * 100000 + "]" * 100000),
])
def test_deeply_nested_calibration_is_refused_not_a_crash(tmp_path, suffix, content):
    """OpenCV's YAML/XML parser recursed on the C stack: 100000 levels killed the process."""
    f = tmp_path / f"c{suffix}"
    f.write_text(content)
    with pytest.raises(ValueError) as exc:
        load_calibration(f)
    assert "nested" in one_line(exc)


def test_calibration_messages_name_the_key(tmp_path):
    f = tmp_path / "c.yml"
    f.write_text("%YAML:1.0\n---\n")  # a header only
    with pytest.raises(ValueError, match="missing key"):
        load_calibration(f)
    f.write_text("%YAML:1.0\n---\nM1: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
                 "   data: [ -250., 0., 159.5, 0., 250., 119.5, 0., 0., 1. ]\nM2: !!opencv-matrix\n   rows: 3\n"
                 "   cols: 3\n   dt: d\n   data: [ 250., 0., 159.5, 0., 250., 119.5, 0., 0., 1. ]\n")
    with pytest.raises(ValueError, match="M1 must have positive focal lengths"):
        load_calibration(f)
    g = tmp_path / "m.json"
    g.write_text(json.dumps({**CALIB, "K1": {"type_id": "opencv-matrix", "rows": 3, "cols": 4, "data": [1] * 9}}))
    with pytest.raises(ValueError, match="key 'K1'.*opencv-matrix") as exc:
        load_calibration(g)
    one_line(exc)
    g.write_text(json.dumps({**CALIB, "image_size1": [10**20, 240]}))
    with pytest.raises(ValueError, match="image_size1.*positive integers"):
        load_calibration(g)


def test_a_folder_is_not_a_file(tmp_path):
    with pytest.raises(IsADirectoryError, match="is a folder"):
        load_calibration(tmp_path)
    with pytest.raises(IsADirectoryError, match="is a folder"):
        read_matches(tmp_path)


def _matches_file(path):
    return write_matches(path, {"command": "test"}, np.zeros((3, 2)), np.ones((2, 2)), [[0, 1], [2, 0]],
                         [1.0, 2.0], ["on_segment", "off_line"])


def test_read_matches_validates_what_it_reads(tmp_path):
    good = _matches_file(tmp_path / "m.json")
    assert read_matches(good)["matches"].tolist() == [[0, 1], [2, 0]]
    bad = tmp_path / "b.json"
    data = json.loads(good.read_text())
    for change, pattern in [({"matches": [[0, 5], [1, 1]]}, "key .matches.*out of range"),
                            ({"keypoints1": [[0, 1], [2]]}, "key 'keypoints1'"),
                            ({"distances": [1.0]}, "same length")]:
        bad.write_text(json.dumps({**data, **change}))
        with pytest.raises(ValueError, match=pattern) as exc:
            read_matches(bad)
        one_line(exc)
    del data["meta"]
    bad.write_text(json.dumps(data))
    with pytest.raises(ValueError, match="missing meta"):
        read_matches(bad)
    csv = _matches_file(tmp_path / "m.csv")
    with pytest.raises(ValueError, match="not read back"):
        read_matches(csv)
    npz = _matches_file(tmp_path / "m.npz")
    with np.load(npz) as z:
        arrays = {k: z[k] for k in z.files}
    np.savez(tmp_path / "meta.npz", **{**arrays, "meta": np.array("abc{")})
    with pytest.raises(ValueError, match="key 'meta': expected a JSON object, got text that is not JSON") as exc:
        read_matches(tmp_path / "meta.npz")
    one_line(exc)
    npz.write_bytes(npz.read_bytes()[:100])  # truncated
    with pytest.raises(ValueError, match="cannot be read"):
        read_matches(npz)


def test_writes_are_atomic_and_follow_symlinks(tmp_path):
    target = tmp_path / "real.json"
    target.write_text("old")
    link = tmp_path / "link.json"
    link.symlink_to(target)
    _matches_file(link)
    assert link.is_symlink() and read_matches(target)["labels"].tolist() == ["on_segment", "off_line"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.json", "real.json"]  # no temporary file left

    class Boom(Exception):
        pass

    with pytest.raises(Boom):
        with written_atomically(target) as tmp:
            tmp.write_text("half")
            raise Boom
    assert "meta" in target.read_text() and sorted(p.name for p in tmp_path.iterdir()) == ["link.json", "real.json"]


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_a_full_disk_names_the_file(tmp_path):
    (tmp_path / "m.json").symlink_to("/dev/full")
    with pytest.raises(OSError, match="m.json.*No space left"):
        _matches_file(tmp_path / "m.json")
    (tmp_path / "f.png").symlink_to("/dev/full")
    with pytest.raises(OSError, match="f.png.*No space left"):
        save_image(tmp_path / "f.png", np.zeros((8, 8), np.uint8))


def test_a_file_in_the_way_of_an_output_folder(tmp_path):
    (tmp_path / "calib.json").write_text("{}")
    with pytest.raises(NotADirectoryError, match="is a file, so it cannot be a folder"):
        output_file(tmp_path / "calib.json" / "out.json", "matches file")


def test_undistortion_where_the_distortion_folds_gives_nan():
    """k1 = -5 folds the image: cv2.undistortPoints returned wrong positions there, silently."""
    pts = np.array([[159.5, 119.5], [170.0, 119.5], [300.0, 200.0], [10.0, 10.0]])
    u = undistort_points(pts, K, [-5.0, 0, 0, 0])
    assert np.isfinite(u[:2]).all() and np.isnan(u[2:]).all()
    # where it has an inverse, distorting again gives the point back
    import cv2
    n = np.column_stack([(u[:2] - [159.5, 119.5]) / 250.0, np.ones(2)])
    back = cv2.projectPoints(n, np.zeros(3), np.zeros(3), np.array(K), np.array([-5.0, 0, 0, 0]))[0].reshape(-1, 2)
    np.testing.assert_allclose(back, pts[:2], atol=1e-3)
