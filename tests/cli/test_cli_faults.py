"""Regression tests of issue 15 for the command line: outputs never replace inputs, errors name the flag.

Each case failed before the fix (benchmarks/faults.py runs these and hundreds more as a user would).
"""

import hashlib
import shutil
import subprocess
import sys

import pytest

from episeg_cv.datasets import data_dir

DEFAULT = data_dir() / "default"


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "episeg_cv.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300, cwd=cwd)


def one_error_line(r, *words):
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if "error" in ln]
    assert len(errors) == 1 and "Traceback" not in r.stderr, r.stderr
    for w in words:
        assert w in errors[0], (w, errors[0])


@pytest.fixture
def pair(tmp_path):
    for name in ("image1.png", "image2.png", "calib.json"):
        shutil.copy(DEFAULT / name, tmp_path / name)
    return tmp_path


def digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.parametrize("option, target", [("--out", "calib.json"), ("--figure", "image1.png")])
def test_match_never_writes_onto_an_input(pair, option, target):
    before = digest(pair / target)
    r = run("match", "image1.png", "image2.png", "--calib", "calib.json", option, target, cwd=pair)
    assert r.returncode == 1
    one_error_line(r, option, "input file")
    assert digest(pair / target) == before


def test_segments_never_writes_onto_an_input(pair):
    before = digest(pair / "image2.png")
    r = run("segments", "image1.png", "image2.png", "--calib", "calib.json", "--out", "image2.png", cwd=pair)
    assert r.returncode == 1 and digest(pair / "image2.png") == before
    one_error_line(r, "--out", "input file")


@pytest.mark.parametrize("args, words", [
    (["match", "image1.png", "image2.png", "--calib", "calib.json", "--max-features", "1" + "0" * 30],
     ["--max-features", "2147483647"]),
    (["match", "image1.png", "image2.png", "--calib", "calib.json", "--figure", "fig.xyz"], ["--figure", "extension"]),
    (["segments", "image1.png", "image2.png", "--calib", "calib.json", "--random", "10000000"], ["--random"]),
    (["synthetic", "room", "--views", "1"], ["--views"]),
    (["synthetic", "room", "--seed", "-1"], ["--seed"]),
    (["synthetic", "room", "--size", "100000", "100000"], ["--size"]),
    (["match", "image1.png", "image2.png", "--calib", "calib.json", "--tol", "nan"], ["--tol", "finite"]),
])
def test_bad_numbers_are_named_by_their_flag(pair, args, words):
    r = run(*args, cwd=pair)
    assert r.returncode == 2, r.stderr
    one_error_line(r, *words)
    assert not (pair / "room").exists()


def test_synthetic_refuses_a_folder_that_holds_a_model(pair):
    (pair / "room" / "model").mkdir(parents=True)
    (pair / "room" / "model" / "images.bin").write_bytes(b"keep")
    r = run("synthetic", "room", "--views", "2", "--size", "64", "48", cwd=pair)
    assert r.returncode == 1 and (pair / "room" / "model" / "images.bin").read_bytes() == b"keep"
    one_error_line(r, "already holds files")


@pytest.mark.parametrize("flag", ["-q", "-v", "--quiet"])
def test_verbosity_before_the_command(pair, flag):
    r = run(flag, "segments", "image1.png", "image2.png", "--calib", "calib.json", "--points", "100,100",
            "--out", "s.png", cwd=pair)
    assert r.returncode == 0, r.stderr
    assert (pair / "s.png").is_file()
    assert (r.stdout == "") == (flag != "-v")


def test_a_folder_given_as_an_image(pair):
    r = run("match", ".", "image2.png", "--calib", "calib.json", cwd=pair)
    assert r.returncode == 1
    one_error_line(r, "is a folder")


def test_demo_output_is_git_ignored():
    from pathlib import Path

    ignore = (Path(__file__).resolve().parents[2] / ".gitignore").read_text().split()
    assert "episeg_demo/" in ignore and "benchmarks/results/quick/" in ignore


def test_an_interrupt_wrapped_by_compiled_code_ends_with_one_notice(monkeypatch, capsys):
    """An interrupt raised inside numba's callbacks surfaces as a SystemError caused by it: the CLI must
    still end with the signal's notice and exit code, and a SystemError of its own stays a crash."""
    import signal as _signal

    import importlib

    cli_main = importlib.import_module("episeg_cv.cli.main")
    from episeg_cv.interrupts import Terminated

    def wrapped(args, console):
        try:
            raise Terminated(_signal.SIGTERM)
        except Terminated as exc:
            raise SystemError("returned a result with an exception set") from exc

    def genuine(args, console):
        raise SystemError("a real internal error")

    parser = cli_main.build_parser()
    real_parse = parser.parse_args
    for func, expect in ((wrapped, 128 + _signal.SIGTERM), (genuine, None)):
        def parse(argv=None, _func=func):
            ns = real_parse(["demo"])
            ns.func = _func
            return ns
        monkeypatch.setattr(parser, "parse_args", parse)
        monkeypatch.setattr(cli_main, "build_parser", lambda: parser)
        if expect is None:
            with pytest.raises(SystemError, match="real internal error"):
                cli_main.main([])
        else:
            assert cli_main.main([]) == expect
            err = capsys.readouterr().err
            assert err.strip() == "episeg: stopped by SIGTERM; nothing half-written was left"
