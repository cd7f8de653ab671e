"""The README's Python example runs as written."""

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[2] / "README.md"


def _python_blocks():
    return re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


@pytest.mark.skipif(not README.exists(), reason="README.md not present")
def test_readme_example_runs(capsys):
    blocks = _python_blocks()
    assert blocks, "the README must hold a Python example"
    assert len(blocks[0].strip().splitlines()) <= 14
    namespace = {}
    exec(compile(blocks[0], str(README), "exec"), namespace)  # noqa: S102 - our own README
    out = capsys.readouterr().out.split()
    n_matches, n_on_segment = int(out[0]), int(out[1])
    assert n_matches > 100
    assert n_on_segment == n_matches  # guided matches all lie on their segment
