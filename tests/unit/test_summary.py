"""The run summary's one description (teleop.core.summary): versioned writing and
reading, the schema check, the table docs/running.md embeds."""

from __future__ import annotations

import dataclasses
import json
import typing
from collections.abc import Mapping
from pathlib import Path

import pytest

from teleop.core.config import load_config
from teleop.core.summary import (
    SUMMARY_FIELDS,
    SUMMARY_VERSION,
    VERSION_FIELD,
    Criterion,
    FaultOutcome,
    PhaseTime,
    RunSummary,
    SummaryError,
    read_run_summary,
    summary_problems,
    summary_table,
    summary_text,
    write_run_summary,
)
from teleop.run.experiments import run_path_following_inprocess

DOC = Path(__file__).resolve().parents[2] / "docs" / "running.md"
BEGIN, END = "<!-- summary_table() begin -->", "<!-- summary_table() end -->"


def test_a_written_summary_reads_back_with_its_version(tmp_path):
    summary = {"scenario": "grasp", "success": True, "criteria": [], "problems": []}
    write_run_summary(tmp_path / "run" / "summary.json", summary)
    again = read_run_summary(tmp_path / "run" / "summary.json")
    assert again.to_json() == {VERSION_FIELD: SUMMARY_VERSION, **summary}
    assert again.scenario == "grasp" and again.success is True and again.criteria == ()
    assert summary_problems(again.to_json()) == []


def test_what_is_no_summary_of_this_version_is_refused_in_one_line(tmp_path):
    path = tmp_path / "summary.json"
    with pytest.raises(SummaryError, match="No such file"):
        read_run_summary(path)
    path.write_text("{")
    with pytest.raises(SummaryError, match="not JSON"):
        read_run_summary(path)
    path.write_text(json.dumps({"plant": 1}))
    with pytest.raises(SummaryError, match="not a run summary"):
        read_run_summary(path)
    path.write_text(json.dumps({"scenario": "grasp"}))  # before versions
    with pytest.raises(SummaryError, match="summary version None, this build reads"):
        read_run_summary(path)
    path.write_text(json.dumps({"scenario": "grasp", VERSION_FIELD: SUMMARY_VERSION + 1}))
    with pytest.raises(SummaryError, match="run it again with this build"):
        read_run_summary(path)


def test_the_check_names_unknown_fields_and_wrong_types():
    problems = summary_problems(
        {"scenario": "grasp", "success": 1, "steps": True, "duration_s": None, "colour": "red"}
    )
    assert problems == [
        "success: int, not boolean",
        "steps: bool, not integer",
        "colour: not a summary field (teleop.core.summary)",
    ]


def test_an_inprocess_run_writes_what_the_schema_describes(tmp_path):
    config = load_config(None, ["run.duration_s=0.3", "run.settle_s=0.1"])
    summary = run_path_following_inprocess(config, progress=None)
    assert summary_problems(summary) == []
    # Its record gives back the same JSON, field for field and in the same order.
    write_run_summary(tmp_path / "summary.json", summary)
    record = read_run_summary(tmp_path / "summary.json")
    assert summary_text(record.to_json()) == (tmp_path / "summary.json").read_text()
    assert record.final_state_sha256 == summary["final_state_sha256"]
    assert all(isinstance(c, Criterion) for c in record.criteria or ())


# The Python type of each JSON type in RunSummary's annotations (``T | None``).
_PYTHON_TYPES = {"boolean": bool, "integer": int, "number": float, "string": str,
                 "array": tuple, "object": Mapping}  # fmt: skip


def test_the_record_has_the_descriptions_fields_in_its_order_and_types():
    """RunSummary is checked against SUMMARY_FIELDS, the one description: a field added
    to one and not the other, or of another type, fails here."""
    hints = typing.get_type_hints(RunSummary)
    names = [f.name for f in dataclasses.fields(RunSummary) if f.name != "written"]
    assert names == [f.name for f in SUMMARY_FIELDS]
    for spec in SUMMARY_FIELDS:
        outer, none = typing.get_args(hints[spec.name])
        assert none is type(None), spec.name
        origin = typing.get_origin(outer) or outer
        assert issubclass(origin, _PYTHON_TYPES[spec.type]), (spec.name, outer)


def test_a_summary_of_several_robots_reads_its_sections_as_records():
    section = {
        "scenario": "grasp",
        "success": True,
        "object_in_box": True,
        "rrd": None,
        "criteria": [{"name": "cube in the bin", "status": "pass", "detail": "yes"}],
    }
    content = {"scenario": "grasp", "mode": "lockstep", "success": True, "failure": None,
               "robots": {"arm0": section}, "services": {}}  # fmt: skip
    record = RunSummary.from_json(content)
    assert record.to_json() == content
    arm0 = record.section("arm0")
    assert arm0.mode == "lockstep" and arm0.object_in_box is True and arm0.robots is None
    assert arm0.criteria == (Criterion("cube in the bin", "pass", "yes"),)
    assert "failure" in arm0.written and "robots" not in arm0.written
    with pytest.raises(SummaryError, match="success: str, not boolean"):
        RunSummary.from_json({"scenario": "grasp", "success": "yes"})
    assert RunSummary(scenario="grasp", success=False).to_json() == {
        "scenario": "grasp", "success": False,
    }  # fmt: skip


def test_the_phases_and_faults_read_as_records_and_write_back_as_read():
    content = {
        "scenario": "grasp",
        "phases": [{"phase": 0, "name": "approach", "sim_time_s": 0.004},
                   {"phase": 1, "name": "open", "sim_time_s": 1.5}],
        "faults": [{"service": "controller", "kind": "kill", "t_s": 1.5, "freeze_s": None,
                    "frozen_s": None, "brake_ms": 2.0, "restart_s": 0.6, "resumed_s": 1.6,
                    "success": True},
                   {"service": "hmd", "kind": "kill", "t_s": None, "freeze_s": None,
                    "frozen_s": None, "brake_ms": None, "restart_s": None, "resumed_s": None,
                    "success": None, "error": "no process to signal"}],
    }  # fmt: skip
    record = RunSummary.from_json(content)
    assert record.phases == (PhaseTime(0, "approach", 0.004), PhaseTime(1, "open", 1.5))
    assert record.faults is not None and record.faults[1].error == "no process to signal"
    assert record.faults[0] == FaultOutcome(
        "controller", "kill", 1.5, brake_ms=2.0, restart_s=0.6, resumed_s=1.6, success=True
    )
    assert json.loads(json.dumps(record.to_json())) == content
    with pytest.raises(SummaryError, match="phases: not an array of objects"):
        RunSummary.from_json({"scenario": "grasp", "phases": ["approach"]})


def test_running_doc_embeds_the_current_summary_table():
    text = DOC.read_text()
    embedded = text[text.index(BEGIN) + len(BEGIN) : text.index(END)]
    assert embedded.strip() == summary_table().strip(), (
        "docs/running.md's summary table is out of date: replace it with the output of "
        "python -m teleop.core.summary"
    )
