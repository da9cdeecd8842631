"""docs/latency.md is rendered from a report: deterministic, complete, refusing non-reports."""

from __future__ import annotations

import json

from teleop.bench import doc
from teleop.bench.loop_stats import HOPS


def report() -> dict:
    stats = {"count": 900, "p50": 500.0, "p99": 1200.0, "max": 3000.0}
    floor = {"count": 900, "p50": 250.0, "p99": 600.0, "max": 900.0}
    hops = {hop.name: {"p50": 50.0 + i, "p99": 90.0 + i} for i, hop in enumerate(HOPS)}
    return {
        "round_trip_us": stats,
        "floor_us": floor,
        "shm_off_round_trip_us": stats,
        "floor_shm_off_us": floor,
        "hops": hops,
        "floor_hops": hops,
        "overhead": {"round_trip": {"p50_ratio": 2.0, "p99_ratio": 2.0}},
        "conclusions": ["round trip p50 500 us"],
        "machine": {"cpus": 2, "loadavg_before": 0.1, "loadavg_after": 0.5},
        "duration_s": 60,
        "baseline_duration_s": 20,
        "date_utc": "2026-11-25 09:00 UTC",
    }


def test_the_document_is_rendered_from_the_report_alone(tmp_path):
    text = doc.render(report())
    assert text == doc.render(json.loads(json.dumps(report())))  # same report, same text
    assert "| stack, shared memory | 500 | 1200 | 3000 | 900 |" in text
    assert "Stack over floor: p50 2.00x, p99 2.00x." in text
    assert all(f"| {hop.name} ({hop.kind}) |" in text for hop in HOPS)
    assert "- round trip p50 500 us" in text and "2026-11-25 09:00 UTC" in text
    assert "old timing" not in text  # a report without that run has no such row
    path = tmp_path / "r.json"
    path.write_text(json.dumps(report()))
    assert doc.main([str(path), "--out", str(tmp_path / "latency.md")]) == 0
    assert (tmp_path / "latency.md").read_text() == text


def test_a_file_that_is_not_a_report_is_refused(tmp_path, capsys):
    path = tmp_path / "x.json"
    path.write_text("[1, 2]")
    assert doc.main([str(path)]) == 2
    assert "not a `teleop latency --json` report" in capsys.readouterr().err
    assert doc.main([str(tmp_path / "missing.json")]) == 2
