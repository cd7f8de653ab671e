"""Smoke test of benchmarks/speed.py: a tiny run writes a parseable speed.md and speed.json.

No timing is asserted (benchmarks are not tests); only that the script runs end to end, that what it
writes is complete and positive, and that the goals are computed from the numbers.
"""

import importlib.util
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

import episeg_cv

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "speed.py"


@pytest.fixture(scope="module")
def speed():
    spec = importlib.util.spec_from_file_location("benchmarks_speed", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def tiny_run(speed, tmp_path_factory):
    """A tiny run with the segment-tree peer made unavailable (whatever the environment says)."""
    peer = sys.modules["_peer"]
    saved = peer._module, peer._why
    mp = pytest.MonkeyPatch()
    mp.setenv(peer.ENV, str(tmp_path_factory.mktemp("no_peer")))
    peer._module = None
    out = tmp_path_factory.mktemp("speed")
    cv2_threads = cv2.getNumThreads()
    try:
        rc = speed.main(["--quick", "--sizes", "150,300", "--repeats", "1", "--image-size", "320x240",
                         "--threads", "1,2", "--out", str(out)])
    finally:
        mp.undo()
        peer._module, peer._why = saved
        episeg_cv.set_num_threads(None)  # the run sets the thread counts of the process
        cv2.setNumThreads(cv2_threads)
    return rc, out


def test_tiny_run_writes_markdown_and_json(speed, tiny_run):
    rc, out = tiny_run
    assert rc == 0
    res = json.loads((out / "speed.json").read_text())
    assert res["command"].startswith("python benchmarks/speed.py --quick --sizes 150,300")
    assert res["machine"]["cv2"] and res["machine"]["cpu_count"] >= 1
    assert res["config"]["threads"] == [1, 2]
    assert list(res["poses"]) == ["forward"]
    pose = res["poses"]["forward"]
    assert list(pose["sizes"]) == ["150", "300"]
    for s in pose["sizes"].values():
        assert s["n1"] == s["n_requested"] and s["n2"] == s["n_requested"]
        assert set(s["threads"]) == {"1", "2"}
        for t in s["threads"].values():
            assert set(t["median_s"]) == set(speed.METHODS)
            for name, times in t["times_s"].items():
                assert len(times) == 1 and all(v > 0 for v in times), name
                assert t["x_faster_than_bf"][name] > 0
            assert t["x_faster_than_bf"]["bf_knn"] == pytest.approx(1.0)
        assert 0 < s["candidates_per_query"]["segment"] <= s["candidates_per_query"]["line"] <= s["n2"]
        assert s["output_size"]["bf_knn"] == 2 * s["n1"]
    for name, ex in pose["exponent"].items():
        assert ex is not None and ex == ex, name  # two sizes: a finite slope
    assert res["goals"]["poses"] == {"forward": None}  # no 10k size in this run
    # stages at the largest size, both constraints, both thread counts, a positive floor
    st = res["stages"]
    assert st["n1"] == 300 and set(st["constraints"]) == {"segment", "line"}
    for r in st["constraints"].values():
        assert set(r["by_threads"]) == {"1", "2"}
        for b in r["by_threads"].values():
            assert set(b["stages_wall_s"]) == set(speed._stages.STAGES) and b["core_wall_s"] > 0
        assert r["floor"]["time_s"] > 0 and r["floor"]["candidates"] > 0
        assert set(r["amdahl"]) == set(speed._stages.STAGES)
        assert all(0 <= v["p"] <= 1 for v in r["amdahl"].values())
    assert res["goals"]["floor"]["segment"]["x"] > 0
    # the peer was unavailable: the race has our rows only, and the report says why and how to build it
    race = res["race"]
    assert not race["available"] and "no guided_desc_match" in race["why_unavailable"]
    assert list(race["sizes"]) == ["150", "300"]
    for s in race["sizes"].values():
        assert set(s["threads"]["1"]) == {"ours segment", "ours line"}
        assert all(v["correct"] <= v["matches"] for v in s["threads"]["1"].values())
    assert res["goals"]["race"] is None
    assert set(res["amdahl"]["forward"]) == set(speed.METHODS)
    assert all(t > 0 for t in res["filter"]["median_s"].values())
    assert res["filter"]["matches"] == speed.FILTER_MATCHES
    b = res["binary"]
    assert b["n1"] > 0 and b["n2"] > 0 and all(t > 0 for t in b["median_s"].values())
    assert b["output_size"]["BFMatcher knnMatch(k=2) (reference)"] > 0
    assert set(b["line_vs_segment"]) == {"match", "knnMatch(k=2)"}

    md = (out / "speed.md").read_text()
    assert res["command"] in md
    assert "## Pose `forward`" in md and "| method | n = 150 | n = 300 |" in md
    assert "x faster than `cv2.BFMatcher.knnMatch(k=2)`, 1 thread(s)" in md
    assert "not evaluated: no n = 10k" in md
    assert "The peer is not available here" in md and "EPISEG_PEER_PATH" in md
    assert "## Stages of `match` at n = 300" in md and "Amdahl" in md
    assert "filter` on 100,000 matches" in md
    assert "## Binary descriptors: ORB" in md


def _size(rounds=15, **base):
    """Per-round times: the given values times a round factor shared by every method (machine load)."""
    load = 1 + 0.5 * np.sin(np.arange(rounds))
    full = {k: 0.1 for k in ("bf_ratio_line", "flann_ratio", "segment_arrays", "line_arrays")}
    full.update(base)
    times = {k: [v * f for f in load] for k, v in full.items()}
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {"median_s": med, "times_s": times, "x_faster_than_bf": {k: med["bf_knn"] / v for k, v in med.items()}}


def test_goals_are_computed_from_the_numbers(speed):
    fast1 = _size(bf_knn=6.0, segment_match=0.08, segment_knn=0.09, line_match=0.16, line_knn=0.14)
    fast2 = _size(bf_knn=3.0, segment_match=0.04, segment_knn=0.05, line_match=0.08, line_knn=0.06)
    poses = {"fast": {"sizes": {"10000": {"threads": {"1": fast1, "2": fast2}}}},
             "none": {"sizes": {"5000": {"threads": {"1": fast1}}}}}
    g = speed.pose_goals(poses)
    assert g["none"] is None
    one, two = g["fast"]["by_threads"]["1"], g["fast"]["by_threads"]["2"]
    assert one["segment_match_x"] == pytest.approx(75.0) and one["met_x"]
    # the shared load cancels in the per-round ratio: exactly 2 and 1.555..., a zero-width interval
    assert one["segment_match_vs_line"] == pytest.approx((2.0, 2.0, 2.0))
    assert one["segment_knn_vs_line"][0] == pytest.approx(0.14 / 0.09) and one["met_vs_line"]
    assert two["segment_match_x"] == pytest.approx(75.0) and two["met_x"]
    assert two["segment_knn_vs_line"][0] == pytest.approx(1.2) and not two["met_vs_line"]  # knnMatch: 1.2 < 1.5
    sc = g["fast"]["scaling"]
    assert sc["per_method"]["segment_match"][0] == pytest.approx(2.0)
    assert sc["per_method"]["segment_knn"][0] == pytest.approx(1.8) and sc["met"]
    slow = _size(bf_knn=3.0, segment_match=0.1, segment_knn=0.1, line_match=0.1, line_knn=0.1)
    g = speed.pose_goals({"slow": {"sizes": {"10000": {"threads": {"1": slow}}}}})["slow"]
    assert not g["by_threads"]["1"]["met_x"] and not g["by_threads"]["1"]["met_vs_line"] and g["scaling"] is None


def test_floor_and_race_goals(speed):
    stages = {"n1": 10000, "constraints": {
        "segment": {"by_threads": {"1": {"core_cpu_s": 0.02}}, "floor": {"time_s": 0.002}},
        "line": {"by_threads": {"1": {"core_cpu_s": 0.024}}, "floor": {"time_s": 0.009}}}}
    f = speed.floor_goal(stages)
    assert f["segment"]["x"] == pytest.approx(10.0) and not f["segment"]["met"]
    assert f["line"]["x"] == pytest.approx(24 / 9) and f["line"]["met"] and not f["met"]
    assert speed.floor_goal(None) is None

    def row(t, correct):
        return {"median_s": t, "correct": correct}

    race = {"available": True, "sizes": {"10000": {"threads": {"1": {
        "ours segment": row(0.02, 99), "ours line": row(0.025, 100), "peer tree": row(0.04, 100),
        "peer hash": row(0.02, 100)}}}}}
    r = speed.race_goal(race)
    tree, hash_ = r["by_size"]["10000"]["1"]["peer tree"], r["by_size"]["10000"]["1"]["peer hash"]
    assert not tree["ours segment"]["met"] and tree["ours line"]["met"] and tree["met"]  # the line: faster, as many
    assert tree["ours segment"]["x_faster"] == pytest.approx(2.0) and tree["ours segment"]["correct_diff"] == -1
    assert not hash_["met"] and not r["met"]
    assert speed.race_goal({"available": False, "sizes": {}}) is None


def test_amdahl(speed):
    st = speed._stages
    assert st.parallel_fraction(10.0, 5.0) == 1.0 and st.parallel_fraction(10.0, 10.0) == 0.0
    assert st.parallel_fraction(10.0, 6.0) == pytest.approx(0.8) and st.parallel_fraction(10.0, 12.0) == 0.0
    assert st.on_cores(10.0, 0.8, 16) == pytest.approx(10 * (0.2 + 0.05))


@pytest.mark.skipif(not __import__("os").environ.get("EPISEG_PEER_PATH"), reason="EPISEG_PEER_PATH is not set")
def test_race_with_the_peer(speed):
    if sys.modules["_peer"].load() is None:
        pytest.skip(f"the peer does not load: {sys.modules['_peer'].why_unavailable()}")
    r = speed.run_race("forward", (200,), 1, (320, 240), (1,))
    row = r["sizes"]["200"]["threads"]["1"]
    assert {"ours segment", "ours line", "peer tree", "peer hash"} <= set(row)
    # the tree tests the same band as our line: the same candidates, hence the same matches (within rounding)
    cand = r["sizes"]["200"]["candidates_per_query"]
    assert cand["peer tree"] == pytest.approx(cand["ours line"], rel=0.01)
    assert abs(row["peer tree"]["matches"] - row["ours line"]["matches"]) <= 2


def test_bad_arguments_exit(speed):
    for bad in (["--repeats", "0"], ["--sizes", "10,x"], ["--threads", "0"], ["--threads", "a"]):
        with pytest.raises(SystemExit):
            speed.parse_args(bad)
