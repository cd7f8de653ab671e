"""set_num_threads / get_num_threads, and results that are the same bits for every thread count.

The parallel kernels keep per-thread minima under total orders and merge them; the serial twins run
the same code on one thread. Every output of the array API is compared byte for byte between one
and two threads, on several poses, both constraints, L2 and Hamming, with descriptors full of ties
(small integers), and with the serial/parallel switch forced to the parallel kernels.
"""

import copy
import threading

import cv2
import numba
import numpy as np
import pytest

import episeg_cv
from episeg_cv import (CandidateIndex, SearchConfig, TwoViewGeometry, guided_matches, knn_descriptors,
                       match_descriptors, radius_descriptors, threads)
from episeg_cv.matching import guided
from episeg_cv.matching.guided import MatchInputs

TWO = numba.config.NUMBA_NUM_THREADS >= 2
needs_two = pytest.mark.skipif(not TWO, reason="numba has a single thread here")

SIZE = (320, 240)
K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])


def rot(v):
    return cv2.Rodrigues(np.asarray(v, float).reshape(3, 1))[0]


#: Poses: forward (epipole inside), lateral (epipole at infinity), converging, backward, pure rotation.
POSES = {
    "forward": (np.eye(3), [0.02, 0.01, -1.0]),
    "lateral": (np.eye(3), [-1.0, 0.0, 0.0]),
    "converging": (rot([0, 0.25, 0.02]), [-1.0, 0.05, 0.3]),
    "backward": (rot([0.01, -0.02, 0]), [0.0, 0.05, 1.0]),
    "rotation": (rot([0.02, 0.03, 0.01]), [0.0, 0.0, 0.0]),
}


def problem(pose, norm, n1=2500, n2=2700, seed=0):
    R, t = POSES[pose]
    g = TwoViewGeometry(K, K, R, t, image_size1=SIZE, image_size2=SIZE)
    rng = np.random.default_rng(seed)
    p1 = rng.uniform(-0.5, np.array(SIZE) - 0.5, (n1, 2))
    p2 = rng.uniform(-0.5, np.array(SIZE) - 0.5, (n2, 2))
    if norm == "hamming":  # 2 bytes: many equal distances
        d1, d2 = (rng.integers(0, 256, (n, 2), dtype=np.uint8) for n in (n1, n2))
    else:  # small integers: many equal scores
        d1, d2 = (rng.integers(0, 3, (n, 6)).astype(np.float32) for n in (n1, n2))
    return g, p1, p2, d1, d2


@pytest.fixture
def always_parallel(monkeypatch):
    """Parallel kernels even for small inputs; the thread count restored after."""
    monkeypatch.setattr(threads, "MIN_PARALLEL_ITEMS", 1)
    threads.set_num_threads(None)  # (whatever an earlier test left)
    before = numba.get_num_threads()
    yield
    threads.set_num_threads(None)
    numba.set_num_threads(before)


def outputs(g, p1, p2, d1, d2, norm, constraint):
    """Every array the matcher returns for these inputs, as bytes."""
    out = {}
    for k in (1, 2, 3):
        nb = knn_descriptors(d1, d2, p1, p2, g, k=k, norm=norm, constraint=constraint)
        out[f"knn{k}"] = [nb.indices, nb.distances, nb.counts, nb.column_best]
    out["match"] = list(match_descriptors(d1, d2, p1, p2, g, norm=norm, constraint=constraint))
    out["cross_check"] = list(match_descriptors(d1, d2, p1, p2, g, norm=norm, constraint=constraint,
                                                cross_check=True, ratio=0.9))
    gm = guided_matches(d1, d2, p1, p2, g, norm=norm, constraint=constraint, pad=64)
    out["guided"] = [gm.pairs, gm.distances, gm.ratio, gm.mutual, gm.candidates]
    out["radius"] = list(radius_descriptors(d1, d2, p1, p2, g, norm=norm, constraint=constraint,
                                            max_distance=2.0 if norm == "hamming" else 1.5))
    out["pairs"] = [CandidateIndex(g, p1, p2, constraint=constraint).pairs()]
    seg = g.segments(p1, margin=2.0)
    out["segments"] = [seg.start, seg.end, seg.valid, seg.line, seg.infinity_point, seg.line_start, seg.line_end]
    return {k: [(a.dtype.str, a.shape, a.tobytes()) for a in map(np.asarray, v)] for k, v in out.items()}


@needs_two
@pytest.mark.parametrize("pose", list(POSES))
@pytest.mark.parametrize("norm", ["l2", "hamming"])
@pytest.mark.parametrize("constraint", ["segment", "line"])
def test_same_bits_for_one_and_two_threads(always_parallel, pose, norm, constraint):
    g, p1, p2, d1, d2 = problem(pose, norm)
    got = {}
    for n in (1, 2):
        numba.set_num_threads(n)
        assert episeg_cv.get_num_threads() == n  # the default follows numba's setting of this thread
        got[n] = outputs(g, p1, p2, d1, d2, norm, constraint)
    assert sum(len(v[0][2]) for v in got[1].values()) > 0
    for key in got[1]:
        assert got[1][key] == got[2][key], key


@needs_two
def test_same_bits_through_set_num_threads_and_default_switch(always_parallel, monkeypatch):
    g, p1, p2, d1, d2 = problem("converging", "l2", n1=3000, n2=3000, seed=1)
    got = []
    for n, min_items in ((1, 1), (2, 1), (2, 10**9)):  # one thread; two; two but below the switch (serial)
        monkeypatch.setattr(threads, "MIN_PARALLEL_ITEMS", min_items)
        episeg_cv.set_num_threads(n)
        got.append(outputs(g, p1, p2, d1, d2, "l2", "segment"))
    assert got[0] == got[1] == got[2]


def test_scan_accumulates_over_groups_of_rows():
    """Two indexes over disjoint groups of rows, scanned into the same arrays, give the whole scan."""
    g, p1, p2, d1, d2 = problem("forward", "l2", n1=800, n2=900, seed=2)
    inp = MatchInputs.check(d1, d2, p1, p2, "l2")
    index = CandidateIndex.build(g, p1, p2, SearchConfig())
    whole = guided._scan(index, inp.distances, 2)
    rows = np.arange(len(index.q_sorted))
    parts = []
    for sel in (rows % 3 == 0, rows % 3 != 0):
        part = copy.copy(index)
        part.q_sorted, part.q_start, part.q_stop = index.q_sorted[sel], index.q_start[sel], index.q_stop[sel]
        parts.append(part)
    acc = guided._Scan.empty(len(p1), len(p2), 2)
    for part in parts:
        acc.add(part, inp.distances)
    for a, b in zip((whole.indices, whole.scores, whole.counts, whole.column_best, whole.column_scores),
                    (acc.indices, acc.scores, acc.counts, acc.column_best, acc.column_scores)):
        np.testing.assert_array_equal(a, b)
    assert whole.counts.sum() > 0


def test_set_and_get():
    try:
        episeg_cv.set_num_threads(1)
        assert episeg_cv.get_num_threads() == 1
        episeg_cv.set_num_threads(10**6)  # clipped to what numba started with
        assert episeg_cv.get_num_threads() == numba.config.NUMBA_NUM_THREADS
        episeg_cv.set_num_threads(np.int64(1))
        assert episeg_cv.get_num_threads() == 1
    finally:
        episeg_cv.set_num_threads(None)
    assert episeg_cv.get_num_threads() == numba.get_num_threads()


@pytest.mark.parametrize("bad, error", [(0, ValueError), (-1, ValueError), (1.5, TypeError), (True, TypeError),
                                        ("2", TypeError)])
def test_bad_counts_are_refused(bad, error):
    with pytest.raises(error, match="n must be an int >= 1 or None"):
        episeg_cv.set_num_threads(bad)


def test_the_setting_holds_in_other_python_threads():
    """numba's own setting is per Python thread; the library's is for the process, and restored after a call."""
    seen = {}

    def work():
        seen["get"] = episeg_cv.get_num_threads()
        seen["inside"] = threads.call_parallel(numba.get_num_threads)
        seen["after"] = numba.get_num_threads()

    try:
        episeg_cv.set_num_threads(1)
        t = threading.Thread(target=work)
        t.start()
        t.join()
    finally:
        episeg_cv.set_num_threads(None)
    assert seen["get"] == 1 and seen["inside"] == 1
    assert seen["after"] == numba.config.NUMBA_NUM_THREADS  # a new thread's numba default, untouched


def test_scratch_buffers_are_per_thread_and_grow():
    s = threads.Scratch()
    a = s.get("x", (4, 3), np.float32)
    assert a.shape == (4, 3) and a.dtype == np.float32 and a.flags.c_contiguous
    b = s.get("x", (2, 2), np.int64)
    assert np.shares_memory(a, b)  # the same buffer, reused
    c = s.get("x", (100, 100), np.float64)
    assert c.shape == (100, 100) and not np.shares_memory(a, c)
    other = {}
    t = threading.Thread(target=lambda: other.setdefault("buf", s.get("x", (4, 3), np.float32)))
    t.start()
    t.join()
    assert not np.shares_memory(other["buf"], c)


def test_an_interrupt_inside_a_parallel_kernel_is_an_interrupt():
    """A Ctrl-C that lands inside a numba parallel kernel came out as a SystemError ("returned a result with
    an exception set"), which the CLI printed as a traceback; it must be the KeyboardInterrupt itself."""

    def kernel(x):  # what numba's dispatcher raises when the signal handler ran inside the launch
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise SystemError("CPUDispatcher(kernel) returned a result with an exception set") from exc

    with pytest.raises(KeyboardInterrupt):
        threads.call_parallel(kernel, 1)

    def broken(x):
        raise SystemError("a real internal error")

    with pytest.raises(SystemError, match="real internal error"):
        threads.call_parallel(broken, 1)


def test_an_interrupt_inside_a_serial_kernel_is_an_interrupt():
    """CI: SIGTERM landed while a serial kernel (numba unpickling a constant) ran, and came out as a
    SystemError with a traceback instead of the one-line notice."""
    from episeg_cv.interrupts import Terminated

    def serial(x):
        try:
            raise Terminated(15)
        except Terminated as exc:
            raise SystemError("CPUDispatcher(serial) returned a result with an exception set") from exc

    with pytest.raises(Terminated):
        threads.run(serial, None, 1, 0)


def test_limit_this_thread_caps_only_the_calling_thread():
    import threading as _threading

    threads.set_num_threads(None)
    full = threads.get_num_threads()
    seen = {}

    def worker():
        threads.limit_this_thread(1)
        seen["worker"] = threads.get_num_threads()
        seen["parallel"] = threads.use_parallel(10**6)
        threads.limit_this_thread(None)
        seen["after"] = threads.get_num_threads()

    t = _threading.Thread(target=worker)
    t.start()
    t.join()
    assert seen == {"worker": 1, "parallel": False, "after": full}
    assert threads.get_num_threads() == full  # the main thread was never capped
    for bad, error in ((0, ValueError), (-1, ValueError), (1.5, TypeError), (True, TypeError), ("2", TypeError)):
        with pytest.raises(error, match="n must be an int >= 1 or None"):
            threads.limit_this_thread(bad)


def test_the_thread_runner_gives_each_worker_one_kernel_thread():
    """On 24 views, 2 thread workers ran at 0.94x of one: every pair also forked kernel threads."""
    from episeg_cv.colmap.runner import Runner

    runner = Runner(workers=2)
    try:
        got = list(runner.imap(lambda _: threads.get_num_threads(), range(6)))
    finally:
        runner.close()
    assert got == [1] * 6


def test_an_interrupt_several_system_errors_deep_is_an_interrupt():
    """The CI trace: Terminated, then three SystemErrors wrapping each other (numba's unpickling inside a
    kernel called by a kernel); looking one cause deep missed it."""
    from episeg_cv.interrupts import Terminated, interrupt_in

    def serial(x):
        try:
            try:
                try:
                    raise Terminated(15)
                except Terminated as exc:
                    raise SystemError("_numba_unpickle returned a result with an exception set") from exc
            except SystemError as exc:
                raise SystemError("_numba_unpickle returned a result with an exception set") from exc
        except SystemError as exc:
            raise SystemError("CPUDispatcher(spread_keys) returned a result with an exception set") from exc

    with pytest.raises(Terminated):
        threads.run(serial, None, 1, 0)
    assert interrupt_in(SystemError("a real internal error")) is None and interrupt_in(None) is None


def _omp_policy_shown(env):
    """The spin count GNU OpenMP reports (``OMP_DISPLAY_ENV=VERBOSE``) when a fresh process, with ``env``
    added to its environment, first uses the library's threads (0: passive; 300000 when nothing is set;
    more for active), and the process's ``GOMP_SPINCOUNT`` after that."""
    import os
    import subprocess
    import sys
    env = {**{k: v for k, v in os.environ.items()
                 if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "NUMBA_THREADING_LAYER")}, **env}
    env["OMP_DISPLAY_ENV"] = "VERBOSE"
    code = ("import os, numba, episeg_cv; episeg_cv.get_num_threads(); "
            "print('LAYER', numba.threading_layer()); print('AFTER', os.environ.get('GOMP_SPINCOUNT'))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    text = out.stdout + out.stderr
    if "LAYER omp" not in text:
        pytest.skip("numba's threading layer here is not OpenMP")
    shown = [line.split("=", 1)[1].strip().strip("'") for line in text.splitlines()
             if line.strip().startswith("GOMP_SPINCOUNT")]
    after = [line.split(" ", 1)[1] for line in text.splitlines() if line.startswith("AFTER")]
    return shown, after


def test_numba_threads_spin_briefly_and_the_environment_is_left_as_it_was():
    shown, after = _omp_policy_shown({})
    assert shown == [str(threads.SPIN_COUNT)]
    assert after == ["None"]


@pytest.mark.parametrize("env, check", [
    ({"OMP_WAIT_POLICY": "ACTIVE"}, lambda n: n > 300000),
    ({"OMP_WAIT_POLICY": "PASSIVE"}, lambda n: n == 0),
    ({"GOMP_SPINCOUNT": "12345"}, lambda n: n == 12345),
])
def test_a_wait_policy_in_the_environment_is_kept(env, check):
    shown, _ = _omp_policy_shown(env)
    assert check(int(shown[0])), shown
