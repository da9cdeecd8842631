"""The run summary's one description (teleop.core.summary): versioned writing and
reading, the schema check, the table docs/running.md embeds."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from teleop.core.config import load_config
from teleop.core.summary import (
    SUMMARY_VERSION,
    VERSION_FIELD,
    SummaryError,
    read_run_summary,
    summary_problems,
    summary_table,
    write_run_summary,
)
from teleop.run.experiments import run_path_following_inprocess

DOC = Path(__file__).resolve().parents[2] / "docs" / "running.md"
BEGIN, END = "<!-- summary_table() begin -->", "<!-- summary_table() end -->"


def test_a_written_summary_reads_back_with_its_version(tmp_path):
    summary = {"scenario": "grasp", "success": True, "criteria": [], "problems": []}
    write_run_summary(tmp_path / "run" / "summary.json", summary)
    again = read_run_summary(tmp_path / "run" / "summary.json")
    assert again == {VERSION_FIELD: SUMMARY_VERSION, **summary}
    assert summary_problems(again) == []


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


def test_an_inprocess_run_writes_what_the_schema_describes():
    config = load_config(None, ["run.duration_s=0.3", "run.settle_s=0.1"])
    summary = run_path_following_inprocess(config, progress=None)
    assert summary_problems(summary) == []


def test_running_doc_embeds_the_current_summary_table():
    text = DOC.read_text()
    embedded = text[text.index(BEGIN) + len(BEGIN) : text.index(END)]
    assert embedded.strip() == summary_table().strip(), (
        "docs/running.md's summary table is out of date: replace it with the output of "
        "python -m teleop.core.summary"
    )
