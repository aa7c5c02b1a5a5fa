"""The engine and the add-on stay layered: no import cycle between their modules (imports
inside functions and under ``TYPE_CHECKING`` count too), and no module imports one of a
layer above its own. Read from the source with ``ast``; nothing is imported."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# Low to high. A module may import its own layer and the layers below it. Subpackages
# (render/, data/, strategies/, ...) are one name each.
ENGINE_LAYERS: tuple[frozenset[str], ...] = tuple(map(frozenset, (
    # no engine imports of their own (but the compiled rasterizer)
    {"__init__", "_C", "allocator", "errors", "threads", "determinism", "adam", "lifeline"},
    # the pieces: scenes, rendering, the Gaussians, prompt boxes, losses and metrics, events
    {"data", "render", "gaussians", "formats", "prompts", "losses", "metrics", "residuals", "sky", "events",
     "distributed", "synthetic"},
    # the method and the run folder: strategies, views, the error field, proposals, the
    # prompt bookkeeping, compaction, batch rules, settings, evaluation, SfM
    {"strategies", "config", "errorfield", "views", "proposals", "propose", "compaction", "batch", "focus",
     "run_folder", "evaluation", "sfm"},
    # the training loop
    {"train"},
    # a training run as a job
    {"run"},
    # commands
    {"cli", "__main__", "bench"},
)))

ADDON_LAYERS: tuple[frozenset[str], ...] = tuple(map(frozenset, (
    # readers, coordinates, Gaussians as arrays, the trainer process, the dataset
    # generator, drawing points
    {"__init__", "coords", "colmap", "plyio", "splats", "trainer", "dataset", "display"},
    # scene objects: the imported dataset, prompt cubes, the Gaussians' attributes, a run's results
    {"importer", "prompts", "splat_attributes", "results"},
    # jobs beside training, and the properties
    {"preview", "reconstruct", "props"},
    {"proposals"},
    {"training"},
    # what the user touches
    {"operators", "ui", "overlay"},
)))


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def package_modules(root: Path) -> dict[str, Path]:
    return {module_name(p, root): p for p in sorted(root.rglob("*.py"))}


def imported_modules(name: str, path: Path, modules: set[str]) -> set[str]:
    """The package's modules that ``name`` imports anywhere in its source."""
    package = name.split(".")[0]
    is_package = path.name == "__init__.py"
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_package else name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            targets = [f"{target}.{a.name}" for a in node.names] + [target]
        for target in targets:
            while target and target not in modules and target != f"{package}._C":
                target = target.rpartition(".")[0]
            if target.startswith(package) and target != name:
                found.add(target)
    return found


def import_graph(root: Path) -> dict[str, set[str]]:
    modules = package_modules(root)
    names = set(modules)
    return {name: imported_modules(name, path, names) for name, path in modules.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def layer_of(module: str, layers: tuple[frozenset[str], ...]) -> int:
    parts = module.split(".")
    top = parts[1] if len(parts) > 1 else "__init__"
    for i, layer in enumerate(layers):
        if top in layer:
            return i
    raise AssertionError(f"{module}: in no layer of tests/test_architecture.py (add it to the layer it belongs to)")


def upward_imports(graph: dict[str, set[str]], layers: tuple[frozenset[str], ...]) -> list[str]:
    return [
        f"{a} imports {b}"
        for a in sorted(graph)
        for b in sorted(graph[a])
        if layer_of(b, layers) > layer_of(a, layers)
    ]


@pytest.mark.parametrize("package, layers", [("promptgs_engine", ENGINE_LAYERS), ("promptgs_blender", ADDON_LAYERS)])
def test_no_import_cycle(package: str, layers) -> None:
    assert cycles(import_graph(REPO / package)) == []


@pytest.mark.parametrize("package, layers", [("promptgs_engine", ENGINE_LAYERS), ("promptgs_blender", ADDON_LAYERS)])
def test_no_upward_import(package: str, layers) -> None:
    assert upward_imports(import_graph(REPO / package), layers) == []


def test_the_checks_find_a_cycle_and_an_upward_import(tmp_path: Path) -> None:
    # A function-level import closing a circle, as the engine once had
    # (train -> batch -> train), and a low module importing a high one.
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "train.py").write_text("from .batch import step\n")
    (pkg / "batch.py").write_text("def step():\n    from .train import Trainer\n")
    (pkg / "errors.py").write_text("from . import train\n")
    graph = import_graph(pkg)
    assert cycles(graph) == [["pkg.batch", "pkg.train"]]
    layers = (frozenset({"__init__", "errors"}), frozenset({"batch", "train"}))
    assert upward_imports(graph, layers) == ["pkg.errors imports pkg.train"]
    (pkg / "batch.py").write_text("def step():\n    pass\n")
    assert cycles(import_graph(pkg)) == []
