"""Every name a benchmark script takes from a helper module of ``benchmarks/`` exists there.

The benchmarks run for minutes and are not part of the test suite, so a helper renamed or removed in
one place (``_noisy_poses.rotation_angle``, once) broke a script only when it was next run. This reads
each script's syntax tree: for ``import _helper as alias``, every ``alias.name`` it uses; for
``from _helper import name``, every name; and checks them against the imported helper.
"""

import ast
import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"
SCRIPTS = sorted(BENCH.glob("*.py")) if BENCH.exists() else []
pytestmark = pytest.mark.skipif(not SCRIPTS, reason="benchmarks/ not present (installed from a wheel)")


def _local(module: str | None) -> bool:
    return module is not None and (BENCH / f"{module}.py").exists()


def used_names(source: str) -> dict:
    """``{helper module: {names}}`` that ``source`` takes from the helper modules of ``benchmarks/``."""
    tree = ast.parse(source)
    aliases, used = {}, {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if _local(a.name):
                    aliases[a.asname or a.name] = a.name
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and _local(node.module):
            used.setdefault(node.module, set()).update(a.name for a in node.names if a.name != "*")
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases:
            used.setdefault(aliases[node.value.id], set()).add(node.attr)
    return used


def _helper(name: str):
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location(f"benchmarks_names_{name}", BENCH / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = mod  # (its dataclasses look their module up there)
        spec.loader.exec_module(mod)
        return mod
    finally:
        sys.path.remove(str(BENCH))


def test_the_reader_sees_both_import_forms():
    """(hand-made) An attribute of an aliased helper and a name imported from one are both found; names of
    other modules are not."""
    src = ("import numpy as np\nimport _common as c\nfrom _gil import wrap, missing\n"
           "x = c.machine_metadata()\ny = np.zeros(1)\nz = c.nothing_here\n")
    assert used_names(src) == {"_common": {"machine_metadata", "nothing_here"}, "_gil": {"wrap", "missing"}}


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_every_helper_name_a_script_uses_exists(script):
    missing = []
    for module, names in used_names(script.read_text()).items():
        helper = _helper(module)
        missing += [f"{module}.{n}" for n in sorted(names) if not hasattr(helper, n)]
    assert not missing, f"{script.name} uses names its helpers do not have: {missing}"
