"""Smoke test of benchmarks/contention.py (without its consensus part, which renders a 24-view room): a tiny
run writes its table, and each row ran with the wait policy it names (GNU OpenMP's own report of its spin
count: the library's short spin, 0 for passive, 300000 for GNU's default).

No timing is asserted (benchmarks are not tests)."""

import json
import subprocess
import sys
from pathlib import Path

import numba
import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "contention.py"


def test_a_tiny_run_writes_its_table_with_the_policy_of_each_row(tmp_path):
    out = subprocess.run([sys.executable, str(SCRIPT), "--calls", "1", "--n", "300", "--image-size", "320x240",
                          "--no-consensus", "--out", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    data = json.loads((tmp_path / "contention.json").read_text())
    assert [(r["policy"].split()[0], r["load"]) for r in data["rows"]] == [
        (p, load) for load in ("idle", "one busy process") for p in ("library", "passive", "GNU")]
    assert data["consensus"] == []
    try:
        numba.threading_layer()
    except ValueError:
        numba.get_num_threads()
    if numba.threading_layer() != "omp":
        pytest.skip("numba's threading layer here is not OpenMP")
    from episeg_cv.threads import SPIN_COUNT
    assert [r["times"]["gomp_spincount"] for r in data["rows"]] == [str(SPIN_COUNT), "0", "300000"] * 2
    for r in data["rows"]:
        for n in ("1", "2"):
            assert r["times"][n]["median_ms"] > 0 and r["times"][n]["x_bf"] > 0
    md = (tmp_path / "contention.md").read_text()
    assert "python benchmarks/contention.py --calls 1 --n 300 --image-size 320x240 --no-consensus" in md
    assert md.count("| library default (short spin) |") == 2
