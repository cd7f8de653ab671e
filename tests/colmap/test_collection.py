"""The parts of the COLMAP path that need no pycolmap: pairs, views, depth ranges, poses JSON, the runner.

These run (and must pass) without pycolmap installed.
"""

import json

import numpy as np
import pytest

from episeg_cv import colmap
from episeg_cv import scenes
from episeg_cv.colmap import View, depth_range_from_depths, exhaustive_pairs, neighbor_pairs, overlap_scores, read_pairs
from episeg_cv.interrupts import interrupts_deferred
from episeg_cv.colmap.runner import Runner


def _view(name, k, center, target, depth_range=(0.0, np.inf)):
    R, t = scenes.look_at(center, target)
    K = [[100.0, 0, 49.5], [0, 100.0, 49.5], [0, 0, 1]]
    return View(name, k, 1, K, R, t, (100, 100), depth_range=depth_range)


def test_read_pairs(tmp_path):
    names = ["a.png", "b.png", "c.png"]
    f = tmp_path / "pairs.txt"
    f.write_text("# comment\n\na.png b.png\nc.png a.png\nb.png a.png\n")
    assert read_pairs(f, names) == [(0, 1), (0, 2)]
    f.write_text("a.png b.png\na.png nope.png\n")
    with pytest.raises(ValueError, match=r"pairs.txt:2: unknown image 'nope.png'"):
        read_pairs(f, names)
    f.write_text("a.png a.png\n")
    with pytest.raises(ValueError, match=r":1: image 'a.png' is paired with itself"):
        read_pairs(f, names)
    f.write_text("a.png\n")
    with pytest.raises(ValueError, match=r":1: expected 'name1 name2'"):
        read_pairs(f, names)
    assert exhaustive_pairs(3) == [(0, 1), (0, 2), (1, 2)]


def test_overlap_and_neighbors_follow_the_cameras():
    # a and b look the same way from 0.5 m apart; c looks back at them from 9 m: it sees
    # where a's rays end between 1 and 6 m. With depth ranges, d (turned 180 degrees
    # next to a) and e (20 m away, looking away) see nothing of what a and b see.
    dr = (1.0, 6.0)
    views = [_view("a", 1, [0, 0, 0], [0, 0, 5], dr), _view("b", 2, [0.5, 0, 0], [0.5, 0, 5], dr),
             _view("c", 3, [0.2, 0, 9], [0.2, 0, 0], dr), _view("d", 4, [0, 0, -0.2], [0, 0, -5], dr),
             _view("e", 5, [20, 0, 0], [30, 0, 1], dr)]
    s = overlap_scores(views)
    np.testing.assert_allclose(s, s.T)
    assert np.all(np.diag(s) == 0)
    assert s[0, 1] > 0.5 and s[0, 2] > 0.5 and s[0, 3] == 0 and s[1, 3] == 0 and np.all(s[4] == 0)
    assert neighbor_pairs(views, 1) == [(0, 2), (1, 2)]  # nobody chooses d or e
    assert {(0, 1), (0, 2), (1, 2)} == set(neighbor_pairs(views, 4))
    with pytest.raises(ValueError, match="neighbors"):
        neighbor_pairs(views, 0)


def test_depth_range_from_depths_is_robust():
    rng = np.random.default_rng(0)
    d = np.concatenate([rng.uniform(2, 5, 1000), [0.01, 500.0, np.nan, -1.0, np.inf]])
    zmin, zmax = depth_range_from_depths(d)
    assert 2 / 1.25 - 0.05 < zmin < 2 and 5 < zmax < 5 * 1.25 + 0.05
    assert depth_range_from_depths([]) == (0.0, np.inf)


def test_poses_json_errors_name_the_image(tmp_path):
    f = tmp_path / "poses.json"
    f.write_text(json.dumps({"images": [{"name": "a.png", "K": np.eye(3).tolist(), "R": np.eye(3).tolist(),
                                         "width": 10, "height": 10}]}))
    with pytest.raises(ValueError, match=r"image 0: missing t"):
        colmap.load_poses(f)
    f.write_text(json.dumps({"images": [{"name": "a.png", "K": np.eye(3).tolist(), "R": [[1, 0, 0], [0, 1, 0],
                                                                                       [0, 0, 2]],
                                         "t": [0, 0, 0], "width": 10, "height": 10}]}))
    with pytest.raises(ValueError, match=r"'a.png'.*R"):
        colmap.load_poses(f)
    f.write_text("{not json")
    with pytest.raises(ValueError, match="invalid JSON at line 1, column 2"):
        colmap.load_poses(f)


def test_ctrl_c_inside_a_pair_write_is_held_until_the_pair_is_written():
    import os
    import signal

    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in an interactive run
    try:
        with pytest.raises(KeyboardInterrupt):
            with interrupts_deferred():
                os.kill(os.getpid(), signal.SIGINT)
                written = True  # still runs: the interrupt waits for the end of the block
        assert written
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # as under nohup: stays ignored
        with interrupts_deferred():
            os.kill(os.getpid(), signal.SIGINT)
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)


def _square(x):
    return x * x


@pytest.mark.parametrize("workers, scheduler", [(1, None), (2, None), (1, "local:1")])
def test_runner_returns_every_item_once(workers, scheduler):
    """More items than the window of jobs in flight (a regression: one item per window was dropped)."""
    if scheduler:
        pytest.importorskip("distributed")
    runner = Runner(workers, scheduler)
    try:
        out = sorted(runner.imap(_square, range(3 * runner.window + 1)))
    finally:
        runner.close()
    assert out == [k * k for k in range(3 * runner.window + 1)]


def test_matching_kernels_release_the_gil():
    """What lets --workers run threads in parallel: every compiled loop of a pair job is nogil."""
    from numba.core.registry import CPUDispatcher

    from episeg_cv.colmap import _consensus_kernel
    from episeg_cv.matching import _index_kernels, _kernels

    kernels = [fn for module in (_kernels, _index_kernels, _consensus_kernel) for fn in vars(module).values()
               if isinstance(fn, CPUDispatcher) and not fn.targetoptions.get("inline")]
    assert len(kernels) >= 8
    for fn in kernels:
        assert fn.targetoptions.get("nogil") or fn.py_func.__name__.startswith("_"), fn.py_func.__name__


def test_threads_share_the_work(monkeypatch):
    """Two threads run two jobs at once (each waits for the other inside the job)."""
    import threading

    barrier = threading.Barrier(2, timeout=30)

    def job(x):
        barrier.wait()  # would time out if the runner ran the jobs one after the other
        return x

    runner = Runner(2)
    try:
        assert sorted(runner.imap(job, range(4))) == [0, 1, 2, 3]
    finally:
        runner.close()
    assert runner.describe == "2 threads"


_CLUSTER_CHILD = """
import os, sys, time
from episeg_cv.colmap.runner import Runner
r = Runner(1, "local:1")
print(list(r._client.run(os.getpid).values())[0], flush=True)
time.sleep(600)
"""


def test_local_cluster_workers_end_with_the_driver(tmp_path):
    """A killed run leaves no Dask worker behind (the watchdog of the worker plugin)."""
    pytest.importorskip("distributed")
    import os
    import signal
    import subprocess
    import sys
    import time

    child = subprocess.Popen([sys.executable, "-c", _CLUSTER_CHILD], stdout=subprocess.PIPE, text=True)
    try:
        line = child.stdout.readline()
        worker = int(line)
        os.kill(child.pid, signal.SIGKILL)  # no clean-up of any kind
        t_kill = time.perf_counter()
        child.wait(timeout=30)
        for _ in range(300):
            try:
                os.kill(worker, 0)
            except ProcessLookupError:
                break
            time.sleep(0.05)
        else:
            os.kill(worker, signal.SIGKILL)
            pytest.fail("the worker outlived its driver by 15 s")
        print(f"worker gone {time.perf_counter() - t_kill:.1f} s after the driver")
    finally:
        if child.poll() is None:
            child.kill()
            child.wait(timeout=30)
        child.stdout.close()


# --------------------------------------------------------------------------------------
# Middlebury *_par.txt
# --------------------------------------------------------------------------------------
def _par_folder(tmp_path, lines, header=True, images=("a.png", "b.png")):
    import cv2

    for name in images:
        cv2.imwrite(str(tmp_path / name), np.zeros((30, 40), np.uint8))
    f = tmp_path / "set_par.txt"
    f.write_text((f"{len(lines)}\n" if header else "") + "\n".join(lines) + "\n")
    return f


def _par_line(name, K, R, t):
    return " ".join([name] + [repr(float(v)) for v in np.concatenate([np.ravel(K), np.ravel(R), np.ravel(t)])])


def test_par_file_is_read_as_given(tmp_path):
    K = np.array([[50.0, 0, 19.5], [0, 51.0, 14.5], [0, 0, 1]])
    R, t = scenes.look_at([1.0, 0, -3], [0, 0, 0])
    lines = [_par_line("a.png", K, np.eye(3), [0, 0, 3]), _par_line("b.png", K, R, t)]
    views = colmap.load_par(_par_folder(tmp_path, lines), tmp_path)
    assert [v.name for v in views] == ["a.png", "b.png"] and [v.image_id for v in views] == [1, 2]
    assert [v.camera_id for v in views] == [1, 1] and views[0].image_size == (40, 30)
    np.testing.assert_allclose(views[1].K, K)  # episeg_cv's convention: as given
    assert views[1].camera_params == (50.0, 51.0, 20.0, 15.0)  # COLMAP's: +0.5
    np.testing.assert_allclose(views[1].R, R, atol=1e-12)
    # without the count line too; a rotation with rounding errors is repaired, a reflection refused
    Rr = np.round(R, 6)
    assert np.abs(Rr.T @ Rr - np.eye(3)).max() > 1e-7
    views = colmap.load_par(_par_folder(tmp_path, [_par_line("a.png", K, Rr, t)], header=False), tmp_path)
    np.testing.assert_allclose(views[0].R.T @ views[0].R, np.eye(3), atol=1e-12)
    with pytest.raises(ValueError, match=r"set_par.txt:2 \('a.png'\).*R"):
        colmap.load_par(_par_folder(tmp_path, [_par_line("a.png", K, np.diag([1.0, 1, -1]), t)]), tmp_path)


@pytest.mark.parametrize("lines, match", [
    (["a.png 1 2 3"], r"set_par.txt:2: expected 'name' and 21 numbers"),
    (["a.png " + " ".join(["x"] * 21)], r"set_par.txt:2: could not convert"),
    ([], "lists no image"),
    (["c.png " + " ".join(["1"] * 21)], r"image .*c.png' is missing"),
])
def test_par_file_errors_name_the_line(tmp_path, lines, match):
    f = _par_folder(tmp_path, lines)
    with pytest.raises(ValueError, match=match):
        colmap.load_par(f, tmp_path)


def test_par_file_count_must_agree(tmp_path):
    K = np.array([[50.0, 0, 19.5], [0, 50.0, 14.5], [0, 0, 1]])
    f = _par_folder(tmp_path, [_par_line("a.png", K, np.eye(3), [0, 0, 3])])
    f.write_text("2\n" + f.read_text().split("\n", 1)[1])
    with pytest.raises(ValueError, match="announces 2 images but lists 1"):
        colmap.load_par(f, tmp_path)
