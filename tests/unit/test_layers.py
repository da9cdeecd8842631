"""Imports only go downward through the layers, and no module graph has a cycle."""

from __future__ import annotations

from pathlib import Path

from teleop.layers import LAYERS, cycles, import_graph, layer_of, upward_imports


def test_the_package_has_no_upward_import_and_no_cycle():
    graph = import_graph()
    assert "teleop.core.config" in graph and "services.plant" in graph
    assert upward_imports(graph) == []
    assert cycles(graph) == []


def test_every_teleop_module_sits_in_a_layer():
    unlayered = [m for m in import_graph() if layer_of(m) is None]
    assert unlayered == ["teleop", "teleop.layers"]


def test_the_check_finds_a_cycle_and_an_upward_import(tmp_path: Path):
    # The same functions on a made-up tree: they must be able to fail.
    (tmp_path / "teleop" / "core").mkdir(parents=True)
    (tmp_path / "teleop" / "sim").mkdir()
    for package in ("teleop", "teleop/core", "teleop/sim"):
        (tmp_path / package / "__init__.py").write_text("")
    (tmp_path / "teleop" / "core" / "a.py").write_text("from teleop.sim.b import f\n")
    (tmp_path / "teleop" / "sim" / "b.py").write_text("def f():\n    import teleop.core.a\n")
    graph = import_graph(tmp_path)
    assert graph["teleop.core.a"] == {"teleop.sim.b"}
    assert upward_imports(graph) == ["teleop.core.a -> teleop.sim.b"]
    assert cycles(graph) == [["teleop.core.a", "teleop.sim.b", "teleop.core.a"]]
    assert LAYERS.index("teleop.core") < LAYERS.index("teleop.sim")


def test_no_service_imports_another():
    """services/ are thin bus adapters side by side: what two share lives in teleop/."""
    graph = import_graph()
    crossing = sorted(
        f"{module} -> {imported}"
        for module, imports in graph.items()
        if module.startswith("services.")
        for imported in imports
        if imported.startswith("services.") and imported != module
    )
    assert crossing == []
