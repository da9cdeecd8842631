"""Imports only go downward through the layers, and no module graph has a cycle."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

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


# Packages a service's process must not load: each costs tens to hundreds of ms of every
# start, and a restarted loop service spends its start-up with the robot braked.
# cryptography makes the run's certificates (the launcher's job); filterpy's kalman
# package brings scipy.stats (about 0.4 s).
NOT_IMPORTED_BY = {
    "plant": ("cryptography", "filterpy", "scipy", "pinocchio", "rerun"),
    "controller": ("cryptography", "filterpy", "rerun"),
    "haptic": ("cryptography", "filterpy", "scipy", "mujoco", "pinocchio", "rerun"),
    "hmd": ("cryptography", "mujoco", "pinocchio", "rerun"),
    "operator": ("cryptography", "filterpy", "scipy", "pinocchio", "rerun"),
    "eyeview": ("cryptography", "filterpy", "scipy", "pinocchio", "rerun"),
    "recorder": ("cryptography", "filterpy", "scipy", "pinocchio"),
}


@pytest.mark.parametrize("service", sorted(NOT_IMPORTED_BY))
def test_a_service_imports_only_what_it_uses(service: str):
    code = f"import sys, services.{service}; print(' '.join(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    loaded = {name.split(".")[0] for name in out.stdout.split()}
    assert "zenoh" in loaded  # the probe itself works
    assert sorted(loaded & set(NOT_IMPORTED_BY[service])) == []
