"""The task criteria (teleop.core.criteria): one verdict for a run, a sweep and the report."""

from __future__ import annotations

import json

import pytest

from teleop.core import criteria
from teleop.core.summary import RunSummary
from teleop.run import sweep
from teleop.viz.report import verdict_text


def _statuses(criteria: list[criteria.Criterion]) -> dict[str, str]:
    return {c.name: c.status for c in criteria}


def test_missing_figures_are_unavailable_never_passed() -> None:
    judged = _statuses(
        criteria.judge_path(
            criteria.TaskFigures.from_json({"path_error_rms_m": 2e-4, "path_error_max_m": 5e-4})
        )
    )
    assert judged == {
        "path error RMS": criteria.PASS,
        "path error max": criteria.PASS,
        "path progress": criteria.UNAVAILABLE,
        "no unintended contact": criteria.UNAVAILABLE,
        "commands applied": criteria.UNAVAILABLE,
    }


def test_path_criteria_fail_with_their_reason() -> None:
    summary = {
        "path_error_rms_m": 1.2e-3,
        "path_error_max_m": 2e-3,
        "path_progress": 0.5,
        "arm_contacts": 40,
    }
    judged = criteria.judge_path(criteria.TaskFigures.from_json(summary))
    failed = [c.detail for c in judged if c.status == criteria.FAIL]
    assert failed == [
        "path error RMS: 1.2 mm > 1 mm",
        "path progress 0.500 < 0.95",
        "unintended contact: 40 steps in contact",
    ]
    ok = {"path_error_rms_m": 1e-5, "path_error_max_m": 2e-5, "path_progress": 0.99,
          "arm_contacts": 0, "commands_applied": 5000}  # fmt: skip
    assert all(
        c.status == criteria.PASS for c in criteria.judge_path(criteria.TaskFigures.from_json(ok))
    )


def test_grasp_criteria_and_the_operators_reason() -> None:
    summary = {
        "object_in_box": False,
        "arm_contacts": 0,
        "max_device_force_n": 8.0,  # the device's peak: it saturated
        "services": {"operator": {"failure": "timeout in carry"}},
    }
    judged = _statuses(criteria.judge_grasp(criteria.TaskFigures.from_json(summary)))
    assert judged == {
        "cube in the bin": criteria.FAIL,
        "no unintended contact": criteria.PASS,
        "device force": criteria.FAIL,
        "commands applied": criteria.UNAVAILABLE,
    }
    assert criteria.event_reasons(RunSummary.from_json(summary)) == ["operator: timeout in carry"]
    light = {"object_in_box": True, "arm_contacts": 0, "max_device_force_n": 1.2,
             "commands_applied": 6000}  # fmt: skip
    assert all(
        c.status == criteria.PASS
        for c in criteria.judge_grasp(criteria.TaskFigures.from_json(light))
    )


def test_a_run_off_its_path_is_no_success_however_it_ended():
    """A path near a singularity: no stall, no contact, the run went to its end; 2.2 mm
    RMS and 93 % progress fail the criteria, so the run is not a success either."""
    summary = {"path_error_rms_m": 2.2e-3, "path_error_max_m": 2.9e-3, "path_progress": 0.93,
               "arm_contacts": 0, "commands_applied": 5000}  # fmt: skip
    verdict = criteria.judge_task("path-following", criteria.TaskFigures.from_json(summary))
    assert not verdict.success and verdict.complete
    assert verdict.failed == ["path error RMS: 2.2 mm > 1 mm", "path progress 0.930 < 0.95"]
    assert verdict.to_json()["success"] is False


def test_a_short_run_is_judged_on_what_it_measured_and_a_problem_fails_it():
    """Before run.settle_s there is no path error: unavailable, which fails a sweep's task
    (complete is False) but not the run; a problem the run reported fails it."""
    short = {"path_progress": None, "arm_contacts": 0, "commands_applied": 400}
    verdict = criteria.judge_task("path-following", criteria.TaskFigures.from_json(short))
    assert verdict.success and not verdict.complete
    assert verdict.unmeasured == ["path error RMS", "path error max", "path progress"]
    stalled = criteria.judge_task(
        "path-following", criteria.TaskFigures.from_json(short), ["the tool stalled 1.0 s"]
    )
    assert not stalled.success
    grasp = criteria.judge_task("grasp", criteria.TaskFigures.from_json(GOOD_GRASP))
    assert grasp.success and grasp.complete


@pytest.mark.parametrize("scenario", ["path-following", "grasp"])
def test_a_run_whose_plant_applied_no_command_fails_and_says_so(scenario):
    """A controller that sent nothing the plant could take (another protocol version, a
    wrong key): whatever the run's other figures, it is a failure with that reason."""
    figures = {**(GOOD_PATH if scenario != "grasp" else GOOD_GRASP), "commands_applied": 0,
               "commands_received": 0}  # fmt: skip
    verdict = criteria.judge_task(scenario, criteria.TaskFigures.from_json(figures))
    assert not verdict.success
    assert verdict.reasons == [
        "the plant applied no command of its controller: none it could read reached it "
        "(see the records dropped)"
    ]
    assert verdict.to_json()["reasons"] == verdict.reasons


def test_a_cube_beside_the_bin_says_how_far():
    away = {**GOOD_GRASP, "object_in_box": False, "object_bin_distance_m": 0.132}
    verdict = criteria.judge_task("grasp", criteria.TaskFigures.from_json(away))
    assert verdict.reasons == ["the cube is not in the bin: 13.2 cm from its inside (bound 0)"]


def _written(scenario: str, figures: dict, problems: list[str]) -> dict:
    """A summary as ``teleop run`` writes it: its scenario, figures and verdict."""
    return {"scenario": scenario, **figures,
            **criteria.judge_task(scenario, criteria.TaskFigures.from_json(figures),
                                  problems).to_json()}  # fmt: skip


GOOD_GRASP = {"object_in_box": True, "arm_contacts": 0, "max_device_force_n": 1.2,
              "commands_applied": 6000}  # fmt: skip
GOOD_PATH = {"path_error_rms_m": 1e-5, "path_error_max_m": 2e-5, "path_progress": 0.99,
             "arm_contacts": 0, "commands_applied": 5000}  # fmt: skip


@pytest.mark.parametrize(
    "scenario, figures, problems",
    [
        ("grasp", GOOD_GRASP, []),
        ("grasp", GOOD_GRASP, ["the operator did not finish the task"]),
        ("grasp", {**GOOD_GRASP, "object_in_box": False}, []),
        ("path-following", GOOD_PATH, []),
        ("path-following", GOOD_PATH, ["plant: the arm left its joint range"]),
        ("path-following", {**GOOD_PATH, "path_progress": None}, []),
    ],
)
def test_run_sweep_and_report_give_a_summary_one_verdict(scenario, figures, problems):
    """What ``teleop run`` wrote, judged again from the summary alone by the run's
    verdict, the sweep's record and the report's section: the same success."""
    summary = _written(scenario, figures, problems)
    read = RunSummary.from_json(json.loads(json.dumps(summary)))  # as read from file
    again = criteria.judge_summary(read)
    assert again.success is summary["success"]
    assert again.to_json() == {
        k: summary[k] for k in ("success", "criteria", "problems", "reasons")
    }
    success, _, reasons = sweep.judge_record(read)
    assert success is (summary["success"] and again.complete)
    if not success:
        assert reasons  # never a silent failure
    section = "\n".join(verdict_text(read))
    assert f"- task: {'success' if summary['success'] else 'failed'}" in section
    assert all(f"- problem: {p}" in section for p in problems)
