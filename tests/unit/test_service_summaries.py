"""The services' summaries as records (teleop.core.service_summaries): held to the run
summary's one description and to what the services write."""

from __future__ import annotations

import dataclasses
import typing

from teleop.bus.service import Service, ServiceOptions
from teleop.core.config import load_config
from teleop.core.service_summaries import (
    RECORDS,
    ControllerSummary,
    Drops,
    PlantSummary,
    ServiceSummary,
    record_problems,
)
from teleop.core.summary import SUMMARY_FIELDS, RunSummary

# Fields the reader of a run directory adds to what a service writes (teleop.bus.service).
READER_FIELDS = {"pid", "running", "earlier_incarnations"}


def test_a_field_the_run_copies_from_a_service_is_in_its_record_as_the_description_says():
    run_hints = typing.get_type_hints(RunSummary)
    for spec in (f for f in SUMMARY_FIELDS if f.by):
        record = RECORDS[spec.by]
        hints = typing.get_type_hints(record)
        assert spec.name in hints, f"{record.__name__} lacks {spec.name}"
        assert hints[spec.name] == run_hints[spec.name], spec.name


def test_the_fields_every_service_writes_are_the_base_records():
    class Quiet(Service):
        name = "quiet"

    summary = Service.summary(Quiet(load_config(), ServiceOptions()))
    base = {f.name for f in dataclasses.fields(ServiceSummary)} - READER_FIELDS
    assert base <= summary.keys()
    assert record_problems("quiet", summary) == []
    for role, record in RECORDS.items():  # every role's record is a ServiceSummary
        assert issubclass(record, ServiceSummary), role


def test_a_record_reads_its_fields_and_its_earlier_processes():
    content = {
        "service": "plant", "pid": 7, "steps": 400, "resumes": [{"sim_time_s": 1.0}],
        "dropped_by_reason": {"JOINT_COMMAND:range": 2}, "dropped_first": {},
        "stale_spells": {"felt_max_ms": 3.0},  # not read by the run: left out
        "earlier_incarnations": [{"pid": 5, "running": True, "steps": 100,
                                  "dropped_by_reason": {"JOINT_COMMAND:range": 1}}],
    }  # fmt: skip
    plant = PlantSummary.from_json(content)
    assert plant.steps == 400 and plant.resumes == ({"sim_time_s": 1.0},)
    (earlier,) = plant.earlier_incarnations
    assert isinstance(earlier, PlantSummary) and earlier.running and earlier.steps == 100
    assert [p.pid for p in plant.incarnations] == [5, 7]
    assert earlier.drops == Drops({"JOINT_COMMAND:range": 1}, {})
    assert plant.to_json()["resumes"] == [{"sim_time_s": 1.0}]
    assert record_problems("plant", content) == []
    wrong = {"steps": 1.5, "motion_problems": "none", "earlier_incarnations": [{"steps": "x"}]}
    assert record_problems("plant", wrong) == [
        "earlier: plant.steps: str, not int | None",
        "plant.steps: float, not int | None",
    ]
    assert record_problems("controller", wrong) == [
        "controller.motion_problems: str, not tuple[str, ...] | None"
    ]
    assert ControllerSummary.from_json({}).motion_problems is None
