"""Two robots on one bus, end to end (``teleop run grasp --robots 2``): two plants and
two controllers under supervisord, each under its own robot id, one operator station
(haptic device, HMD, scripted operator, recorder) driving them in turn.

One lockstep run (deterministic): both tasks succeed; the handle drives one robot at a
time (each robot's handle is recorded centred while the other is driven); each robot's
section of the summary is judged again the same way; one recording holds both robots,
side by side in its 3D view, and ``--report`` writes a report per robot with its own
verdict. That a robot's processes are kept to its own keys is
tests/integration/test_access.py's.
"""

from __future__ import annotations

import numpy as np
import pytest

from teleop.core.config import load_config
from teleop.core.criteria import judge_summary
from teleop.core.rundir import RECORDING_FILE, REPORT_SUMMARY_FILE, report_dir
from teleop.viz import entities as ent
from teleop.viz.blueprint import view_specs
from teleop.viz.rrd import Recording
from tests.e2e.test_grasp import assert_physical, grasp

ROBOTS = ("arm0", "arm1")


@pytest.fixture(scope="module")
def two_robots(tmp_path_factory) -> dict:
    tmp_path = tmp_path_factory.mktemp("robots")
    summary = grasp(
        tmp_path, "two", "--mode", "lockstep", "--seed", "0", "--robots", "2", "--report"
    )
    return {**summary, "report_dir": report_dir(tmp_path / "two" / RECORDING_FILE)}


def test_both_robots_tasks_succeed_one_after_the_other(two_robots):
    summary = two_robots
    assert summary["success"] and summary["problems"] == []
    assert tuple(summary["robots"]) == ROBOTS
    services = summary["services"]
    assert {f"{s}-{r}" for s in ("plant", "controller") for r in ROBOTS} <= set(services)
    assert not {"plant", "controller"} & set(services)
    for robot_id, section in summary["robots"].items():
        assert section["success"] and section["object_in_box"], robot_id
        assert [p["name"] for p in section["phases"]][-1] == "retreat", robot_id
        assert judge_summary(section).summary() == {
            key: section[key] for key in ("success", "criteria", "problems", "reasons")
        }  # the one verdict, given again the same way
        assert_physical({**summary, **section})
        assert set(section["cpu_s_per_sim_s"]) == {"plant", "controller"}
    first, second = (summary["robots"][r]["phases"] for r in ROBOTS)
    # arm1's task starts where arm0's ended: one hand, one task at a time
    switches = services["haptic"]["robot_switches"]
    assert [s["robot"] for s in switches] == [1]
    switch_s = switches[0]["tick"] * load_config().tick_s
    assert first[-1]["sim_time_s"] < switch_s <= second[0]["sim_time_s"] + 0.1
    assert summary["dropped_messages"] == 0 and summary["unlinked_peers"] == {}


def test_one_recording_shows_both_robots_each_handle_centred_while_the_other_is_driven(
    two_robots,
):
    summary = two_robots
    switch_ns = round(
        summary["services"]["haptic"]["robot_switches"][0]["tick"]
        * load_config().tick_s * 1e9
    )  # fmt: skip
    assert all(summary["robots"][r]["rrd"] == summary["rrd"] for r in ROBOTS)
    rec = Recording(summary["rrd"])
    assert rec.robots == list(ROBOTS)
    config = load_config(None, ['run.scenario="grasp"', "run.robots=2"])
    for spec in view_specs(config):  # both worlds in the 3D view, every plot fed
        for entity in spec.entities:
            assert entity in rec.batches, entity
        for root in spec.subtrees:
            if not root.endswith(ent.ENTITY_EYE_VIEW):  # rendered in realtime runs only
                assert any(e.startswith(root + "/") for e in rec.batches), root
    handles = []
    for robot_id in ROBOTS:
        series = rec.under(robot_id).scalars(ent.TIMELINE_SIM)
        axes = [series[ent.axis_entity(ent.ENTITY_HAPTIC_P, a)] for a in ent.AXES]
        handles.append((axes[0].t_ns, np.abs(np.stack([s.values for s in axes])).max(axis=0)))
    (t0, handle0), (t1, handle1) = handles
    assert handle0[t0 < switch_ns].max() > 0.005  # arm0 driven first
    assert handle0[t0 >= switch_ns].max() == 0.0  # then centred
    assert handle1[t1 < switch_ns].max() == 0.0  # arm1 waits, its handle centred
    assert handle1[t1 >= switch_ns].max() > 0.005  # then driven


def test_the_report_has_a_part_per_robot_with_its_own_verdict(two_robots):
    for robot_id in ROBOTS:
        text = (two_robots["report_dir"] / robot_id / REPORT_SUMMARY_FILE).read_text()
        assert text.startswith(f"# Run report: {RECORDING_FILE}, robot {robot_id}")
        assert "- task: success (grasp" in text
        figures = list((two_robots["report_dir"] / robot_id).glob("*.png"))
        assert len(figures) >= 3, figures
