"""The latency report's statistics on synthetic data: percentiles against an exact
reference, hops, chain accounting, ratios to the floor, conclusions, the stamp log."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from teleop.bench import latency, loop_stats, run_counts
from teleop.bus.messages import N_STAGES, Stage
from teleop.bus.stamps import StampLog
from teleop.core.clock import NS_PER_S, NS_PER_US
from teleop.core.summary import RunSummary

# HDR histograms keep 3 significant digits: a percentile is within this fraction of the
# exact order statistic (the bucket's highest equivalent value; 2^-10 < 1e-3).
HDR_RELATIVE_PRECISION = 1e-3
PERIOD_NS = 1_000_000


def _reference(values_ns: np.ndarray, pct: float) -> float:
    """The exact order statistic HDR approximates (nearest rank, the rank rounded half up
    as HdrHistogram does; numpy's inverted_cdf takes the ceiling instead), in us."""
    rank = max(1, int(pct * values_ns.size / 100.0 + 0.5))
    return float(np.sort(values_ns)[rank - 1]) / NS_PER_US


def assert_matches_reference(figures: loop_stats.LatencyStats, values_ns: np.ndarray) -> None:
    assert figures.count == values_ns.size
    for key, pct in loop_stats.PERCENTILES.items():
        exact = _reference(values_ns, pct)
        assert figures.percentile_us(key) == pytest.approx(
            exact, rel=HDR_RELATIVE_PRECISION, abs=1e-3
        ), key
    assert figures.max_us == pytest.approx(values_ns.max() / NS_PER_US)


def _synthetic_traces(n: int, rng: np.random.Generator) -> np.ndarray:
    """Loops every PERIOD_NS with positive random gaps between consecutive stages."""
    gaps = rng.integers(1_000, 200_000, size=(n, N_STAGES))
    gaps[:, 0] = 0
    traces = np.cumsum(gaps, axis=1) + (np.arange(n) * PERIOD_NS)[:, None] + NS_PER_S
    return traces.astype(np.int64)


def test_percentiles_match_numpy_within_hdr_precision():
    rng = np.random.default_rng(0)
    values_ns = rng.lognormal(mean=np.log(300e3), sigma=0.8, size=20_000).astype(np.int64)
    assert_matches_reference(loop_stats.stats_us(values_ns), values_ns)
    empty = loop_stats.stats_us(np.array([], dtype=np.int64))
    assert empty.p99_us is None and empty.count == 0
    assert empty.to_json() == {"count": 0} | dict.fromkeys(
        ("p50", "p90", "p99", "p999", "max", "mean")
    )


def test_hops_add_up_to_the_round_trip_and_incomplete_loops_are_left_out():
    rng = np.random.default_rng(1)
    traces = _synthetic_traces(3000, rng)
    broken = traces[:10].copy()
    broken[:, Stage.PLANT_APPLIED] = 0  # a state the plant stepped without a new command
    loops = loop_stats.complete_loops(np.vstack([traces, broken]))
    assert loops.shape[0] == 3000
    total = sum(loop_stats.hop_ns(loops, hop) for hop in loop_stats.HOPS)
    np.testing.assert_array_equal(total, loop_stats.hop_ns(loops, loop_stats.ROUND_TRIP))
    report = loop_stats.analyse(traces)
    kept = loop_stats.after_warmup(traces)
    assert kept.shape[0] == 3000 - round(loop_stats.WARMUP_S * NS_PER_S / PERIOD_NS)
    assert_matches_reference(report.round_trip_us, loop_stats.hop_ns(kept, loop_stats.ROUND_TRIP))
    assert report.non_monotonic == 0
    swapped = traces.copy()
    swapped[5, Stage.PLANT_RX], swapped[5, Stage.PLANT_APPLIED] = (
        swapped[5, Stage.PLANT_APPLIED],
        swapped[5, Stage.PLANT_RX],
    )
    assert loop_stats.non_monotonic(swapped) == 1


def test_chain_accounting_finds_missing_and_duplicate_samples():
    rng = np.random.default_rng(2)
    traces = _synthetic_traces(100, rng)
    samples = np.stack([np.arange(100), traces[:, Stage.HAPTIC_SAMPLE]], axis=1)
    assert loop_stats.chain_accounting(samples, traces).to_json() == {
        "samples": 100,
        "returned": 100,
        "missing": 0,
        "shed": 0,
        "unaccounted": 0,
        "duplicates": 0,
    }
    damaged = np.vstack([np.delete(traces, [40, 41], axis=0), traces[[7]]])
    shed = traces[[41], Stage.HAPTIC_SAMPLE]
    counts = loop_stats.chain_accounting(samples, damaged, shed)
    assert counts.missing == 2 and counts.duplicates == 1
    assert counts.shed == 1 and counts.unaccounted == 1


def test_overhead_is_a_ratio_to_the_floor_and_none_without_a_floor_stage():
    stack = loop_stats.LoopAnalysis(_figures(300.0, 900.0), {"plant_wait": _figures(5.0, 9.0)}, 0)
    floor = loop_stats.LoopAnalysis(
        _figures(200.0, 600.0), {"plant_wait": _figures(0.001, 0.001)}, 0
    )
    result = loop_stats.overhead(stack, floor)
    assert result["round_trip"].p50_ratio == pytest.approx(1.5)
    assert result["round_trip"].p99_extra_us == pytest.approx(300.0)
    assert result["plant_wait"].p50_ratio is None
    assert result["plant_wait"].p50_extra_us == pytest.approx(4.999)
    missing = loop_stats.overhead(stack, loop_stats.LoopAnalysis(loop_stats.LatencyStats(0), {
        "plant_wait": loop_stats.LatencyStats(0)}, 0))  # fmt: skip
    assert missing["round_trip"].to_json() == dict.fromkeys(
        ("p50_ratio", "p50_extra_us", "p99_ratio", "p99_extra_us")
    )


def test_stamp_log_keeps_the_newest_rows_and_saves_them_oldest_first(tmp_path):
    log = StampLog(3, max_rows=5)
    for i in range(7):
        log.append((i, 2 * i, 3 * i))
    np.testing.assert_array_equal(log.rows[:, 1], [4, 6, 8, 10, 12])
    assert log.dropped == 2 and log.count == 7
    log.save(tmp_path / "x.npy")
    np.testing.assert_array_equal(np.load(tmp_path / "x.npy"), log.rows)


def _figures(p50_us: float | None, p99_us: float | None = None) -> loop_stats.LatencyStats:
    """Figures of a run with the given p50 and p99 (us)."""
    return loop_stats.LatencyStats(10, p50_us=p50_us, p99_us=p99_us)


def _report(**changes) -> latency.LatencyReport:
    """A report with no loops, counters at 0 and no payload sweep, with ``changes``."""
    none = loop_stats.LatencyStats(0)
    no_hops = {hop.name: none for hop in loop_stats.HOPS}
    ratio = loop_stats.FloorRatio(None, None, None, None)
    report = latency.LatencyReport(
        round_trip_us=none,
        hops_us=no_hops,
        floor_us=none,
        floor_parts_us=(none,),
        floor_hops_us=no_hops,
        floor_back_to_back_us=none,
        floor_sent=0,
        floor_received=0,
        shm_off_round_trip_us=none,
        shm_off_hops_us=no_hops,
        floor_shm_off_us=none,
        floor_shm_off_back_to_back_us=none,
        overhead={"round_trip": ratio} | dict.fromkeys(no_hops, ratio),
        lost=run_counts.LostCounts(0, 0, 0, 0),
        reordered=run_counts.ReorderedCounts(0, 0, 0),
        shed=run_counts.ShedCounts(0, 0, 0, 0, 0, 0),
        chain=loop_stats.ChainAccounting(10, 10, 0, 0, 0, 0),
        non_monotonic=0,
        rates=run_counts.ServiceRates(None, None, None, None),
        cpu_share={"plant": None},
        deadline_misses=run_counts.DeadlineMisses(
            run_counts.PlantMisses(None, None, None, None, None),
            run_counts.HapticMisses(None, None, None, None),
        ),
        payload_sweep=(),
        dropped_messages=0,
        machine=latency.Machine(2, (0.5, 0.5, 0.5), (), {}),
    )
    return dataclasses.replace(report, **changes)


def test_conclusions_name_the_frame_and_1mib_sizes_and_a_side_that_got_nothing():
    stats = _figures(500.0, 900.0)
    report = _report(
        round_trip_us=stats,
        floor_us=_figures(250.0, 600.0),
        floor_back_to_back_us=_figures(None, 300.0),
        overhead={"round_trip": loop_stats.FloorRatio(None, None, 1.5, None)},
        machine=latency.Machine(2, (0.5, 0.5, 0.5), (0, 1), None),
        payload_sweep=(
            latency.SweepRow(64, stats, stats, 1.0, False),
            latency.SweepRow(latency.EYE_VIEW_FRAME_BYTES, _figures(400.0), _figures(800.0),
                             2.0, True),
            latency.SweepRow(1 << 20, _figures(1000.0), loop_stats.LatencyStats(0), None, False),
        ),
    )  # fmt: skip
    lines = latency.conclusions(report)
    assert not any(line.startswith("64 B") for line in lines)
    assert f"{latency.EYE_VIEW_FRAME_BYTES} B (eye-view frame): SHM is faster" in "\n".join(lines)
    assert "1048576 B: no payload came back over TCP" in lines
    assert lines[-2].startswith("idle CPUs polled (cpu.idle_poll): 0, 1;")
    halting = dataclasses.replace(report.machine, idle_poll_cpus=())
    assert "idle CPUs halt (cpu.idle_poll off)" in latency.conclusions(
        dataclasses.replace(report, machine=halting)
    )
    failed = dataclasses.replace(halting, idle_poll_failed={"1": "not polled: no cgroup"})
    lines = latency.conclusions(dataclasses.replace(report, machine=failed))
    assert "idle CPUs halt (cpu.idle_poll off)" not in lines
    assert "idle CPU 1 halts, its poller says: not polled: no cgroup" in lines


def test_the_report_reads_back_from_its_json_as_written():
    stats = loop_stats.stats_us(np.array([200_000, 300_000, 900_000]))
    report = _report(
        round_trip_us=stats,
        floor_parts_us=(stats, stats),
        payload_sweep=(
            latency.SweepRow(64, stats, None, None, False),
            latency.SweepRow(65536, loop_stats.LatencyStats(0, not_measured="too big"), stats,
                             None, False),
        ),
        old_timing_round_trip_us=stats,
        old_timing_hops_us={hop.name: stats for hop in loop_stats.HOPS},
        conclusions=("a line",),
        machine=latency.Machine(2, (0.5, 0.5, 0.5), (0,), {"1": "off"}, (0.1, 0.2, 0.3)),
        duration_s=5.0,
        rrd="out.rrd",
    )  # fmt: skip
    content = json.loads(json.dumps(report.to_json()))
    assert content["payload_sweep"][0]["tcp_us"] == {}
    assert content["payload_sweep"][1]["shm_us"]["not_measured"] == "too big"
    assert list(content["machine"])[-1] == "loadavg_before"
    assert "wall_s" not in content and content["rrd"] == "out.rrd"
    assert latency.LatencyReport.from_json(content) == report
    assert "old_timing_hops" not in _report().to_json()


def test_the_services_counters_are_read_from_the_run_summary():
    services = {
        "plant": {"steps": 100, "overrun_fraction": 0.0, "rate_hz": 250.0, "skipped_ticks": 1,
                  "arrival": {"commands_shed": 2, "commands_lost": 3, "stalls": 4}},
        "controller": {"haptic_shed": 5, "skipped_states": 6, "cycles": 500, "cpu_s": 1.0},
        "haptic": {"feedback_reordered": 7, "loop": {"overruns": 8}},
        "hmd": {"published": 90},
    }  # fmt: skip
    summary = RunSummary.from_json({"services": services, "wall_s": 2.0, "stack_wall_s": 4.0})
    assert run_counts.shed_counters(summary) == run_counts.ShedCounts(5, 0, 0, 2, 0, 0)
    lost, reordered = run_counts.stream_counters(summary)
    assert lost == run_counts.LostCounts(haptic=0, command=3, state=6, feedback=0)
    assert reordered == run_counts.ReorderedCounts(haptic=0, command=0, feedback=7)
    assert run_counts.service_rates(summary).to_json() == {
        "plant": 250.0, "haptic": None, "controller": 250.0, "hmd": 45.0}  # fmt: skip
    assert run_counts.cpu_share(summary) == {
        "plant": None, "controller": 0.25, "haptic": None, "hmd": None}  # fmt: skip
    assert run_counts.deadline_misses(summary).to_json() == {
        "plant": {"steps": 100, "periods_without_command": None, "stalls": 4,
                  "overrun_fraction": 0.0, "skipped_ticks": 1},
        "haptic": {"steps": None, "overruns": 8, "skipped_ticks": None,
                   "lateness_p99_us": None},
    }  # fmt: skip


def test_variant_rounds_rotate_so_every_variant_runs_in_every_position():
    sys.path.insert(0, str(Path(__file__).parents[1] / "benchmarks"))
    try:
        from variants import round_order
    finally:
        sys.path.pop(0)
    names = ["default", "a", "b"]
    orders = [round_order(names, r) for r in range(3)]
    assert orders[0] == names
    for position in range(3):
        assert sorted(order[position] for order in orders) == sorted(names)
    assert round_order(names, 3) == names


def test_the_histogram_axis_fits_the_data_not_a_fixed_range():
    from teleop.bench.latency import fitted_bins_us

    raw = {"stack": np.array([200_000, 2_000_000]), "empty": np.array([], dtype=np.int64)}
    bins = fitted_bins_us(raw)
    assert 100 < bins[0] < 200 and 2000 < bins[-1] < 4000  # 200 us .. 2 ms, with margins
    assert np.all(np.diff(np.log10(bins)) > 0)


def test_the_floor_sends_only_sizes_its_pools_carry_and_says_why_not_the_others():
    from shm import PoolReport
    from teleop.bench.relay import FLOOR_PAYLOADS_PER_POOL, unmeasurable_reason
    from teleop.core.config import BusConfig

    bus = BusConfig()
    why = "RLIMIT_MEMLOCK (ulimit -l) 8388608 B leaves room for a pool of 699050 B"
    pool = PoolReport(16 << 20, 640 * 1024, 8 << 20, True, why)
    assert unmeasurable_reason(64, bus, pool) == ""  # inline, below the SHM threshold
    assert unmeasurable_reason(65536, bus, pool) == ""
    reason = unmeasurable_reason(1 << 20, bus, pool)
    assert f"holds fewer than {FLOOR_PAYLOADS_PER_POOL} payloads of 1048576 B" in reason
    assert why in reason
    # Shared memory off: the socket carries any size; on without a pool, none that
    # needs the SHM path (the low-latency transport would lose it without an error).
    assert unmeasurable_reason(1 << 20, BusConfig(shm=False), None) == ""
    assert "pool of 0 B" in unmeasurable_reason(65536, bus, None)
    not_sent = loop_stats.LatencyStats(0, not_measured=reason)
    report = _report(payload_sweep=(latency.SweepRow(1 << 20, not_sent, _figures(900.0), None,
                                                     False),))  # fmt: skip
    assert f"1048576 B: not measured over SHM ({reason})" in latency.conclusions(report)


def test_across_two_clocks_the_offset_is_found_within_its_uncertainty_and_each_way_too():
    """Loops whose robot-side stamps are on a clock three hours behind the operator's,
    the way out 5-6 ms and back 2-3 ms (unequal): the offset is found within the half
    wire time it claims, each way within that of its true times, the round trip exact."""
    rng = np.random.default_rng(3)
    behind_ns = -3 * 3600 * NS_PER_S
    traces = _synthetic_traces(4000, rng) - 2 * behind_ns  # both clocks running for hours
    out_ns = rng.integers(5_000_000, 6_000_000, size=traces.shape[0])
    back_ns = rng.integers(2_000_000, 3_000_000, size=traces.shape[0])
    robot = slice(Stage.CONTROLLER_RX, Stage.FEEDBACK_TX + 1)
    traces[:, robot] += out_ns[:, None]
    traces[:, Stage.FEEDBACK_RX :] += (out_ns + back_ns)[:, None]
    true_round_trip = loop_stats.hop_ns(loop_stats.warm_loops(traces), loop_stats.ROUND_TRIP)
    traces[:, robot] += behind_ns
    figures = loop_stats.across_clocks(traces)
    uncertainty_ns = figures.offset_uncertainty_us * NS_PER_US
    assert 3.5e6 < uncertainty_ns < 4.5e6  # half the least out + back: (5 + 2) / 2 ms-ish
    assert abs(figures.offset_s * NS_PER_S - behind_ns) <= uncertainty_ns
    out_us, back_us = figures.operator_to_robot_us, figures.robot_to_operator_us
    assert abs(out_us.p50_us * NS_PER_US - 5.5e6) <= uncertainty_ns + 0.1e6
    assert abs(back_us.p50_us * NS_PER_US - 2.5e6) <= uncertainty_ns + 0.1e6
    assert_matches_reference(figures.round_trip_us, true_round_trip)
    assert loop_stats.across_clocks(traces[:0]).to_json() == {"loops": 0}
