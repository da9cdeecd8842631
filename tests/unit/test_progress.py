"""Progress lines and the short end-of-run summary (pure)."""

from __future__ import annotations

from teleop.core.criteria import TaskFigures, judge_task
from teleop.run.progress import PROGRESS_PERIOD_S, RunProgress, human_summary

PHASES = ("approach", "open", "descend")


def test_a_task_shows_its_phase_and_task_time_not_a_fraction_of_the_duration():
    progress = RunProgress(60.0, PHASES)
    assert progress.line(0.1).endswith("task not started")
    progress.on_phase(0, 0.2)
    progress.on_phase(1, 4.3)
    line = progress.line(5.3)
    assert "sim    5.3 s" in line and "task   5.1 s" in line and "phase 2/3 open" in line
    assert "%" not in line


def test_a_line_comes_at_each_new_phase_and_every_period_of_sim_time():
    progress = RunProgress(60.0, PHASES)
    progress.on_phase(0, 0.0)
    assert progress.due(0.0) is not None
    assert progress.due(1.0) is None
    progress.on_phase(1, 1.5)
    assert "open" in (progress.due(1.5) or "")
    assert progress.due(2.0) is None
    assert progress.due(PROGRESS_PERIOD_S) is not None


def test_a_run_without_an_operator_shows_its_share_of_the_duration():
    assert "50%)" in RunProgress(10.0).line(5.0)


def test_the_short_summary_says_the_outcome_the_verdict_and_where_the_files_are():
    summary = {
        "scenario": "grasp",
        "mode": "realtime",
        "success": True,
        "duration_s": 19.8,
        "phases": [{"phase": 0, "name": "approach"}, {"phase": 1, "name": "open"}],
        "max_contact_force_n": 2.04,
        "realtime_verdict": "degraded",
        "realtime_problems": ["the watchdog braked 7 time(s)"],
        "refused_privileges": ["SCHED_FIFO refused for plant (EPERM)"],
        "rrd": "/r/recording.rrd",
        "run_dir": "/r",
    }
    lines = human_summary(summary, "/r/summary.json")
    text = "\n".join(lines)
    assert lines[0] == "grasp (realtime): success: the cube is in the bin"
    assert "19.8 s" in text and "2 begun, the last: open" in text and "2.04 N" in text
    assert "real time          degraded" in text and "braked 7" in text
    assert "SCHED_FIFO refused" in text and "/r/summary.json" in text
    assert len(lines) <= 16


def test_the_short_summary_shows_clearance_and_an_obstacle_only_when_there_is_one():
    base = {"scenario": "grasp", "mode": "lockstep", "success": True, "arm_contacts": 0}
    plain = "\n".join(human_summary({**base, "obstacle_min_clearance_m": 1000.0}, None))
    assert "arm n/a (min), contacts 0" in plain and "obstacle" not in plain
    shown = {**base, "min_clearance_m": 0.0097, "obstacle_min_clearance_m": 0.064}
    text = "\n".join(human_summary(shown, None))
    assert "arm 9.7 mm (min), contacts 0, obstacle 64.0 mm" in text
    path = {"scenario": "path-following", "mode": "lockstep", "path_progress": 0.98,
            "stalled_s": 0.0, "min_clearance_m": 0.027, "arm_contacts": 0}  # fmt: skip
    text = "\n".join(human_summary(path, None))
    assert "path_progress 0.980, stalled 0.0 s" in text and "arm 27.0 mm" in text


def test_a_lockstep_run_reports_its_speed_and_its_data_not_a_real_time_verdict():
    summary = {"scenario": "grasp", "mode": "lockstep", "success": True,
               "realtime_factor": 0.489, "overrun_fraction": 0.0, "stale_commands": 0,
               "dropped_messages": 0, "realtime_verdict": "clean"}  # fmt: skip
    text = "\n".join(human_summary(summary, None))
    assert "lockstep (deterministic, not paced): 0.49 x real time, dropped 0" in text
    assert "data               clean" in text
    assert "real time" not in text.replace("x real time", "") and "watchdog" not in text


def test_a_viewer_that_could_not_start_is_said_and_the_recording_named():
    summary = {"scenario": "grasp", "mode": "lockstep", "success": True, "rrd": "/r/x.rrd",
               "services": {"recorder": {"viewer": "not spawned: no display"}}}  # fmt: skip
    text = "\n".join(human_summary(summary, None))
    assert "live viewer        not spawned: no display: open the recording" in text
    assert "live viewer" not in "\n".join(human_summary({**summary, "services": {}}, None))


def test_the_short_summary_names_every_protective_stop():
    stops = [
        {"cause": "contact_force", "t_s": 4.2, "measured": 9.1, "released_t_s": 5.0,
         "steps_held": 800},
        {"cause": "tool_speed", "t_s": 7.5, "measured": 0.34, "released_t_s": None,
         "steps_held": 12},
    ]  # fmt: skip
    summary = {"scenario": "grasp", "mode": "realtime", "success": True,
               "protective_stop": {"count": 2, "stops": stops}}  # fmt: skip
    text = "\n".join(human_summary(summary, None))
    assert "PROTECTIVE STOP    at 4.200 s sim time: contact force 9.1" in text
    assert "released at 5.000 s" in text and "tool speed 0.34" in text
    assert "still held at the end" in text
    assert "PROTECTIVE" not in "\n".join(human_summary({**summary, "protective_stop": None}, None))


def test_a_run_of_several_robots_shows_each_robot_and_names_its_one_recording_once():
    section = {"success": True, "rrd": "/r/recording.rrd", "max_contact_force_n": 1.0}
    summary = {
        "scenario": "grasp", "mode": "lockstep", "success": True, "rrd": "/r/recording.rrd",
        "robots": {"arm0": section, "arm1": {**section, "max_contact_force_n": 2.5}},
    }  # fmt: skip
    text = "\n".join(human_summary(summary, None))
    assert "2 robots: success" in text and "robot arm0:" in text and "robot arm1:" in text
    assert "2.50 N" in text
    assert text.count("/r/recording.rrd") == 1 and "(every robot)" in text


def test_a_failed_run_says_why_a_line_each():
    """A person's cube released beside the bin: the short summary gives the reason, with
    the distance and the bound, and the problems after it; a success gives none."""
    figures = {"object_in_box": False, "object_bin_distance_m": 0.131, "arm_contacts": 0,
               "max_device_force_n": 2.0, "commands_applied": 5000}  # fmt: skip
    problems = ["the operator did not finish the task"]
    verdict = judge_task("grasp", TaskFigures.from_json(figures), problems)
    summary = {"scenario": "grasp", "mode": "realtime", **figures, **verdict.to_json()}
    lines = human_summary(summary, None)
    assert lines[0] == "grasp (realtime): FAILED"
    assert lines[1].split() == [
        "why", "the", "cube", "is", "not", "in", "the", "bin:", "13.1", "cm", "from", "its",
        "inside", "(bound", "0)",
    ]  # fmt: skip
    assert lines[2].strip() == "the operator did not finish the task"
    in_bin = TaskFigures.from_json({**figures, "object_in_box": True})
    good = {**summary, **judge_task("grasp", in_bin).to_json()}
    assert not any(line.lstrip().startswith("why") for line in human_summary(good, None))
