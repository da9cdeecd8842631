"""The across-sites report's records: the JSON the command writes reads back as the same
record, with the stack's run when there is one; the tables and the verdict read the
record."""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from teleop.bench import sites
from teleop.bench.loop_stats import AcrossClocks, stats_us


def _report() -> sites.SitesReport:
    direct, routed = sites.PathTrips(100, 0.2, 0.4), sites.PathTrips(99, 0.3, 0.6)
    delayed = sites.PathTrips(100, 10.3, 10.9, delay_ms=5.0, p50_over_floor_plus_2_delays=1.01)
    return sites.SitesReport(
        load_average_start=(0.5, 0.4, 0.3),
        pings=100,
        rate_hz=1000.0,
        rounds=({sites.DIRECT: direct, sites.ROUTERS: routed},
                {sites.ROUTERS: routed, sites.DIRECT: direct}),
        delays=(delayed,),
        routers_over_direct_p50=1.5,
        routers_over_direct_p99=1.5,
        load_average_end=(0.6, 0.4, 0.3),
        lost=2,
    )  # fmt: skip


def test_the_sites_report_reads_back_from_its_json_and_tables_alike():
    report = _report()
    content = json.loads(json.dumps(report.to_json()))
    assert list(content) == [
        "load_average_start", "pings", "rate_hz", "rounds", "delays",
        "routers_over_direct_p50", "routers_over_direct_p99", "load_average_end", "lost",
    ]  # fmt: skip
    assert content["rounds"][1] == {
        "routers": {"received": 99, "p50_ms": 0.3, "p99_ms": 0.6},
        "direct": {"received": 100, "p50_ms": 0.2, "p99_ms": 0.4},
    }
    assert content["delays"][0]["delay_ms"] == 5.0
    assert sites.SitesReport.from_json(content) == report
    lines = sites.table(report)
    assert "| routers + netem |" in "\n".join(lines).replace("  ", " ")
    assert lines[-1] == "2 samples never came back"
    assert not report.clean  # samples lost
    assert report.routers_floor_ms() == {"p50_ms": 0.3, "p99_ms": 0.6}


def _stack(success: bool = True, loops: int = 3) -> sites.StackAcrossSites:
    figures = stats_us(np.array([1_000_000, 2_000_000, 3_000_000]))
    loop = AcrossClocks(loops, 0.5, 100.0, figures, figures, figures, figures)
    return sites.StackAcrossSites(success, "", 1.0, 0, 1000, loop)


def test_the_stack_across_sites_reads_back_in_its_report_and_tables():
    stack = _stack()
    content = json.loads(json.dumps(stack.to_json()))
    assert list(content)[:6] == ["success", "failure", "realtime_factor", "braked_steps",
                                 "steps", "loops"]  # fmt: skip
    assert sites.StackAcrossSites.from_json(content) == stack
    report = dataclasses.replace(_report(), lost=0, stack=stack)
    written = json.loads(json.dumps(report.to_json()))
    assert written["stack"] == content and sites.SitesReport.from_json(written) == report
    assert report.clean
    assert not dataclasses.replace(report, stack=_stack(success=False)).clean
    assert not dataclasses.replace(report, stack=_stack(loops=0)).clean
    lines = sites.stack_table(stack, report.routers_floor_ms())
    assert lines[0].startswith("The realtime grasp across two sites: success, realtime factor")
    assert any("floor: bare ends through the routers" in line for line in lines)
    none = sites.StackAcrossSites(False, "no loop", None, None, None, AcrossClocks(0))
    assert none.to_json()["loops"] == 0
    assert sites.stack_table(none, None) == ["the stack across the sites closed no loop"]
