"""End-to-end smoke run of benchmarks/compare.py on small scenes (no exact figures checked)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "compare.py"


@pytest.mark.skipif(not SCRIPT.exists(), reason="benchmarks/ not present (installed from a wheel)")
def test_compare_quick_produces_sane_tables(tmp_path):
    out = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--quiet", "--scenes", "forward", "motorcycle",
                          "--out", str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    md = (tmp_path / "compare.md").read_text()
    for heading in ("## Per scene", "## Summary over all scenes", "## Choosing the acceptance rule",
                    "## Outliers surviving", "## Search space"):
        assert heading in md
    data = json.loads((tmp_path / "compare.json").read_text())
    assert [r["scene"] for r in data["results"]] == ["forward", "motorcycle"]
    for res in data["results"]:
        assert res["matchable"] > 50
        for curve in list(res["curves"].values()) + list(res["rules"].values()):
            assert all(0 <= c <= n for n, c in zip(curve["returned"], curve["correct"]))
            # a looser threshold never returns fewer matches
            assert all(a <= b for a, b in zip(curve["returned"], curve["returned"][1:]))
        seg = res["curves"]["segment-guided"]
        n, c = seg["returned"][-1], seg["correct"][-1]
        assert n > 0 and c / n > 0.5  # sane: most guided matches are right even with the ratio test off
        assert 0 < res["reduction"] < 1
        assert res["candidates_per_query"]["segment-guided"] <= res["candidates_per_query"]["line-guided"]
    for stem in ("forward", "motorcycle"):
        assert (tmp_path / f"compare_pr_{stem}.png").stat().st_size > 1000
        assert (tmp_path / f"compare_segments_{stem}.png").stat().st_size > 1000
