"""Smoke test of benchmarks/speed.py: a tiny run writes a parseable speed.md and speed.json.

No timing is asserted (benchmarks are not tests); only that the script runs end to end
and that what it writes is complete and positive.
"""

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "speed.py"


@pytest.fixture(scope="module")
def speed():
    spec = importlib.util.spec_from_file_location("benchmarks_speed", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def tiny_run(speed, tmp_path_factory):
    out = tmp_path_factory.mktemp("speed")
    rc = speed.main(["--quick", "--sizes", "150,300", "--repeats", "1", "--image-size", "320x240", "--out", str(out)])
    return rc, out


def test_tiny_run_writes_markdown_and_json(speed, tiny_run):
    rc, out = tiny_run
    assert rc == 0
    res = json.loads((out / "speed.json").read_text())
    assert res["command"].startswith("python benchmarks/speed.py --quick --sizes 150,300")
    assert res["machine"]["cv2"] and res["machine"]["cpu_count"] >= 1
    assert list(res["poses"]) == ["forward"]
    pose = res["poses"]["forward"]
    assert list(pose["sizes"]) == ["150", "300"]
    for s in pose["sizes"].values():
        assert s["n1"] == s["n_requested"] and s["n2"] == s["n_requested"]
        assert set(s["median_s"]) == set(speed.METHODS)
        for name, times in s["times_s"].items():
            assert len(times) == 1 and all(t > 0 for t in times), name
            assert s["x_faster_than_bf"][name] > 0
        assert s["x_faster_than_bf"]["bf_knn"] == pytest.approx(1.0)
        assert 0 < s["candidates_per_query"]["segment"] <= s["candidates_per_query"]["line"] <= s["n2"]
        assert s["output_size"]["bf_knn"] == 2 * s["n1"]
    for name, ex in pose["exponent"].items():
        assert ex is not None and ex == ex, name  # two sizes: a finite slope
    assert res["targets"] == {"forward": None}  # no 10k size in this run
    assert all(t > 0 for t in res["filter"]["median_s"].values())
    assert res["filter"]["matches"] == speed.FILTER_MATCHES
    b = res["binary"]
    assert b["n1"] > 0 and b["n2"] > 0 and all(t > 0 for t in b["median_s"].values())
    assert b["output_size"]["BFMatcher knnMatch(k=2) (reference)"] > 0
    assert set(b["line_vs_segment"]) == {"match", "knnMatch(k=2)"}

    md = (out / "speed.md").read_text()
    assert res["command"] in md
    assert "## Pose `forward`" in md and "| method | n = 150 | n = 300 | exponent |" in md
    assert "Not evaluated" in md
    assert "filter` on 100,000 matches" in md
    assert "## Binary descriptors: ORB" in md


def test_targets_are_computed_from_the_numbers(speed):
    def size(seg_m, seg_k, line_m, line_k, rounds=15):
        """Per-round times: the given value, times a round factor shared by every method (machine load)."""
        load = 1 + 0.5 * np.sin(np.arange(rounds))
        base = {"bf_knn": 2.0, "segment_match": seg_m, "segment_knn": seg_k, "line_match": line_m, "line_knn": line_k}
        times = {k: [v * f for f in load] for k, v in base.items()}
        med = {k: float(np.median(v)) for k, v in times.items()}
        return {"median_s": med, "times_s": times, "x_faster_than_bf": {k: med["bf_knn"] / v for k, v in med.items()}}

    poses = {"fast": {"sizes": {"10000": size(0.05, 0.08, 0.1, 0.1)}},
             "slow": {"sizes": {"10000": size(0.2, 0.08, 0.1, 0.1)}},
             "none": {"sizes": {"5000": size(0.05, 0.05, 0.1, 0.1)}}}
    t = speed.targets(poses)
    assert t["fast"]["met"] and t["fast"]["segment_match_x"] == pytest.approx(40.0)
    # the shared load cancels in the per-round ratio: exactly 2 and 1.25, with a zero-width interval
    assert t["fast"]["segment_match_vs_line"] == pytest.approx((2.0, 2.0, 2.0))
    assert t["fast"]["segment_knn_vs_line"] == pytest.approx((1.25, 1.25, 1.25))
    assert not t["slow"]["met_20x"] and not t["slow"]["met_faster_than_line"] and not t["slow"]["met"]
    assert t["none"] is None


def test_faster_than_line_needs_the_whole_interval_above_one(speed):
    rng = np.random.default_rng(0)
    seg = np.full(15, 0.05)
    noisy = seg * rng.choice([0.8, 1.3], 15)  # sometimes faster, sometimes slower than the segment
    median, low, high = speed.ratio_interval(noisy, seg)
    assert low < 1 < high and low <= median <= high
    times = {"bf_knn": [2.0] * 15, "segment_match": seg, "line_match": noisy, "segment_knn": seg, "line_knn": 2 * seg}
    s = {"median_s": {k: float(np.median(v)) for k, v in times.items()}, "times_s": times}
    s["x_faster_than_bf"] = {k: 2.0 / v for k, v in s["median_s"].items()}
    t = speed.targets({"p": {"sizes": {"10000": s}}})["p"]
    assert t["met_20x"] and not t["met_faster_than_line"] and not t["met"]


def test_bad_arguments_exit(speed):
    with pytest.raises(SystemExit):
        speed.parse_args(["--repeats", "0"])
    with pytest.raises(SystemExit):
        speed.parse_args(["--sizes", "10,x"])
