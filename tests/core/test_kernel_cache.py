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
