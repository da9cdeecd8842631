"""The docs' figures that come from the code: each test fails when doc and code drift."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from teleop.bus.messages import (
    HEADER_FIELDS,
    PLANT_STATE,
    PROTOCOL_HISTORY,
    PROTOCOL_VERSION,
    SCHEMAS,
    Field,
    Kind,
    Schema,
    Stage,
    changelog_text,
    unversioned_change,
    version_text,
)
from teleop.bus.stamps import Inbound
from teleop.core import markdown
from teleop.core.config import Config, load_config
from teleop.sim.plant import Plant
from tests.conftest import ARM7_OVERRIDES

ROOT = Path(__file__).resolve().parents[2]
PROTOCOL_DOC = ROOT / "docs" / "protocol.md"
RUNNING_DOC = ROOT / "docs" / "running.md"
# Every text a reader takes a tool-speed figure from.
SPEED_TEXTS = sorted(
    [*ROOT.glob("docs/*.md"), ROOT / "README.md", *ROOT.glob("examples/*.py")]
    + [ROOT / "examples" / "README.md"]
)
# What each tool-speed setting is for (the table of docs/running.md).
SPEED_SETTINGS = {
    "plant.tool_speed_limit_m_s": "the plant's safety limit: it cuts any admitted command "
    "whose tool motion asks for more",
    "control.max_tool_speed_m_s": "path following's controller caps its own command here, "
    "below the plant's limit",
    "teleop.max_tool_speed_m_s": "teleoperation's controller caps the operator's rate "
    "command here, below the plant's limit",
    "plant.tool_speed_stop_m_s": "the plant's protective stop: a tool measured faster than "
    "this after a step (pushed, or not following its drives) is braked and held",
}
# Phrases that state the plant's limit or a controller's cap, with the figure (m/s).
LIMIT_PHRASES = (
    r"`plant\.tool_speed_limit_m_s`\s*[(,]\s*(\d+\.\d+) m/s",
    r"`plant\.tool_speed_limit_m_s`\s+is\s+(\d+\.\d+) m/s",
    r"plant's (\d+\.\d+) m/s(?: safety| tool)? limit",
    r"(\d+\.\d+) m/s(?: safety| tool)? limit",
    r"cuts? the tool (?:at|to) (\d+\.\d+) m/s",
)
CAP_PHRASES = (
    r"max_tool_speed_m_s`\s*\((\d+\.\d+) m/s",
    r"(\d+\.\d+) m/s caps?\b",
    r"capped at (\d+\.\d+) m/s",
)


def _embedded(path: Path, name: str) -> str:
    text = path.read_text()
    begin, end = f"<!-- {name}() begin -->", f"<!-- {name}() end -->"
    return text[text.index(begin) + len(begin) : text.index(end)]


def speed_limits(config: Config) -> str:
    """The tool-speed table of docs/running.md, from ``config``."""
    values = {
        "plant.tool_speed_limit_m_s": config.plant.tool_speed_limit_m_s,
        "control.max_tool_speed_m_s": config.control.max_tool_speed_m_s,
        "teleop.max_tool_speed_m_s": config.teleop.max_tool_speed_m_s,
        "plant.tool_speed_stop_m_s": config.plant.tool_speed_stop_m_s,
    }
    rows = [(f"`{k}`", f"{v:.2f} m/s", SPEED_SETTINGS[k]) for k, v in values.items()]
    return "\n".join(markdown.table(("setting", "default", "what"), rows, "lr"))


def speed_figures(text: str) -> dict[str, set[float]]:
    """The plant-limit and cap figures ``text`` states (by the phrases above)."""
    flat = " ".join(text.split())  # a phrase may span lines
    found: dict[str, set[float]] = {"limit": set(), "cap": set()}
    for kind, phrases in (("limit", LIMIT_PHRASES), ("cap", CAP_PHRASES)):
        for phrase in phrases:
            found[kind] |= {float(v) for v in re.findall(phrase, flat)}
    return found


def test_protocol_doc_states_the_protocol_version():
    embedded = _embedded(PROTOCOL_DOC, "version_text")
    assert embedded.strip() == version_text().strip(), (
        "docs/protocol.md is stale: paste `python -m teleop.bus.messages version` between "
        "the markers"
    )
    assert f"**{PROTOCOL_VERSION}**" in embedded


def test_the_records_are_the_version_they_say_and_the_changelog_lists_every_version():
    assert unversioned_change() is None
    assert [v.version for v in PROTOCOL_HISTORY] == list(range(1, PROTOCOL_VERSION + 1))
    embedded = _embedded(PROTOCOL_DOC, "changelog_text")
    assert embedded.strip() == changelog_text().strip(), (
        "docs/protocol.md's version table is out of date: replace it with "
        "python -m teleop.bus.messages changelog"
    )


def test_a_layout_change_without_a_new_version_is_caught():
    """A field added to PLANT_STATE, or a limit moved: each is a change a client must
    hear of, so each fails the check until a new version says it."""
    body = PLANT_STATE.fields[len(HEADER_FIELDS) :]
    assert unversioned_change({**SCHEMAS, Kind.PLANT_STATE: Schema(Kind.PLANT_STATE, body)}) is None
    grown = Schema(Kind.PLANT_STATE, [*body, Field("extra", "u1")])
    problem = unversioned_change({**SCHEMAS, Kind.PLANT_STATE: grown})
    assert problem is not None and "bump PROTOCOL_VERSION" in problem
    bounded = next(i for i, f in enumerate(body) if f.hi is not None)
    moved = [*body]
    moved[bounded] = dataclasses.replace(body[bounded], hi=body[bounded].hi + 1)
    assert unversioned_change({**SCHEMAS, Kind.PLANT_STATE: Schema(Kind.PLANT_STATE, moved)})


def test_protocol_doc_accounts_every_counter_of_the_command_stream():
    """Every counter of the plant's ``command_stream`` is named where the doc adds them up."""
    text = PROTOCOL_DOC.read_text()
    section = text[text.index("**Where every command goes**") :]
    section = section[: section.index("\n### ")]
    counters = {*Inbound(Stage.CONTROLLER_TX).counts(), "future_state"}
    for name in sorted(counters):
        assert f"`{name}`" in section or f"command_stream.{name}" in section, name


def joint_reach_table() -> str:
    """The table of docs/running.md "The limits a controller meets": each shipped arm's
    joint reach (Plant.joint_reach_m) and the uniform joint-speed budget it gives."""
    rows = []
    for name, overrides in (("6-DOF (default)", ()), ("7-DOF", ARM7_OVERRIDES)):
        config = load_config(None, overrides)
        reach = Plant(config).joint_reach_m()
        budget = config.plant.tool_speed_limit_m_s / reach.max()
        rows.append((name, ", ".join(f"{r:.3f}" for r in reach), f"{budget:.3f} rad/s"))
    header = ("arm", "reach per joint, base to wrist (m)", "sum of joint speeds at most")
    return "\n".join(markdown.table(header, rows, "llr"))


def test_running_doc_gives_each_arms_joint_reach():
    expected = joint_reach_table()
    assert _embedded(RUNNING_DOC, "joint_reach").strip() == expected, (
        f"docs/running.md is stale: put this table between the markers:\n{expected}"
    )


def test_the_joint_reach_bounds_the_tool_speed_in_any_configuration(any_arm_config):
    """|J q'| <= sum |q'_i| reach_i for random configurations and joint speeds: the rule
    of thumb holds wherever the arm is."""
    plant = Plant(any_arm_config)
    reach = plant.joint_reach_m()
    rng = np.random.default_rng(7)
    home = plant.data.qpos[plant.qpos_index].copy()
    for _ in range(300):
        plant.set_arm_configuration(home + rng.uniform(-3.0, 3.0, home.shape))
        qd = rng.normal(0.0, 1.0, home.shape)
        speed = float(np.linalg.norm(plant.tool_jacobian() @ qd))
        assert speed <= float(np.abs(qd) @ reach) + 1e-12


def test_running_doc_gives_the_configs_tool_speed_figures():
    config = load_config(None, [])
    expected = speed_limits(config)
    assert _embedded(RUNNING_DOC, "speed_limits").strip() == expected, (
        f"docs/running.md is stale: put this table between the markers:\n{expected}"
    )


@pytest.mark.parametrize("path", SPEED_TEXTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_tool_speed_figure_in_the_docs_is_the_configs(path):
    config = load_config(None, [])
    caps = {config.control.max_tool_speed_m_s, config.teleop.max_tool_speed_m_s}
    found = speed_figures(path.read_text())
    assert found["limit"] <= {config.plant.tool_speed_limit_m_s}, (
        f"{path.name} states a plant tool-speed limit of {sorted(found['limit'])} m/s; "
        f"plant.tool_speed_limit_m_s is {config.plant.tool_speed_limit_m_s}"
    )
    assert found["cap"] <= caps, (
        f"{path.name} states a controller cap of {sorted(found['cap'])} m/s; the config's "
        f"are {sorted(caps)}"
    )


def test_the_figure_check_can_fail():
    """The phrases catch a stale figure in each way the docs state one."""
    stale = (
        "`plant.tool_speed_limit_m_s` (0.25 m/s, above the controllers' 0.20 m/s caps); "
        "below the plant's 0.35 m/s safety\nlimit; the plant cuts the tool at 0.4 m/s; "
        "`control.max_tool_speed_m_s` (0.1 m/s; capped at 0.15 m/s; "
        "`plant.tool_speed_limit_m_s`,\n0.45 m/s"
    )
    assert speed_figures(stale) == {"limit": {0.25, 0.35, 0.4, 0.45}, "cap": {0.2, 0.1, 0.15}}
