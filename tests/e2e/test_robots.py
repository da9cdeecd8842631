"""Two robots on one bus, end to end (``teleop run grasp --robots 2``): two plants and
two controllers under supervisord, each under its own robot id, one operator station
(haptic device, HMD, scripted operator, recorder) driving them in turn.

One lockstep run (deterministic): both tasks succeed; the handle drives one robot at a
time (the other's recording shows a centred handle); each robot's section of the summary
is judged again the same way; each robot has its own recording. That a robot's processes
are kept to its own keys is tests/integration/test_access.py's.
"""

from __future__ import annotations

import numpy as np
import pytest

from teleop.core.config import load_config
from teleop.core.criteria import judge_summary
from teleop.viz import entities as ent
from teleop.viz.rrd import Recording
from tests.e2e.test_grasp import assert_physical, grasp

ROBOTS = ("arm0", "arm1")


@pytest.fixture(scope="module")
def two_robots(tmp_path_factory) -> dict:
    tmp_path = tmp_path_factory.mktemp("robots")
    return grasp(tmp_path, "two", "--mode", "lockstep", "--seed", "0", "--robots", "2")


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
            key: section[key] for key in ("success", "criteria", "problems")
        }  # the one verdict, given again the same way
        assert_physical({**summary, **section})
        assert set(section["cpu_s_per_sim_s"]) == {"plant", "controller"}
    first, second = (summary["robots"][r]["phases"] for r in ROBOTS)
    # arm1's task starts where arm0's ended: one hand, one task at a time
    switches = services["haptic"]["robot_switches"]
    assert [s["robot"] for s in switches] == [1]
    switch_s = switches[0]["tick"] * load_config().plant.timestep_s
    assert first[-1]["sim_time_s"] < switch_s <= second[0]["sim_time_s"] + 0.1
    assert summary["dropped_messages"] == 0 and summary["unlinked_peers"] == {}


def test_each_robot_records_its_own_handle_centred_while_the_other_is_driven(two_robots):
    summary = two_robots
    switch_ns = round(
        summary["services"]["haptic"]["robot_switches"][0]["tick"]
        * load_config().plant.timestep_s * 1e9
    )  # fmt: skip
    rrds = [summary["robots"][r]["rrd"] for r in ROBOTS]
    assert summary["rrds"] == rrds and len(set(rrds)) == 2
    handles = []
    for rrd in rrds:
        series = Recording(rrd).scalars(ent.TIMELINE_SIM)
        axes = [series[ent.axis_entity(ent.ENTITY_HAPTIC_P, a)] for a in ent.AXES]
        handles.append((axes[0].t_ns, np.abs(np.stack([s.values for s in axes])).max(axis=0)))
    (t0, handle0), (t1, handle1) = handles
    assert handle0[t0 < switch_ns].max() > 0.005  # arm0 driven first
    assert handle0[t0 >= switch_ns].max() == 0.0  # then centred
    assert handle1[t1 < switch_ns].max() == 0.0  # arm1 waits, its handle centred
    assert handle1[t1 >= switch_ns].max() > 0.005  # then driven
