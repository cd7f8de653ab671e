"""``kernel_cache.on_first_compile``: called once when a kernel compiles, never when numba's cache has it."""

import os
import subprocess
import sys

import numba as nb
import numpy as np
import pytest

from episeg_cv.kernel_cache import on_first_compile

SCRIPT = """
import numpy as np
from episeg_cv.kernel_cache import on_first_compile
from episeg_cv._finite_kernels import largest_magnitude
seen = []
with on_first_compile(seen.append):
    largest_magnitude(np.ones(3, np.float32))
    largest_magnitude(np.ones(3, np.float64))  # a second compile (another signature): no second call
print(seen)
"""


def _run(cache):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    r = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip()


def test_called_once_on_an_empty_cache_and_not_once_cached(tmp_path):
    assert _run(tmp_path) == "['episeg_cv._finite_kernels.magnitude_bits']"
    assert any(tmp_path.rglob("*.nbi"))  # numba wrote the cache there
    assert _run(tmp_path) == "[]"  # loaded from the cache: nothing compiles


def test_kernels_of_other_packages_do_not_count():
    @nb.njit
    def not_ours(x):  # compiled here, in the tests' module
        return x + 1

    seen = []
    with on_first_compile(seen.append):
        assert not_ours(np.int64(2)) == 3
    with on_first_compile(seen.append, package=__name__[:-1]):  # a prefix of the module's name is another
        assert not_ours(np.int32(2)) == 3
    assert seen == []
    with on_first_compile(seen.append, package=__name__):
        assert not_ours(2.5) == 3.5  # a new signature: compiled now
    assert seen == [f"{__name__}.test_kernels_of_other_packages_do_not_count.<locals>.not_ours"]


def test_the_listener_is_removed_after_the_block():
    @nb.njit
    def later(x):
        return x * 2

    seen = []
    with on_first_compile(seen.append, package=__name__):
        pass
    later(3)
    assert seen == []


def test_callback_must_be_callable():
    with pytest.raises(TypeError, match="callback must be callable, got str"):
        with on_first_compile("print"):
            pass


# --------------------------------------------------------------------------------------
# compile_kernels: the recorded kernels compiled ahead, in several processes

import json  # noqa: E402

from numba.core import types as nbt  # noqa: E402
from numba.core.registry import CPUDispatcher  # noqa: E402

from episeg_cv import kernel_cache  # noqa: E402
from episeg_cv.kernel_cache import SIGNATURES, compile_kernels  # noqa: E402

CHEAP = "episeg_cv._finite_kernels:magnitude_bits"
#: Its entry as the list records one (the type of ``largest_magnitude`` of float32 descriptors).
CHEAP_ENTRY = {"seconds": 0.1, "parallel": False, "signatures": [["Array(uint32, 1, 'C', False, aligned=True)",
                                                                  "uint32"]]}


def test_every_recorded_kernel_exists_and_its_types_parse():
    """The list is recorded from the commands (``benchmarks/first_run.py --record``): a kernel renamed or
    removed since, or a type this numba cannot read, fails here (record it again)."""
    listed = json.loads(SIGNATURES.read_text())["kernels"]
    assert len(listed) >= 10
    for name, entry in listed.items():
        module, _, qualname = name.partition(":")
        kernel = getattr(__import__(module, fromlist=[qualname]), qualname)
        assert isinstance(kernel, CPUDispatcher), name
        assert bool(kernel.targetoptions.get("parallel")) == entry["parallel"], name
        assert entry["seconds"] > 0 and entry["signatures"], name
        for sig in entry["signatures"]:
            assert all(isinstance(kernel_cache._argument_type(t), nbt.Type) for t in sig), (name, sig)


@pytest.mark.parametrize("text, expected", [
    ("int64", nbt.int64),
    ("float64", nbt.float64),
    ("bool", nbt.boolean),
    ("Array(float64, 2, 'C', False, aligned=True)", nbt.Array(nbt.float64, 2, "C")),
    ("Array(float32, 1, 'A', True, aligned=True)", nbt.Array(nbt.float32, 1, "A", readonly=True)),
    ("Literal[bool](True)", nbt.literal(True)),
])
def test_argument_types_read_back_from_their_repr(text, expected):
    assert kernel_cache._argument_type(text) == expected
    assert repr(expected) == text  # the form the list records


def _listing(tmp_path, kernels):
    path = tmp_path / "kernels.json"
    path.write_text(json.dumps({"kernels": kernels}))
    return path


def test_compiles_into_an_empty_cache_then_loads(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    out = compile_kernels(2, functions=[CHEAP], signatures=_listing(tmp_path, {CHEAP: CHEAP_ENTRY}))
    assert (out["processes"], out["kernels"], out["signatures"], out["skipped"]) == (1, 1, 1, [])
    assert any(cache.rglob("*magnitude_bits*.nbi"))  # written to the cache the environment names
    # a process of the commands now loads it: nothing of it compiles
    script = ("import numpy as np\nfrom episeg_cv.kernel_cache import on_first_compile\n"
              "from episeg_cv._finite_kernels import largest_magnitude\nseen = []\n"
              "with on_first_compile(seen.append):\n    largest_magnitude(np.ones(3, np.float32))\nprint(seen)")
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                       env=dict(os.environ, NUMBA_CACHE_DIR=str(cache)))
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stderr


def test_kernels_are_shared_out_longest_first_and_stale_entries_are_skipped(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    path = _listing(tmp_path, {
        CHEAP: CHEAP_ENTRY,
        "episeg_cv._finite_kernels:no_such_kernel": {"seconds": 9.0, "parallel": False, "signatures": [["int64"]]},
        "episeg_cv._finite_kernels:largest_magnitude": {"seconds": 5.0, "parallel": False, "signatures": [["int64"]]},
    })
    out = compile_kernels(3, signatures=path)
    assert out["processes"] == 3 and out["kernels"] == 1 and out["signatures"] == 1
    assert len(out["skipped"]) == 2  # a kernel this version lacks; a function that is not a kernel
    assert any("no_such_kernel" in s for s in out["skipped"]) and any("largest_magnitude" in s for s in out["skipped"])


def test_a_signature_the_kernel_no_longer_takes_is_skipped(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    path = _listing(tmp_path, {CHEAP: {"seconds": 1.0, "parallel": False, "signatures": [["float64", "float64"]]}})
    out = compile_kernels(1, signatures=path)
    assert out["kernels"] == 1 and out["signatures"] == 0 and len(out["skipped"]) == 1


def test_on_one_core_the_parallel_twins_are_left_out(tmp_path, monkeypatch):
    import numba

    monkeypatch.setattr(numba.config, "NUMBA_NUM_THREADS", 1)
    path = _listing(tmp_path, {"episeg_cv._finite_kernels:magnitude_bits_parallel":
                               {"seconds": 1.0, "parallel": True, "signatures": [["int64"]]}})
    out = compile_kernels(2, signatures=path)
    assert (out["processes"], out["kernels"], out["signatures"]) == (0, 0, 0)


@pytest.mark.parametrize("kwargs, error, match", [
    ({"processes": 0}, ValueError, "processes must be an int >= 1 or None, got 0"),
    ({"processes": 1.5}, TypeError, "processes must be an int >= 1 or None, got float"),
    ({"processes": True}, TypeError, "processes must be an int >= 1 or None, got bool"),
    ({"functions": CHEAP}, TypeError, "functions must be a sequence of 'module:function' names"),
    ({"functions": ["episeg_cv:nope"]}, ValueError, "functions: 'episeg_cv:nope' is not a kernel of"),
])
def test_bad_arguments(kwargs, error, match):
    with pytest.raises(error, match=match):
        compile_kernels(**kwargs)


def test_a_failing_process_is_an_error_with_its_message(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    # importing the CLI's __main__ runs the command line: the process exits with argparse's usage error
    path = _listing(tmp_path, {"episeg_cv.cli.__main__:main": {"seconds": 1.0, "parallel": False,
                                                               "signatures": [["int64"]]}})
    with pytest.raises(RuntimeError, match=r"compiling the kernels failed in 1 of 1 processes: .*error"):
        compile_kernels(1, signatures=path)
