"""The house rules of the source tree, checked on the files themselves (nothing is imported).

* The package's modules (``nsplat/``, ``ops/`` and ``models/``, installed as ``nsplat.ops``/``nsplat.models``)
  import each other without a cycle, and only at module level (no import inside a function to dodge one).
* The package is layered (:data:`LAYERS`, what nsplat/__init__.py's docstring maps): every module belongs to one
  room, and a room imports only from rooms of lower layers; the top of ``nsplat/`` holds only the shared
  vocabulary, the scene and the command line.
* The viewer depends on the tasks, never the reverse: no module under ``nsplat/tasks/`` or
  ``nsplat/fitting/`` imports ``nsplat.viewer`` (at module level or inside a function). Tasks build
  their views with :mod:`nsplat.render.view_model`; the viewer reaches them through the task registry.
* No Python module of the package (``nsplat/``, ``ops/``, ``models/``) is longer than 450 lines.
* Tests import the package and the shared modules of the ``benchmarks`` and ``tools`` packages
  (``tools.allocation``, ``benchmarks.targets``), never a script (a module that runs as
  ``python -m benchmarks.<name>`` or ``python -m tools.<name>``).
* The tools may use the benchmarks' shared modules; the benchmarks never import the tools (one direction only).
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAX_LINES = 450
#: Source folder → the package it installs as (pyproject.toml ``package-dir``).
PACKAGES = {"nsplat": "nsplat", "ops": "nsplat.ops", "models": "nsplat.models"}
#: The repository's folders of scripts (not installed): the benchmarks and the tools.
SCRIPT_PACKAGES = ("benchmarks", "tools")
#: The package's rooms, lowest layer first: a module of a room imports only rooms of strictly lower layers (and its own
#: room). A room is a package or a module; a module belongs to the longest room that prefixes its name.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("nsplat.ops", "nsplat.models"),
    ("nsplat.errors", "nsplat.config", "nsplat.cameras", "nsplat.points"),
    ("nsplat.data",),
    ("nsplat.scene",),
    ("nsplat.render", "nsplat.evaluation", "nsplat.run"),
    ("nsplat.gaussians", "nsplat.fitting"),
    ("nsplat.tasks",),
    ("nsplat.viewer",),
    ("nsplat.cli",),
)


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


def _package_modules(root: Path = ROOT) -> dict[str, Path]:
    """Dotted name → file of every module of the installed package."""
    out = {}
    for folder, package in PACKAGES.items():
        for f in sorted((root / folder).rglob("*.py")):
            parts = [p for p in f.relative_to(root / folder).with_suffix("").parts if p != "__init__"]
            out[".".join([package, *parts])] = f
    return out


def _module_level_imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package modules that module ``name`` (file ``path``) imports in its top-level statements (also
    under ``if``/``try``): ``from a import b`` counts as ``a.b`` when that is a module, else as ``a``;
    relative imports are resolved against the module's package."""
    out = set()
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    todo = list(ast.parse(path.read_text(), str(path)).body)
    while todo:
        node = todo.pop()
        if isinstance(node, (ast.If, ast.Try)):
            todo += node.body + node.orelse + getattr(node, "finalbody", []) + \
                [n for h in getattr(node, "handlers", []) for n in h.body]
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name in modules}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([node.module] if node.module else []))
            if base not in modules:
                continue
            subs = {f"{base}.{a.name}" for a in node.names} & set(modules)
            out |= subs | ({base} if len(subs) < len(node.names) else set())
    return out


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module, and modules importing themselves."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1 or v in graph[v]:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _graph(root: Path = ROOT) -> dict[str, set[str]]:
    modules = _package_modules(root)
    return {name: _module_level_imports(name, path, modules) for name, path in modules.items()}


def test_the_package_has_no_import_cycle():
    graph = _graph()
    assert len(graph) > 50 and sum(map(len, graph.values())) > 100  # the scan sees the package
    cycles = _cycles(graph)
    assert not cycles, "import cycles among the package's modules:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_package_modules_are_imported_at_module_level_only():
    modules = _package_modules()
    bad = []
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        top = {id(n) for n in _walk_top(tree.body)}
        bad += [f"{path.relative_to(ROOT)}:{n.lineno}" for n in ast.walk(tree)
                if isinstance(n, (ast.Import, ast.ImportFrom)) and id(n) not in top
                and any(m.startswith("nsplat") for m in _names_of(n))]
    assert not bad, "imports of the package inside functions or classes (a cycle dodged?):\n" + "\n".join(bad)


def _walk_top(body: list[ast.stmt]) -> list[ast.stmt]:
    """Top-level statements, including those under module-level ``if``/``try``."""
    out = []
    for node in body:
        out.append(node)
        if isinstance(node, (ast.If, ast.Try)):
            out += _walk_top(node.body + node.orelse + getattr(node, "finalbody", []) +
                             [n for h in getattr(node, "handlers", []) for n in h.body])
    return out


def _names_of(node: ast.Import | ast.ImportFrom) -> list[str]:
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    return [node.module or ""] if node.level == 0 else ["nsplat (relative)"]


def test_the_cycle_check_finds_a_planted_cycle(tmp_path):
    for folder in PACKAGES:
        (tmp_path / folder).mkdir()
    (tmp_path / "nsplat" / "__init__.py").write_text("")
    (tmp_path / "nsplat" / "a.py").write_text("from nsplat.b import f\n")
    (tmp_path / "nsplat" / "b.py").write_text("import torch\nif True:\n    from nsplat import c\n")
    (tmp_path / "nsplat" / "c.py").write_text("from nsplat.a import g\n")
    (tmp_path / "ops" / "__init__.py").write_text("from .d import h\n")
    (tmp_path / "ops" / "d.py").write_text("from . import e\n")
    (tmp_path / "ops" / "e.py").write_text("import nsplat.ops.d\n")
    assert _cycles(_graph(tmp_path)) == [["nsplat.a", "nsplat.b", "nsplat.c"], ["nsplat.ops.d", "nsplat.ops.e"]]


def test_tasks_and_fitter_do_not_import_the_viewer():
    files = sorted((ROOT / "nsplat" / "tasks").rglob("*.py")) + sorted((ROOT / "nsplat" / "fitting").glob("*.py"))
    assert len(files) > 10
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


def _is_script(path: Path) -> bool:
    """Whether a module runs as a program (has an ``if __name__ == "__main__":`` block)."""
    return any(isinstance(n, ast.If) and "__main__" in ast.unparse(n.test) for n in ast.parse(path.read_text()).body)


def test_tests_do_not_load_benchmark_scripts():
    bad = []
    for f in sorted(p for p in (ROOT / "tests").glob("*.py") if p.name != Path(__file__).name):
        tree = ast.parse(f.read_text(), str(f))
        for line, name in _imported_modules(f):
            parts = name.split(".")
            if parts[0] not in SCRIPT_PACKAGES:
                continue
            target = next((ROOT.joinpath(*parts[:k]).with_suffix(".py") for k in range(len(parts), 1, -1)
                           if ROOT.joinpath(*parts[:k]).with_suffix(".py").is_file()), None)
            if target is None or _is_script(target):
                bad.append(f"{f.name}:{line}: {name}")
        bad += [f"{f.name}:{n.lineno}: path into {n.value}/" for n in ast.walk(tree)
                if isinstance(n, ast.Constant) and n.value in SCRIPT_PACKAGES]
    assert not bad, "tests import the package or the shared modules of benchmarks/ and tools/, not scripts: " + str(bad)


def _room(module: str, layers: tuple[tuple[str, ...], ...] = LAYERS) -> tuple[int, str] | None:
    """``(layer, room)`` of a dotted module name: the longest room that is the module or a package above it."""
    found = [(len(room), k, room) for k, rooms in enumerate(layers) for room in rooms
             if module == room or module.startswith(room + ".")]
    return max(found)[1:] if found else None


def _layer_violations(graph: dict[str, set[str]], layers: tuple[tuple[str, ...], ...] = LAYERS) -> list[str]:
    """``a -> b`` for every import of a module ``b`` that is not in ``a``'s room or a lower layer's."""
    bad = []
    for a, imported in sorted(graph.items()):
        if _room(a, layers) is None:  # the root package (nsplat/__init__.py) or a homeless module (tested apart)
            continue
        la, ra = _room(a, layers)
        for b in sorted(imported):
            lb, rb = _room(b, layers)
            if rb != ra and lb >= la:
                bad.append(f"{a} ({ra}, layer {la}) -> {b} ({rb}, layer {lb})")
    return bad


def test_every_module_belongs_to_a_room():
    homeless = [m for m in _package_modules() if m != "nsplat" and _room(m) is None]
    assert not homeless, f"modules in no room of LAYERS (put them in a sub-package or add the room): {homeless}"


def test_rooms_import_only_lower_layers():
    bad = _layer_violations(_graph())
    assert not bad, "imports against the layering (a room imports only rooms below it):\n" + "\n".join(bad)


def test_the_top_of_the_package_holds_only_the_vocabulary_the_scene_and_the_command_line():
    top = {f.stem for f in (ROOT / "nsplat").glob("*.py")} - {"__init__"}
    rooms = {room.rpartition(".")[2] for layer in LAYERS for room in layer if room.count(".") == 1}
    packages = {d.name for d in (ROOT / "nsplat").iterdir() if (d / "__init__.py").is_file()}
    assert top == rooms - packages - {"ops", "models"}, f"top-level modules of nsplat/ outside LAYERS: {top}"
    assert top == {"errors", "config", "cameras", "points", "scene", "cli"}


def test_the_layer_check_finds_a_planted_upward_import(tmp_path):
    for folder in PACKAGES:
        (tmp_path / folder).mkdir()
    for pkg in ("data", "render", "tasks"):
        (tmp_path / "nsplat" / pkg).mkdir()
        (tmp_path / "nsplat" / pkg / "__init__.py").write_text("")
    (tmp_path / "nsplat" / "__init__.py").write_text("")
    (tmp_path / "nsplat" / "data" / "views.py").write_text("from nsplat.render.video import f\n")
    (tmp_path / "nsplat" / "render" / "video.py").write_text("from nsplat.data.views import g\n")
    (tmp_path / "nsplat" / "tasks" / "demo.py").write_text("from nsplat.render import video\n")
    (tmp_path / "ops" / "__init__.py").write_text("from nsplat.tasks import demo\n")
    layers = (("nsplat.ops",), ("nsplat.data",), ("nsplat.render",), ("nsplat.tasks",))
    assert _layer_violations(_graph(tmp_path), layers) == [
        "nsplat.data.views (nsplat.data, layer 1) -> nsplat.render.video (nsplat.render, layer 2)",
        "nsplat.ops (nsplat.ops, layer 0) -> nsplat.tasks.demo (nsplat.tasks, layer 3)"]
    assert _room("nsplat.render.video", layers) == (2, "nsplat.render") and _room("nsplat.x", layers) is None


def test_benchmarks_do_not_import_tools():
    files = sorted((ROOT / "benchmarks").glob("*.py"))
    assert len(files) > 10
    bad = [f"{f.name}:{line}: {name}" for f in files for line, name in _imported_modules(f)
           if name.split(".")[0] == "tools"]
    assert not bad, "tools/ may import benchmarks/, never the reverse: " + str(bad)


def test_the_fitter_reads_as_the_algorithm():
    """:func:`nsplat.fitting.fit` stays short enough to read as the algorithm; its parts live in named helpers."""
    tree = ast.parse((ROOT / "nsplat" / "fitting" / "fitter.py").read_text())
    fit = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "fit")
    assert fit.end_lineno - fit.lineno + 1 <= 80
