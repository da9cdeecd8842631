"""Two robots on one bus, end to end (``teleop run grasp --robots 2``): two plants and
two controllers under supervisord, each under its own robot id, one operator station
(haptic device, HMD, scripted operator, recorder) driving them in turn.

One lockstep run (deterministic): both tasks succeed; the handle drives one robot at a
time (each robot's handle is recorded centred while the other is driven); each robot's
section of the summary is judged again the same way; one recording holds both robots,
side by side in its 3D view, and ``--report`` writes a report per robot with its own
verdict. Beside it, where this machine can make test hosts, the same run across three
(a robot site per robot, the operator site on a clock of its own): each robot ends bit
for bit as on one host. That a robot's processes are kept to its own keys is
tests/integration/test_access.py's.
"""

from __future__ import annotations

import contextlib

import numpy as np
import pytest

from teleop.core.config import load_config
from teleop.core.criteria import judge_summary
from teleop.core.rundir import RECORDING_FILE, REPORT_SUMMARY_FILE, report_dir
from teleop.core.summary import RunSummary
from teleop.viz import entities as ent
from teleop.viz.blueprint import view_specs
from teleop.viz.rrd import Recording
from tests.e2e.hosts import HostsUnavailable, three_hosts
from tests.e2e.sites import TwoSites
from tests.e2e.test_grasp import assert_physical, finish_grasps, start_grasps
from tests.e2e.users import HANG_S

ROBOTS = ("arm0", "arm1")
# The operator site's monotonic clock this far ahead of the robot sites' (s).
OPERATOR_CLOCK_AHEAD_S = 7200
# No eye views across the sites (an observer: the final states do not depend on it), so
# the two runs at once leave each other more of the 2 cores.
SITES_SETTINGS = ("--set", 'run.scenario="grasp"', "--set", "run.seed=0",
                  "--set", "run.robots=2", "--set", "run.duration_s=120",
                  "--set", "eyeview.enabled=false")  # fmt: skip


@pytest.fixture(scope="module")
def two_robots(tmp_path_factory) -> dict:
    """The lockstep run of two robots on one host and, at once, across three test hosts
    (under "sites": the plants' summaries and the hub's recorder's, or why there are
    none)."""
    tmp_path = tmp_path_factory.mktemp("robots")
    with contextlib.ExitStack() as stack:
        try:
            robot, operator, second = stack.enter_context(three_hosts())
        except HostsUnavailable as exc:
            sites: TwoSites | str | BaseException = f"no test hosts: {exc}"
        else:
            sites = TwoSites(robot, operator, tmp_path / "sites", second_robot=second,
                             operator_clock_ahead_s=OPERATOR_CLOCK_AHEAD_S)  # fmt: skip
        args = ("--mode", "lockstep", "--seed", "0", "--robots", "2", "--report")
        started = start_grasps(tmp_path, {"two": args})
        if isinstance(sites, TwoSites):
            stack.enter_context(sites)
            try:
                sites.start(SITES_SETTINGS, strangers=False)
            except Exception as exc:  # the sites test reports it; the others go on
                sites = exc
        summary = finish_grasps(started)["two"]
        if isinstance(sites, TwoSites):
            try:
                sites.finish_robots(ROBOTS, HANG_S)
            except Exception as exc:
                sites = exc
    return {**summary, "report_dir": report_dir(tmp_path / "two" / RECORDING_FILE), "sites": sites}


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
        assert judge_summary(RunSummary.from_json(section)).to_json() == {
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


def test_across_three_hosts_each_robot_ends_as_on_one_host(two_robots):
    """A robot site per robot (the second joined the first's with the bundle it wrote for
    it, its router linked to the first's), the operator site on its own host and clock:
    both tasks done, each robot's final state bit for bit the one-host run's, the hub's
    one recording holding both robots."""
    sites = two_robots["sites"]
    if isinstance(sites, str):
        pytest.skip(sites)
    if isinstance(sites, BaseException):
        raise sites
    for robot_id in ROBOTS:
        plant = sites.summaries[f"plant-{robot_id}"]
        assert plant["finished"] and plant["object_in_box"], robot_id
        expected = two_robots["services"][f"plant-{robot_id}"]["final_state_sha256"]
        assert plant["final_state_sha256"] == expected, robot_id
    # Each site's processes linked to their own site's at once (the hub's recorder did
    # not wait for arm1's processes, on another site).
    assert all(sites.summaries[n]["unlinked_peers"] == [] for n in sites.summaries)
    recorded = sites.summaries["recorder"]["robots"]
    assert set(recorded) == set(ROBOTS)
    assert all(recorded[r]["samples_logged"]["plant_state"] > 0 for r in ROBOTS)
    assert Recording(str(sites.robot_dir / RECORDING_FILE)).robots == list(ROBOTS)
    assert "robot-site-arm1.json" in sites.robot_up  # the hub said where it is
    # The second robot's site: its own router, linked to the operator's through the hub.
    assert "robot_router-arm1: the other site is linked" in sites.second_robot_status
