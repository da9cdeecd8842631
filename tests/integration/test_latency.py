"""End-to-end latency: the stamps, the report's statistics, the floor chain, the stack.

The unit tests check the statistics against a plain numpy reference and the plant's
apply-on-arrival grid arithmetic. The integration tests run real processes under
supervisord: the realtime teleoperation stack (every service and the recorder) for 11 s,
and the bare relay chain. They check correctness (stamps in loop order, every handle
sample back exactly once, the report equal to a computation on the raw files) and one
generous sanity bound; wall-clock targets are the benchmark's
(tests/benchmarks/latency.py), not the tests'.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from teleop.bench import latency
from teleop.bench.relay import FLOOR_STAND_INS
from teleop.bus.messages import N_STAGES, Stage
from teleop.bus.stamps import StampLog
from teleop.core.clock import NS_PER_S, NS_PER_US
from teleop.core.config import load_config
from teleop.core.rundir import HAPTIC_SAMPLES_FILE, HAPTIC_TRACE_FILE

# HDR histograms keep 3 significant digits: a percentile is within this fraction of the
# exact order statistic (the bucket's highest equivalent value; 2^-10 < 1e-3).
HDR_RELATIVE_PRECISION = 1e-3
# The stack run: 10 s measured after the 1 s warm-up.
STACK_DURATION_S = 11.0
# A generous bound that only a broken pipeline (a stuck hop, a lost wake-up) can break.
ROUND_TRIP_P99_BOUND_US = 20_000.0
PERIOD_NS = 1_000_000


def _reference(values_ns: np.ndarray, pct: float) -> float:
    """The exact order statistic HDR approximates (nearest rank, the rank rounded half up
    as HdrHistogram does; numpy's inverted_cdf takes the ceiling instead), in us."""
    rank = max(1, int(pct * values_ns.size / 100.0 + 0.5))
    return float(np.sort(values_ns)[rank - 1]) / NS_PER_US


def assert_matches_reference(figures: dict, values_ns: np.ndarray) -> None:
    assert figures["count"] == values_ns.size
    for key, pct in latency.PERCENTILES.items():
        exact = _reference(values_ns, pct)
        assert figures[key] == pytest.approx(exact, rel=HDR_RELATIVE_PRECISION, abs=1e-3), key
    assert figures["max"] == pytest.approx(values_ns.max() / NS_PER_US)


# -- statistics, on synthetic data --------------------------------------------------------


def test_percentiles_match_numpy_within_hdr_precision():
    rng = np.random.default_rng(0)
    values_ns = rng.lognormal(mean=np.log(300e3), sigma=0.8, size=20_000).astype(np.int64)
    assert_matches_reference(latency.stats_us(values_ns), values_ns)
    assert latency.stats_us(np.array([], dtype=np.int64))["p99"] is None


def _synthetic_traces(n: int, rng: np.random.Generator) -> np.ndarray:
    """Loops every PERIOD_NS with positive random gaps between consecutive stages."""
    gaps = rng.integers(1_000, 200_000, size=(n, N_STAGES))
    gaps[:, 0] = 0
    traces = np.cumsum(gaps, axis=1) + (np.arange(n) * PERIOD_NS)[:, None] + NS_PER_S
    return traces.astype(np.int64)


def test_hops_add_up_to_the_round_trip_and_incomplete_loops_are_left_out():
    rng = np.random.default_rng(1)
    traces = _synthetic_traces(3000, rng)
    broken = traces[:10].copy()
    broken[:, Stage.PLANT_APPLIED] = 0  # a state the plant stepped without a new command
    loops = latency.complete_loops(np.vstack([traces, broken]))
    assert loops.shape[0] == 3000
    total = sum(latency.hop_ns(loops, hop) for hop in latency.HOPS)
    np.testing.assert_array_equal(total, latency.hop_ns(loops, latency.ROUND_TRIP))
    report = latency.analyse(traces)
    kept = latency.after_warmup(traces)
    assert kept.shape[0] == 3000 - round(latency.WARMUP_S * NS_PER_S / PERIOD_NS)
    assert_matches_reference(report["round_trip_us"], latency.hop_ns(kept, latency.ROUND_TRIP))
    assert report["non_monotonic"] == 0
    swapped = traces.copy()
    swapped[5, Stage.PLANT_RX], swapped[5, Stage.PLANT_APPLIED] = (
        swapped[5, Stage.PLANT_APPLIED],
        swapped[5, Stage.PLANT_RX],
    )
    assert latency.non_monotonic(swapped) == 1


def test_chain_accounting_finds_missing_and_duplicate_samples():
    rng = np.random.default_rng(2)
    traces = _synthetic_traces(100, rng)
    samples = np.stack([np.arange(100), traces[:, Stage.HAPTIC_SAMPLE]], axis=1)
    assert latency.chain_accounting(samples, traces) == {
        "samples": 100,
        "returned": 100,
        "missing": 0,
        "shed": 0,
        "unaccounted": 0,
        "duplicates": 0,
    }
    damaged = np.vstack([np.delete(traces, [40, 41], axis=0), traces[[7]]])
    shed = traces[[41], Stage.HAPTIC_SAMPLE]
    counts = latency.chain_accounting(samples, damaged, shed)
    assert counts["missing"] == 2 and counts["duplicates"] == 1
    assert counts["shed"] == 1 and counts["unaccounted"] == 1


def test_overhead_is_a_ratio_to_the_floor_and_none_without_a_floor_stage():
    stack = {"round_trip_us": {"p50": 300.0, "p99": 900.0}, "hops": {"plant_wait": {"p50": 5.0,
             "p99": 9.0}}}  # fmt: skip
    floor = {"round_trip_us": {"p50": 200.0, "p99": 600.0}, "hops": {"plant_wait": {"p50": 0.001,
             "p99": 0.001}}}  # fmt: skip
    result = latency.overhead(stack, floor)
    assert result["round_trip"]["p50_ratio"] == pytest.approx(1.5)
    assert result["round_trip"]["p99_extra_us"] == pytest.approx(300.0)
    assert result["plant_wait"]["p50_ratio"] is None
    assert result["plant_wait"]["p50_extra_us"] == pytest.approx(4.999)


def test_stamp_log_grows_saves_and_stays_bounded(tmp_path):
    log = StampLog(3, capacity_rows=2, max_rows=5)
    for i in range(7):
        log.append((i, 2 * i, 3 * i))
    np.testing.assert_array_equal(log.rows[:, 1], [0, 2, 4, 6, 8])
    assert log.overflow == 2
    log.save(tmp_path / "x.npy")
    np.testing.assert_array_equal(np.load(tmp_path / "x.npy"), log.rows)


# -- real processes -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def stack_run(tmp_path_factory) -> latency.StackRun:
    """The realtime stack, every service and the recorder, operator moving, 11 s."""
    run_dir = tmp_path_factory.mktemp("latency") / "stack"
    return latency.run_stack("stack", None, [], STACK_DURATION_S, run_dir)


@pytest.fixture(scope="module")
def floor_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("latency") / "floor"


@pytest.fixture(scope="module")
def floor_run(floor_dir) -> latency.FloorRun:
    return latency.run_floor(
        "floor",
        None,
        [],
        floor_dir,
        paced_s=2.0,
        back_to_back_count=200,
        sweep_sizes=(64, 65536),
        sweep_count=20,
    )


def test_stamps_follow_the_loop_in_order(stack_run):
    loops = latency.complete_loops(stack_run.traces)
    assert loops.shape[0] > 0
    assert latency.non_monotonic(loops) == 0
    # Each hop is a real interval: starts after the previous one (loop order) and none
    # is negative; the round trip is the sum of its hops.
    for hop in latency.HOPS:
        assert (latency.hop_ns(loops, hop) >= 0).all(), hop.name


def test_no_sample_lost_or_counted_twice_at_1khz(stack_run):
    services = stack_run.summary["services"]
    lost, reordered = latency.stream_counters(services)
    assert lost == {"haptic": 0, "command": 0, "state": 0, "feedback": 0}
    assert reordered == {"haptic": 0, "command": 0, "feedback": 0}
    chain = latency.chain_accounting(stack_run.samples, stack_run.traces, stack_run.shed_ns)
    assert chain["duplicates"] == 0
    # Every handle sample came back exactly once, unless a service behind its schedule
    # (a CPU stall on a loaded host) shed it on purpose and logged it: nothing vanishes.
    assert chain["unaccounted"] == 0, chain
    assert chain["returned"] + chain["missing"] == chain["samples"]
    # About ten seconds at 1 kHz came back (the device loop skips late ticks rather than
    # bursting, so a loaded machine samples a little less than 1 kHz).
    period_s = 1e-3
    assert chain["returned"] >= 0.1 * (STACK_DURATION_S - latency.WARMUP_S) / period_s


def test_report_equals_a_reference_computation_on_the_raw_files(stack_run):
    run_dir = Path(stack_run.summary["run_dir"])
    traces = np.load(run_dir / HAPTIC_TRACE_FILE)
    assert (np.load(run_dir / HAPTIC_SAMPLES_FILE)[:, 1] > 0).all()
    # Reference: plain numpy on the file, independent of the module's helpers.
    complete = traces[(traces > 0).all(axis=1)]
    first_ns = complete[:, Stage.HAPTIC_SAMPLE].min()
    kept = complete[complete[:, Stage.HAPTIC_SAMPLE] >= first_ns + latency.WARMUP_S * NS_PER_S]
    analysis = stack_run.analysis
    round_trip_ns = kept[:, Stage.FEEDBACK_RENDERED] - kept[:, Stage.HAPTIC_SAMPLE]
    assert_matches_reference(analysis["round_trip_us"], round_trip_ns)
    transport_ns = kept[:, Stage.PLANT_RX] - kept[:, Stage.CONTROLLER_TX]
    assert_matches_reference(analysis["hops"]["controller_to_plant"], transport_ns)


def test_round_trip_sanity_bound(stack_run):
    assert stack_run.analysis["round_trip_us"]["p99"] < ROUND_TRIP_P99_BOUND_US


def test_floor_chain_returns_every_payload_with_the_loop_stamps(floor_run):
    assert floor_run.sent == floor_run.received > 0
    loops = latency.complete_loops(floor_run.paced_traces)
    assert loops.shape[0] == floor_run.received
    assert latency.non_monotonic(loops) == 0
    # The relays do no work: nothing waits between the plant's arrival and its step.
    assert (latency.hop_ns(loops, latency.HOPS[3]) == 0).all()
    assert floor_run.back_to_back["count"] == 200
    assert [floor_run.sweep[size]["count"] for size in (64, 65536)] == [20, 20]


def test_floor_relays_run_on_the_cpus_of_the_services_they_stand_in_for(floor_run, floor_dir):
    cpu = load_config(None, []).cpu
    for relay, service in FLOOR_STAND_INS.items():
        wanted = sorted(set(cpu.for_service(service, "realtime")) & os.sched_getaffinity(0))
        log = (floor_dir / "logs" / f"{relay}.log").read_text()
        if wanted:
            assert f"pinned to CPU(s) {wanted}" in log, relay
        assert f"SCHED_FIFO priority {cpu.fifo_priority}" in log, relay


def test_a_floor_bracketing_the_stack_counts_both_halves(floor_run, stack_run):
    # The second half, as if run 100 s later (unset stamps stay 0).
    traces = floor_run.paced_traces
    later_traces = np.where(traces > 0, traces + 100 * NS_PER_S, 0)
    later = dataclasses.replace(floor_run, paced_parts=(later_traces,))
    both = latency.bracket(floor_run, later)
    assert both.paced["round_trip_us"]["count"] == 2 * floor_run.paced["round_trip_us"]["count"]
    assert both.sent == 2 * floor_run.sent and both.received == 2 * floor_run.received
    assert both.paced_by_part == (floor_run.paced["round_trip_us"],) * 2
    # Each half loses its own warm-up: the reference is each part's loops, concatenated.
    loops = latency.after_warmup(latency.complete_loops(floor_run.paced_traces))
    reference_ns = np.concatenate([latency.hop_ns(loops, latency.ROUND_TRIP)] * 2)
    assert_matches_reference(both.paced["round_trip_us"], reference_ns)
    report, raw = latency.build_report(stack_run, stack_run, both, floor_run, None)
    assert report["floor_parts_us"] == [floor_run.paced["round_trip_us"]] * 2
    assert raw["floor"].size == reference_ns.size
    assert any("before / after the stack" in line for line in report["conclusions"])


def test_report_files(stack_run, floor_run, tmp_path):
    report, raw = latency.build_report(stack_run, stack_run, floor_run, floor_run, None)
    for key in ("round_trip_us", "floor_us", "floor_back_to_back_us", "shm_off_round_trip_us"):
        assert set(report[key]) >= {"count", "p50", "p90", "p99", "p999", "max"}
    assert set(report["hops"]) == {hop.name for hop in latency.HOPS}
    assert set(report["lost"]) >= {"haptic", "command"} and "reordered" in report
    assert set(report["rate_hz"]) == {"plant", "haptic", "controller", "hmd"}
    assert [row["bytes"] for row in report["payload_sweep"]] == [64, 65536]
    # The p50 split: the transport hops' and the other stages' p50s, summed.
    (split,) = [line for line in report["conclusions"] if line.startswith("where the p50 goes")]
    hops = report["hops"]
    transport_us = sum(hops[h.name]["p50"] for h in latency.HOPS if h.kind == "transport")
    work_us = sum(hops[h.name]["p50"] for h in latency.HOPS if h.kind != "transport")
    assert f"transport hops {transport_us:.0f} us" in split
    assert f"compute and wait stages {work_us:.0f} us" in split
    assert f"controller_command {hops['controller_command']['p50']:.0f}" in split
    # The stack and the floor ran with their idle CPUs polling (the default).
    assert report["machine"]["idle_poll_cpus"] == sorted(os.sched_getaffinity(0))
    latency.write_json(report, tmp_path / "out.json")
    latency.write_png(report, raw, tmp_path / "out.png")
    latency.log_to_rerun(report, raw, tmp_path / "out.rrd")
    assert json.loads((tmp_path / "out.json").read_text())["hops"] == report["hops"]
    assert (tmp_path / "out.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    verify = subprocess.run(
        [str(Path(sys.executable).parent / "rerun"), "rrd", "verify", str(tmp_path / "out.rrd")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert verify.returncode == 0, verify.stderr[-2000:]


def test_cli_refuses_a_run_shorter_than_the_warmup():
    result = subprocess.run(
        [sys.executable, "-m", "teleop.cli", "latency", "--duration", "0.5"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and "warm-up" in result.stderr


def test_conclusions_name_the_frame_and_1mib_sizes_and_a_side_that_got_nothing():
    stats = {"p50": 500.0, "p99": 900.0}
    empty = {"count": 0, "p50": None, "p99": None}
    report = {
        "round_trip_us": stats,
        "floor_us": {"p50": 250.0, "p99": 600.0},
        "floor_back_to_back_us": {"p99": 300.0},
        "overhead": {"round_trip": {"p99_ratio": 1.5}},
        "lost": {"haptic": 0, "command": 0, "feedback": 0},
        "reordered": {"haptic": 0},
        "chain": {"missing": 0, "samples": 10},
        "shed": {"haptic": 0},
        "machine": {"idle_poll_cpus": [0, 1]},
        "payload_sweep": [
            {"bytes": 64, "shm_us": stats, "tcp_us": stats, "tcp_over_shm_p50": 1.0,
             "shm_faster": False},
            {"bytes": latency.EYE_VIEW_FRAME_BYTES, "shm_us": {"p50": 400.0},
             "tcp_us": {"p50": 800.0}, "tcp_over_shm_p50": 2.0, "shm_faster": True},
            {"bytes": 1 << 20, "shm_us": {"p50": 1000.0}, "tcp_us": empty,
             "tcp_over_shm_p50": None, "shm_faster": False},
        ],
    }  # fmt: skip
    lines = latency.conclusions(report)
    assert not any(line.startswith("64 B") for line in lines)
    assert f"{latency.EYE_VIEW_FRAME_BYTES} B (eye-view frame): SHM is faster" in "\n".join(lines)
    assert "1048576 B: no payload came back over TCP" in lines
    assert lines[-2].startswith("idle CPUs polled (cpu.idle_poll): 0, 1;")
    report["machine"]["idle_poll_cpus"] = []
    assert "idle CPUs halt (cpu.idle_poll off)" in latency.conclusions(report)
    report["machine"]["idle_poll_failed"] = {1: "not polled: no CPU cgroup hierarchy"}
    lines = latency.conclusions(report)
    assert "idle CPUs halt (cpu.idle_poll off)" not in lines
    assert "idle CPU 1 halts, its poller says: not polled: no CPU cgroup hierarchy" in lines


def test_loop_stage_cost_benchmark_replays_every_stage(tmp_path):
    """The cold-cache replay of the loop's stages (tests/benchmarks/loop_stage_cost.py)
    runs the real services' callbacks end to end: every stage gets a time, warm and cold."""
    out = tmp_path / "loop_stage_cost.json"
    script = Path(__file__).parents[1] / "benchmarks" / "loop_stage_cost.py"
    args = [sys.executable, str(script), "--periods", "20", "--rounds", "1", "--json", str(out)]
    subprocess.run(args, check=True, timeout=120, stdin=subprocess.DEVNULL, capture_output=True)
    stages = json.loads(out.read_text())["stages_us"]
    expected = [hop.name for hop in latency.HOPS if hop.kind in ("compute", "wait")]
    assert sorted(stages) == sorted(expected)
    for figures in stages.values():
        assert figures["warm"] > 0 and figures["cold"] > 0


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
