"""The house rules of the source tree, checked on the files themselves (nothing is imported).

* The viewer depends on the tasks, never the reverse: no module under ``nsplat/tasks/`` and not
  ``nsplat/fitting.py`` imports ``nsplat.viewer`` (at module level or inside a function). Tasks build
  their views with :mod:`nsplat.view_model`; the viewer reaches them through the task registry.
* No Python module of the package (``nsplat/``, ``ops/``, ``models/``) is longer than 450 lines.
* Tests import the package, never a script of ``benchmarks/``.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAX_LINES = 450


def _imported_modules(path: Path) -> list[tuple[int, str]]:
    """``(line, dotted module)`` of every import in ``path``; ``from a import b`` yields ``a.b``."""
    out: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out += [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
    return out


def _viewer_imports(path: Path) -> list[tuple[int, str]]:
    return [(line, name) for line, name in _imported_modules(path)
            if name == "nsplat.viewer" or name.startswith("nsplat.viewer.")]


def test_tasks_and_fitter_do_not_import_the_viewer():
    files = sorted((ROOT / "nsplat" / "tasks").glob("*.py")) + [ROOT / "nsplat" / "fitting.py"]
    assert len(files) > 2
    bad = [f"{f.relative_to(ROOT)}:{line}: {name}" for f in files for line, name in _viewer_imports(f)]
    assert not bad, "the viewer depends on the tasks, never the reverse:\n" + "\n".join(bad)


def test_the_import_check_sees_module_and_function_level_imports(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("import nsplat.viewer.live\nfrom nsplat import viewer, render\n\n\n"
                     "def f():\n    from nsplat.viewer.runs import load_run\n")
    assert _viewer_imports(probe) == [(1, "nsplat.viewer.live"), (2, "nsplat.viewer"),
                                      (6, "nsplat.viewer.runs.load_run")]


@pytest.mark.parametrize("folder", ["nsplat", "ops", "models"])
def test_no_module_exceeds_the_line_limit(folder):
    files = sorted((ROOT / folder).rglob("*.py"))
    assert files
    long = {str(f.relative_to(ROOT)): n for f in files if (n := len(f.read_text().splitlines())) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines (split them into modules named for what they do): {long}"


def test_tests_do_not_load_benchmark_scripts():
    bad = []
    for f in sorted(p for p in (ROOT / "tests").glob("*.py") if p.name != Path(__file__).name):
        tree = ast.parse(f.read_text(), str(f))
        bad += [f"{f.name}:{line}: {name}" for line, name in _imported_modules(f) if name.split(".")[0] == "benchmarks"]
        bad += [f"{f.name}:{n.lineno}: path into benchmarks/" for n in ast.walk(tree)
                if isinstance(n, ast.Constant) and n.value == "benchmarks"]
    assert not bad, "tests import the package (move the code into nsplat/), not benchmark scripts: " + str(bad)
