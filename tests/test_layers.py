"""The folder tree is the architecture: every import points down the layer order.

Order, lowest first: the shared utilities at the top level (``checks``, ``config``, ``inputs``,
``io``, ``llvm``, ``machine``, ``outputs``, ``processes``, ``progress``, ``version``), then
``geometry``, ``render``, ``data``, ``model``, then ``training`` and ``inference`` side by side
(neither imports the other: a trained network needs nothing of the trainer, and the trainer
nothing of test time), then ``evaluation``, ``apps``, ``bench``, ``cli``. A module may import
its own layer and the layers below it, never one above or beside. Imports inside functions
count too (the project defers heavy imports into functions).
"""

from __future__ import annotations

import ast
import shutil
from pathlib import Path

import sq_mitsuba

PACKAGE = Path(sq_mitsuba.__file__).resolve().parent
UTILITIES = ("checks", "config", "inputs", "io", "llvm", "machine", "outputs", "processes",
             "progress", "version")
# One tuple per rank, lowest first; the layers of one rank may not import each other.
RANKS = (("utilities",), ("geometry",), ("render",), ("data",), ("model",),
         ("training", "inference"), ("evaluation",), ("apps",), ("bench",), ("cli",))
LAYERS = tuple(name for rank in RANKS for name in rank)
#: Most modules a package folder may hold (``__init__`` included): a longer list is a sign
#: that the folder does several jobs.
MAX_MODULES = 15
# The package root re-exports the inference API and runs the CLI: it sits on top.
TOP = ("__init__", "__main__")


def layer_of(module: str) -> str | None:
    """The layer (a name of :data:`LAYERS`, or "top") of a dotted ``sq_mitsuba...`` module
    name (None: not ours)."""
    parts = module.split(".")
    if parts[0] != "sq_mitsuba":
        return None
    if len(parts) == 1 or parts[1] in TOP:
        return "top"
    if parts[1] in UTILITIES or parts[1] == "scenes":  # scenes: package data, imports nothing
        return "utilities"
    if parts[1] not in LAYERS:
        raise AssertionError(f"{module}: not in a layer folder; layers are {LAYERS}")
    return parts[1]


def rank_of(layer: str) -> int:
    """Position of ``layer`` in :data:`RANKS` (the package root above them all)."""
    if layer == "top":
        return len(RANKS)
    return next(k for k, names in enumerate(RANKS) if layer in names)


def module_name(path: Path, root: Path) -> str:
    relative = path.relative_to(root.parent).with_suffix("")
    parts = list(relative.parts)
    if parts[-1] == "__init__" and len(parts) > 1:
        parts = parts[:-1]
    return ".".join(parts)


def imported_modules(tree: ast.AST, module: str, is_package: bool) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in ``tree``, relative ones resolved."""
    package = module if is_package else module.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            found.append((node.lineno, name))
            # ``from sq_mitsuba import bench`` imports the submodule sq_mitsuba.bench.
            found += [(node.lineno, f"{name}.{alias.name}") for alias in node.names
                      if name == "sq_mitsuba"]
    return found


def layer_violations(root: Path) -> list[str]:
    """One line per import in the package at ``root`` that points to a higher layer."""
    problems = []
    for path in sorted(root.rglob("*.py")):
        module = module_name(path, root)
        own = layer_of(module)
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for line, target in imported_modules(tree, module, path.name == "__init__.py"):
            layer = layer_of(target)
            if layer is None or own is None or layer == own:
                continue
            if rank_of(layer) >= rank_of(own):
                problems.append(f"{path.relative_to(root.parent)}:{line}: {module} "
                                f"({_name(own)}) imports {target} ({_name(layer)})")
    return problems


def _name(layer: str) -> str:
    return "package root" if layer == "top" else layer


def test_every_import_points_down():
    assert layer_violations(PACKAGE) == []


def test_every_module_sits_in_a_layer_folder():
    for path in PACKAGE.rglob("*.py"):
        layer_of(module_name(path, PACKAGE))  # raises for a module outside the layers


def test_a_planted_upward_import_is_caught(tmp_path):
    copy = tmp_path / "sq_mitsuba"
    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__"))
    planted = copy / "geometry" / "planted.py"
    planted.write_text("def late():\n    from sq_mitsuba.render.backend import mitsuba\n"
                       "    return mitsuba\n")
    relative = copy / "render" / "planted_relative.py"
    relative.write_text("from ..inference import fit\n")
    beside = copy / "training" / "planted_beside.py"
    beside.write_text("from sq_mitsuba.inference.search import search_poses\n")
    problems = layer_violations(copy)
    assert len(problems) == 3, problems
    assert "geometry/planted.py:2" in problems[0] and "(render)" in problems[0]
    assert "render/planted_relative.py:1" in problems[1] and "(inference)" in problems[1]
    assert "training/planted_beside.py:1" in problems[2] and "(inference)" in problems[2]


def test_no_package_folder_holds_more_than_fifteen_modules():
    crowded = {str(folder.relative_to(PACKAGE.parent)): count
               for folder in [PACKAGE, *(p for p in PACKAGE.rglob("*") if p.is_dir())]
               if (count := len(list(folder.glob("*.py")))) > MAX_MODULES}
    assert crowded == {}, (f"more than {MAX_MODULES} modules in a folder: {crowded}; group "
                           "some by role in a subpackage (as training/run/), docs/README.md")


def test_shared_utilities_import_nothing_of_the_project():
    for name in UTILITIES:
        path = PACKAGE / f"{name}.py"
        tree = ast.parse(path.read_text(encoding="utf-8"))
        ours = [t for _, t in imported_modules(tree, f"sq_mitsuba.{name}", False)
                if t.startswith("sq_mitsuba")]
        assert ours == [], f"{path.name} imports {ours}"


def test_no_module_points_to_documents_outside_the_repository():
    # The repository stands on its own: conventions live in docstrings and the README.
    outside = ("DESIGN", "../shared", "seed/000_")
    for path in PACKAGE.rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        for word in outside:
            assert word not in text, f"{path.relative_to(PACKAGE.parent)} mentions {word!r}"


# ------------------------------------------------------------------------ import cycles


def import_graph(root: Path) -> dict[str, set[str]]:
    """Module -> the package's modules it imports (anywhere in it, functions included).

    ``from package import name`` counts as importing ``package.name`` when that is a module,
    else the package itself; a module's import of its own enclosing package is left out
    (Python runs a package's ``__init__`` before any of its modules anyway)."""
    modules = {module_name(path, root): path for path in sorted(root.rglob("*.py"))}
    graph: dict[str, set[str]] = {}
    for module, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        targets: set[str] = set()
        for node in ast.walk(tree):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = imported_modules(ast.Module([node], []), module,
                                        path.name == "__init__.py")[0][1]
                names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base
                         for alias in node.names]
            for name in names:
                while name and name not in modules:  # a.b.c imports a.b too; keep ours
                    name = name.rpartition(".")[0]
                if name and name != module and not module.startswith(name + "."):
                    targets.add(name)
        graph[module] = targets
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle per strongly connected group of mutually importing modules (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph.get(node, ())):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            group = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                group.append(member)
                if member == node:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return groups


def test_no_modules_import_each_other_in_a_loop():
    assert import_cycles(import_graph(PACKAGE)) == []


def test_a_planted_import_cycle_is_caught(tmp_path):
    copy = tmp_path / "sq_mitsuba"
    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__"))
    (copy / "geometry" / "planted_a.py").write_text("from sq_mitsuba.geometry import planted_b\n")
    (copy / "geometry" / "planted_b.py").write_text(
        "def late():\n    from sq_mitsuba.geometry.planted_c import x\n    return x\n")
    (copy / "geometry" / "planted_c.py").write_text("from .planted_a import y\nx = 1\n")
    assert import_cycles(import_graph(copy)) == [["sq_mitsuba.geometry.planted_a",
                                                  "sq_mitsuba.geometry.planted_b",
                                                  "sq_mitsuba.geometry.planted_c"]]


# ------------------------------------------------------------------------ private names


LEARNING = ("sq_mitsuba.model", "sq_mitsuba.training", "sq_mitsuba.inference")


def private_learning_imports(paths: list[Path]) -> list[str]:
    """One line per import of a ``_private`` name of the model, training or inference layers
    in ``paths``."""
    problems = []
    for path in paths:
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith(LEARNING):
                problems += [f"{path}:{node.lineno}: {node.module}.{alias.name}"
                             for alias in node.names if alias.name.startswith("_")]
            elif isinstance(node, ast.Import):
                problems += [f"{path}:{node.lineno}: {alias.name}" for alias in node.names
                             if alias.name.startswith(LEARNING) and any(
                                 part.startswith("_") and part != "__init__"
                                 for part in alias.name.split("."))]
    return problems


def test_nothing_outside_learning_imports_its_private_names():
    """The training step, the trainer and the losses are public: the benchmark, the CLI,
    evaluation and the experiments under eval/ use them by their public names."""
    own = {"model", "training", "inference"}
    outside = [p for p in sorted(PACKAGE.rglob("*.py")) if not own & set(p.relative_to(
        PACKAGE).parts)]
    experiments = sorted((PACKAGE.parent / "eval").rglob("*.py"))
    assert experiments, "eval/ scripts not found"
    assert private_learning_imports(outside + experiments) == []


def test_a_planted_private_import_is_caught(tmp_path):
    planted = tmp_path / "bench.py"
    planted.write_text("def f():\n    from sq_mitsuba.training.train import _loop, train\n")
    assert private_learning_imports([planted]) == [
        f"{planted}:2: sq_mitsuba.training.train._loop"]


def test_no_file_in_the_learning_layers_is_over_500_lines():
    long = {str(p.relative_to(PACKAGE)): n for layer in ("model", "training", "inference")
            for p in (PACKAGE / layer).rglob("*.py")
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > 500}
    assert long == {}, (f"over 500 lines: {long}; split the file by role (one file, one "
                        "role), docs/README.md")
