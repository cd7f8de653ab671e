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
