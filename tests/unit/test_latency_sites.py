"""The across-sites report's records: the JSON the command writes reads back as the same
record, and its tables are the same from the record or from its JSON."""

from __future__ import annotations

import json

import numpy as np

from teleop.bench import sites
from teleop.bench.latency import AcrossClocks, stats_us


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
    assert lines == sites.table(content)
    assert "| routers + netem |" in "\n".join(lines).replace("  ", " ")
    assert lines[-1] == "2 samples never came back"


def test_the_stack_across_sites_tables_alike_from_its_record_or_json():
    figures = stats_us(np.array([1_000_000, 2_000_000, 3_000_000]))
    loop = AcrossClocks(3, 0.5, 100.0, figures, figures, figures, figures)
    stack = sites.StackAcrossSites(True, "", 1.0, 0, 1000, loop)
    content = json.loads(json.dumps(stack.to_json()))
    assert list(content)[:6] == ["success", "failure", "realtime_factor", "braked_steps",
                                 "steps", "loops"]  # fmt: skip
    assert sites.StackAcrossSites.from_json(content) == stack
    floor = {"p50_ms": 0.3, "p99_ms": 0.6}
    lines = sites.stack_table(stack, floor)
    assert lines == sites.stack_table(content, floor)
    assert lines[0].startswith("The realtime grasp across two sites: success, realtime factor")
    none = sites.StackAcrossSites(False, "no loop", None, None, None, AcrossClocks(0))
    assert none.to_json()["loops"] == 0
    assert sites.stack_table(none.to_json(), None) == ["the stack across the sites closed no loop"]
