"""The ``episeg`` command, run in subprocesses on the bundled data: exit codes, files that parse."""

import csv
import json
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest

from episeg_cv import Calibration, load_calibration, save_calibration
from episeg_cv.io import read_matches
from episeg_cv.datasets import data_dir

DEFAULT = data_dir() / "default"
IMG1, IMG2, CALIB = str(DEFAULT / "image1.png"), str(DEFAULT / "image2.png"), str(DEFAULT / "calib.json")
LABELS = {"on_segment", "beyond_infinity", "beyond_epipole", "off_line", "empty_segment", "out_of_range"}


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "episeg_cv.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=300)


def _check_no_traceback(r):
    assert "Traceback" not in r.stderr, r.stderr


# --- demo ----------------------------------------------------------------------------------
def test_demo_writes_figures_and_matches(tmp_path):
    out = tmp_path / "demo"
    r = run("demo", "--out", out)
    assert r.returncode == 0, r.stderr
    for name in ("segment-guided", "line-guided", "BFMatcher + ratio 0.8 + line filter", "precision"):
        assert name in r.stdout
    for name in ("matches.png", "segments.png"):
        img = cv2.imread(str(out / name))
        assert img is not None and img.ndim == 3 and img.shape[1] >= 1280
    data = json.loads((out / "matches.json").read_text())
    meta = data["meta"]
    assert meta["format"] == "episeg-matches" and meta["counts"]["matches"] == len(data["matches"]) > 100
    assert 0 < meta["counts"]["correct"] <= meta["counts"]["matches"]
    assert {row["method"] for row in meta["comparison"]} >= {"BFMatcher + ratio 0.8"}
    assert len(data["distances"]) == len(data["labels"]) == len(data["matches"])
    assert set(data["labels"]) <= LABELS
    m = np.array(data["matches"])
    assert m[:, 0].max() < len(data["keypoints1"]) and m[:, 1].max() < len(data["keypoints2"])


def test_demo_quiet_prints_nothing(tmp_path):
    r = run("demo", "--out", tmp_path, "--quiet", "--max-features", "500", "--points", "3")
    assert r.returncode == 0, r.stderr
    assert r.stdout == "" and r.stderr == ""


# --- match ---------------------------------------------------------------------------------
@pytest.mark.parametrize("detector, constraint, extra", [
    ("sift", "segment", []),
    ("orb", "line", ["--cross-check"]),
    ("akaze", "segment", ["--depth-range", "0.5", "inf"]),
    ("sift", "none", ["--ratio", "0.7"]),
])
def test_match_json(tmp_path, detector, constraint, extra):
    out, fig = tmp_path / "m.json", tmp_path / "m.png"
    r = run("match", IMG1, IMG2, "--calib", CALIB, "--detector", detector, "--constraint", constraint,
            "--max-features", "800", "--out", out, "--figure", fig, *extra)
    assert r.returncode == 0, r.stderr
    data = json.loads(out.read_text())
    meta = data["meta"]
    assert meta["settings"]["detector"] == detector and meta["settings"]["constraint"] == constraint
    assert meta["counts"]["matches"] == len(data["matches"]) > 0
    assert meta["counts"]["keypoints1"] == len(data["keypoints1"]) <= 800
    assert not meta["undistorted"] and "keypoints1_undistorted" not in data
    assert set(data["labels"]) <= LABELS
    if constraint == "segment":
        assert set(data["labels"]) == {"on_segment"}
    if constraint == "none":  # plain BFMatcher: some matches off the line
        assert sum(lab != "on_segment" for lab in data["labels"]) > 0
    assert cv2.imread(str(fig)) is not None


def test_match_threads_gives_the_same_matches_and_is_recorded(tmp_path):
    outs = []
    for extra in ([], ["--threads", "1"], ["--threads", "2"]):
        out = tmp_path / f"m{len(outs)}.npz"
        r = run("match", IMG1, IMG2, "--calib", CALIB, "--max-features", "3000", "--out", out, "-q", *extra)
        assert r.returncode == 0, r.stderr
        outs.append(read_matches(out))
    for o in outs[1:]:
        np.testing.assert_array_equal(o["matches"], outs[0]["matches"])
    assert [o["meta"]["settings"]["threads"] for o in outs] == [None, 1, 2]
    r = run("match", IMG1, IMG2, "--calib", CALIB, "--threads", "0")
    assert r.returncode == 2 and "--threads" in r.stderr and "positive integer" in r.stderr
    _check_no_traceback(r)


def test_match_npz_and_csv_hold_the_same_matches(tmp_path):
    for name in ("m.npz", "m.csv", "m.json"):
        r = run("match", IMG1, IMG2, "--calib", CALIB, "--max-features", "600", "--out", tmp_path / name, "-q")
        assert r.returncode == 0, r.stderr
    z, j = read_matches(tmp_path / "m.npz"), read_matches(tmp_path / "m.json")
    assert set(z) >= {"meta", "keypoints1", "keypoints2", "matches", "distances", "labels"}
    assert z["matches"].dtype.kind == "i" and z["matches"].shape[1] == 2
    np.testing.assert_array_equal(z["matches"], j["matches"])
    np.testing.assert_allclose(z["distances"], j["distances"], rtol=1e-5)
    assert z["meta"]["counts"]["matches"] == len(z["matches"])
    with open(tmp_path / "m.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["x1", "y1", "x2", "y2", "distance", "label"]
    assert len(rows) == len(j["matches"])
    i1, i2 = j["matches"][0]
    np.testing.assert_allclose([float(rows[0]["x1"]), float(rows[0]["y2"])],
                               [j["keypoints1"][i1, 0], j["keypoints2"][i2, 1]], atol=1e-3)


def test_match_undistorts_with_distortion_coefficients(tmp_path):
    c = load_calibration(CALIB)
    yml = save_calibration(tmp_path / "stereo.yml", Calibration(c.K1, c.K2, c.R, c.t, None, None,
                                                                [-0.05, 0.01, 0, 0, 0], [-0.05, 0.01, 0, 0, 0]))
    r = run("match", IMG1, IMG2, "--calib", yml, "--max-features", "600", "--out", tmp_path / "m.json")
    assert r.returncode == 0, r.stderr
    data = read_matches(tmp_path / "m.json")
    assert data["meta"]["undistorted"] is True
    assert data["keypoints1_undistorted"].shape == data["keypoints1"].shape
    assert not np.allclose(data["keypoints1_undistorted"], data["keypoints1"])
    r = run("segments", IMG1, IMG2, "--calib", yml, "--random", "4", "--out", tmp_path / "s.png")
    assert r.returncode == 0, r.stderr


# --- segments --------------------------------------------------------------------------------
def test_segments_figure(tmp_path):
    out = tmp_path / "fig.png"
    r = run("segments", IMG1, IMG2, "--calib", CALIB, "--points", "100,100", "320.5,240", "600,50", "--out", out)
    assert r.returncode == 0, r.stderr
    img = cv2.imread(str(out))
    assert img is not None and img.shape[1] > 2 * 640 and img.shape[0] > 480
    assert "epipole in image 2" in r.stdout and r.stdout.count("\n") >= 5
    r = run("segments", IMG1, IMG2, "--calib", CALIB, "--random", "5", "--depth-range", "1", "5", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "segments.png").is_file()


# --- errors and usage ------------------------------------------------------------------------
def test_wrong_calibration_gives_exit_1_and_a_clear_message(tmp_path):
    bad = tmp_path / "calib.json"
    bad.write_text(json.dumps({"K1": [[500, 0, 320], [0, 500, 240]], "K2": np.eye(3).tolist(),
                               "R": np.eye(3).tolist(), "t": [1, 0, 0]}))
    r = run("match", IMG1, IMG2, "--calib", bad)
    assert r.returncode == 1
    _check_no_traceback(r)
    assert r.stderr.strip() == "episeg: error: calib.json: key 'K1' must be a 3x3 matrix, got shape (2, 3)"
    r = run("segments", IMG1, IMG2, "--calib", data_dir() / "motorcycle" / "calib.json")
    assert r.returncode == 1 and "image_size1 is 741x500 but the image is 640x480" in r.stderr
    _check_no_traceback(r)


@pytest.mark.parametrize("posed", [False, True])
def test_match_consistency(tmp_path, posed):
    """--consistency: a subset of the plain run's matches (with a pose too: all matches are anchors), recorded
    in meta.settings."""
    calib = ("--calib", CALIB) if posed else ()
    out, plain = tmp_path / "c.json", tmp_path / "p.json"
    r = run("match", IMG1, IMG2, *calib, "--max-features", "800", "--consistency", "--out", out)
    assert r.returncode == 0, r.stderr
    assert run("match", IMG1, IMG2, *calib, "--max-features", "800", "--out", plain).returncode == 0
    got, ref = json.loads(out.read_text()), json.loads(plain.read_text())
    assert got["meta"]["settings"]["consistency"] and not ref["meta"]["settings"]["consistency"]
    assert 0.7 * len(ref["matches"]) < len(got["matches"]) < len(ref["matches"])
    assert {tuple(m) for m in got["matches"]} <= {tuple(m) for m in ref["matches"]}


@pytest.mark.parametrize("args, message", [
    (["match", IMG1, "missing.png", "--calib", CALIB], "image not found: missing.png"),
    (["match", IMG1, IMG2, "--calib", "missing.json"], "calibration file not found: missing.json"),
    (["match", IMG1, IMG2, "--calib", CALIB, "--out", "m.txt"], "--out must end in .json, .npz or .csv"),
    (["match", IMG1, IMG2, "--calib", CALIB, "--depth-range", "5", "1"], "zmin < zmax"),
    (["segments", IMG1, IMG2, "--calib", CALIB, "--points", "1000,3"], "outside image 1"),
    (["match", CALIB, IMG2, "--calib", CALIB], "cannot read image"),
])
def test_bad_data_gives_exit_1(tmp_path, args, message):
    r = run(*args, cwd=tmp_path)
    assert r.returncode == 1, r.stderr
    _check_no_traceback(r)
    assert message in r.stderr and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("args", [
    ["match", IMG1, IMG2, "--calib", CALIB, "--bogus"],
    ["match", IMG1, IMG2, "--tol", "wide"],
    ["match", IMG1, IMG2, "--calib", CALIB, "--detector", "surf"],
    ["segments", IMG1, IMG2, "--calib", CALIB, "--points", "1;2"],
    ["nonsense"],
    [],
])
def test_usage_errors_give_exit_2(args):
    r = run(*args)
    assert r.returncode == 2
    assert "usage:" in r.stderr
    _check_no_traceback(r)


@pytest.mark.parametrize("command", ["demo", "match", "segments", "bench"])
def test_help_has_an_example(command):
    r = run(command, "--help")
    assert r.returncode == 0 and "example" in r.stdout and f"episeg {command}" in r.stdout


def test_installed_script():
    exe = shutil.which("episeg")
    if exe is None:
        pytest.skip("the episeg script is not on PATH")
    r = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "demo" in r.stdout and "bench" in r.stdout


# --- bench (on a mocked benchmarks folder: the real run is long) --------------------------------
FAKE_SCRIPT = """\
import argparse, pathlib, sys
p = argparse.ArgumentParser()
{quick}
args = p.parse_args()
out = pathlib.Path(__file__).parent / "results"
out.mkdir(exist_ok=True)
(out / "{name}.md").write_text("quick=" + str(getattr(args, "quick", None)))
"""


def test_bench_runs_the_scripts_and_passes_quick_only_where_accepted(tmp_path):
    d = tmp_path / "benchmarks"
    d.mkdir()
    (d / "table1.py").write_text(FAKE_SCRIPT.format(quick="", name="table1"))
    (d / "compare.py").write_text(FAKE_SCRIPT.format(quick='p.add_argument("--quick", action="store_true")',
                                                     name="compare"))
    r = run("bench", "--quick", "--dir", d)
    assert r.returncode == 0, r.stderr
    assert (d / "results" / "table1.md").read_text() == "quick=None"
    assert (d / "results" / "compare.md").read_text() == "quick=True"
    assert "speed.py not found" in r.stderr
    assert str(d / "results") in r.stdout and "compare.md" in r.stdout
    (d / "compare.py").write_text("import sys; sys.exit(3)")
    r = run("bench", "--dir", d, "--only", "compare.py")
    assert r.returncode == 1 and "compare.py failed with exit code 3" in r.stderr


def test_bench_without_a_benchmarks_folder(tmp_path):
    r = run("bench", "--dir", tmp_path / "nowhere")
    assert r.returncode == 1 and "benchmarks folder not found" in r.stderr
    _check_no_traceback(r)


# --- tol auto and no pose ------------------------------------------------------------------------
def test_match_tol_auto_records_the_estimate(tmp_path):
    out = tmp_path / "m.json"
    r = run("match", IMG1, IMG2, "--calib", CALIB, "--tol", "auto", "--max-features", "800", "--out", out, "-v")
    assert r.returncode == 0, r.stderr
    meta = json.loads(out.read_text())["meta"]
    assert meta["settings"]["tol"] == "auto" and meta["pose"]["source"] == "calibration"
    assert meta["pose"]["estimated_tol"] == 2.0 and meta["pose"]["pose_kept"]
    assert "tol auto: 2.00 px, pose kept" in r.stderr
    assert set(json.loads(out.read_text())["labels"]) == {"on_segment"}


@pytest.mark.parametrize("with_intrinsics, method", [(False, "fundamental"), (True, "essential")])
def test_match_without_a_pose(tmp_path, with_intrinsics, method):
    args = []
    if with_intrinsics:
        ref = json.loads((DEFAULT / "calib.json").read_text())
        k = tmp_path / "k.json"
        k.write_text(json.dumps({"K1": ref["K1"], "K2": ref["K2"]}))
        args = ["--calib", k]
    out = tmp_path / "m.json"
    r = run("match", IMG1, IMG2, *args, "--max-features", "800", "--out", out, "-v")
    assert r.returncode == 0, r.stderr
    _check_no_traceback(r)
    data = json.loads(out.read_text())
    meta = data["meta"]
    assert meta["pose"]["source"] == f"estimated ({method} matrix)"
    assert 2.0 <= meta["pose"]["estimated_tol"] <= 8.0 and meta["pose"]["inliers"] > 50
    assert meta["counts"]["matches"] == len(data["matches"]) > 100
    assert meta["calib"] == (None if not with_intrinsics else str(args[1]))
    assert f"no pose: {method} matrix from" in r.stderr
    # the matches lie on the true segments (the bundled pair's calibration)
    calib = load_calibration(CALIB)
    from episeg_cv import filter_pairs
    ok = filter_pairs(data["matches"], data["keypoints1"], data["keypoints2"], calib.geometry, tol=3.0)
    assert ok.mean() > 0.95


def test_match_without_a_pose_rejecting_repeats(tmp_path):
    """--reject-repeats: match_without_pose(reject_repeats=True), a subset of the plain run's matches; refused
    with a calibration that holds a pose (it applies to an estimated geometry)."""
    out, plain = tmp_path / "r.json", tmp_path / "p.json"
    r = run("match", IMG1, IMG2, "--max-features", "800", "--reject-repeats", "--out", out)
    assert r.returncode == 0, r.stderr
    assert run("match", IMG1, IMG2, "--max-features", "800", "--out", plain).returncode == 0
    got, ref = json.loads(out.read_text()), json.loads(plain.read_text())
    assert got["meta"]["settings"]["reject_repeats"] and not ref["meta"]["settings"]["reject_repeats"]
    assert 0 < len(got["matches"]) <= len(ref["matches"])
    assert {tuple(m) for m in got["matches"]} <= {tuple(m) for m in ref["matches"]}
    r = run("match", IMG1, IMG2, "--calib", CALIB, "--reject-repeats", "--out", tmp_path / "x.json")
    assert r.returncode == 1 and "--reject-repeats applies when the geometry is estimated" in r.stderr
    _check_no_traceback(r)


@pytest.mark.parametrize("args, message", [
    (["--tol", "bogus"], "expected a finite number of pixels >= 0 or 'auto'"),
    (["--tol", "-2"], "expected a finite number of pixels >= 0 or 'auto'"),
    (["--constraint", "none"], "--constraint none matches with plain cv2.BFMatcher and needs no geometry"),
    (["--depth-range", "1", "5"], "--depth-range needs a calibration"),
])
def test_match_without_a_pose_errors(args, message):
    r = run("match", IMG1, IMG2, *args, "--max-features", "300")
    assert r.returncode in (1, 2) and message in r.stderr, r.stderr
    _check_no_traceback(r)


def test_match_partial_pose_and_featureless_images(tmp_path):
    ref = json.loads((DEFAULT / "calib.json").read_text())
    partial = tmp_path / "partial.json"
    partial.write_text(json.dumps({"K1": ref["K1"], "K2": ref["K2"], "R": ref["R"]}))
    r = run("match", IMG1, IMG2, "--calib", partial)
    assert r.returncode == 1 and "partial.json: missing key 't' (a vector of 3 numbers): a partial pose" in r.stderr
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((120, 160), 128, np.uint8))
    r = run("match", blank, blank)
    assert r.returncode == 1 and "cannot estimate the geometry from the images: too few matches" in r.stderr
    _check_no_traceback(r)


# --- the first run after installing ------------------------------------------------------------
@pytest.mark.parametrize("skipped", [[], ["episeg_cv.x:gone: AttributeError"]])
def test_compile_command_reports_what_it_compiled(monkeypatch, capsys, skipped):
    import importlib

    from episeg_cv import kernel_cache
    cli_main = importlib.import_module("episeg_cv.cli.main")
    calls = []

    def fake(processes=None):  # compile_kernels itself is tested in tests/core/test_kernel_cache.py
        calls.append(processes)
        return {"processes": processes or 2, "kernels": 25, "signatures": 31, "skipped": skipped, "seconds": 12.34}

    monkeypatch.setattr(kernel_cache, "compile_kernels", fake)
    assert cli_main.main(["compile", "--processes", "3"]) == 0
    out = capsys.readouterr().out
    assert calls == [3] and "compiled or loaded 25 kernels (31 signatures) in 12.3 s on 3 process(es)" in out
    assert ("1 kernel signature(s) skipped" in out) is bool(skipped)


def test_compile_command_refuses_a_bad_process_count():
    r = run("compile", "--processes", "0")
    assert r.returncode == 2 and "argument --processes: expected a positive integer, got '0'" in r.stderr


@pytest.mark.parametrize("quiet", [False, True])
def test_a_compiling_kernel_is_announced_unless_quiet(tmp_path, monkeypatch, capsys, quiet):
    import contextlib
    import importlib

    from episeg_cv import kernel_cache
    cli_main = importlib.import_module("episeg_cv.cli.main")

    @contextlib.contextmanager
    def compiling(callback):  # as numba's listener reports a kernel that starts compiling in the block
        callback("episeg_cv.matching._kernels.knn_scan")
        yield

    monkeypatch.setattr(kernel_cache, "on_first_compile", compiling)
    args = ["segments", IMG1, IMG2, "--calib", CALIB, "--random", "2", "--out", str(tmp_path / "s.png")]
    assert cli_main.main((["-q"] if quiet else []) + args) == 0
    err = capsys.readouterr().err
    notice = "episeg: compiling the kernels on their first use (up to a minute, once"
    assert (("'episeg compile' compiles them all ahead, on every core" in err) is not quiet), err
    assert (notice in err) is not quiet and err.count("compiling the kernels") == (0 if quiet else 1), err
