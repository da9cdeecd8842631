"""The package's layers, and the check that imports only go downward.

Each layer may import the layers below it and its own, never one above; no module
graph cycle anywhere. ``python -m teleop.layers`` prints the module graph's
violations (none: exit 0); ``tests/unit/test_layers.py`` runs the same check.
"""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterator
from pathlib import Path

# Bottom to top. ``shm`` is the shared-memory layer the bus sits on; ``services`` are the
# processes' bus adapters, above everything, and nothing imports them.
LAYERS = (
    "shm",
    "teleop.core",
    "teleop.bus",
    "teleop.sim",
    "teleop.control",
    "teleop.devices",
    "teleop.viz",
    "teleop.run",
    "teleop.bench",
    "teleop.cli",
    "services",
)
PROJECT_PACKAGES = ("shm", "teleop", "services")
REPO_ROOT = Path(__file__).resolve().parents[1]


def module_name(path: Path, root: Path = REPO_ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def layer_of(module: str) -> int | None:
    """Index in LAYERS of the layer ``module`` belongs to (None: not layered)."""
    best = None
    for index, layer in enumerate(LAYERS):
        if module == layer or module.startswith(layer + "."):
            best = index
    return best


def project_imports(path: Path, module: str, root: Path = REPO_ROOT) -> Iterator[str]:
    """Every project module ``path`` imports, at any depth (function bodies included)."""
    tree = ast.parse(path.read_text(), str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            # ``from pkg import mod`` names a module when pkg/mod.py exists
            names = [base]
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                if (root / (sub.replace(".", "/") + ".py")).exists() or (
                    root / sub.replace(".", "/") / "__init__.py"
                ).exists():
                    names.append(sub)
        else:
            continue
        for name in names:
            if name.split(".")[0] in PROJECT_PACKAGES:
                yield name


def import_graph(root: Path = REPO_ROOT) -> dict[str, set[str]]:
    """module -> the project modules it imports (packages resolved to their modules)."""
    graph: dict[str, set[str]] = {}
    for package in PROJECT_PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            module = module_name(path, root)
            graph[module] = set(project_imports(path, module, root)) - {module}
    known = set(graph)
    for module, targets in graph.items():
        graph[module] = {t for t in targets if t in known and not _is_parent(t, module)}
    return graph


def _is_parent(package: str, module: str) -> bool:
    return module.startswith(package + ".")


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    """'a -> b' for every import of a module in a higher layer (or of an unlayered one)."""
    found = []
    for module, targets in sorted(graph.items()):
        here = layer_of(module)
        for target in sorted(targets):
            there = layer_of(target)
            if here is None or there is None or there > here:
                found.append(f"{module} -> {target}")
    return found


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles of ``graph`` (each a list of modules), by depth-first search."""
    found: list[list[str]] = []
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(module: str) -> None:
        state[module] = 1
        path.append(module)
        for target in sorted(graph.get(module, ())):
            if state.get(target) == 1:
                found.append([*path[path.index(target) :], target])
            elif target not in state:
                visit(target)
        path.pop()
        state[module] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module)
    return found


def main() -> int:
    graph = import_graph()
    problems = [f"upward import: {line}" for line in upward_imports(graph)]
    problems += ["cycle: " + " -> ".join(cycle) for cycle in cycles(graph)]
    for line in problems:
        print(line)
    edges = sum(len(t) for t in graph.values())
    print(f"{len(graph)} modules, {edges} imports, {len(problems)} problems")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
