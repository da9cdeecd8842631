"""The latency measurement end to end: the realtime teleoperation stack (every service
and the recorder) for 11 s and the bare relay chain, under supervisord. Correctness only
(stamps in loop order, every handle sample back exactly once, the report equal to a
computation on the raw files); wall-clock figures are the benchmark's
(tests/benchmarks/latency.py), not the tests'."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from teleop.bench import latency, loop_stats, run_counts
from teleop.bench.relay import FLOOR_STAND_INS
from teleop.bus.messages import Stage
from teleop.bus.service import fifo_scheduling
from teleop.core.clock import NS_PER_S
from teleop.core.config import load_config
from teleop.core.rundir import HAPTIC_SAMPLES_FILE, HAPTIC_TRACE_FILE
from teleop.run.idle_poll import NOT_POLLED, idle_cgroup_writable
from tests.e2e.outcome import needs_realtime_stack
from tests.unit.test_latency_report import assert_matches_reference

# The stack run: 10 s measured after the 1 s warm-up.
STACK_DURATION_S = 11.0


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
    loops = loop_stats.complete_loops(stack_run.traces)
    assert loops.shape[0] > 0
    assert loop_stats.non_monotonic(loops) == 0
    # Each hop is a real interval: starts after the previous one (loop order) and none
    # is negative; the round trip is the sum of its hops.
    for hop in loop_stats.HOPS:
        assert (loop_stats.hop_ns(loops, hop) >= 0).all(), hop.name


@needs_realtime_stack
def test_no_sample_lost_or_counted_twice_at_1khz(stack_run):
    lost, reordered = run_counts.stream_counters(stack_run.summary)
    assert lost == run_counts.LostCounts(haptic=0, command=0, state=0, feedback=0)
    assert reordered == run_counts.ReorderedCounts(haptic=0, command=0, feedback=0)
    chain = loop_stats.chain_accounting(stack_run.samples, stack_run.traces, stack_run.shed_ns)
    assert chain.duplicates == 0
    # Every handle sample came back exactly once, unless a service behind its schedule
    # (a CPU stall on a loaded host) shed it on purpose and logged it: nothing vanishes.
    assert chain.unaccounted == 0, chain
    assert chain.returned + chain.missing == chain.samples
    # About ten seconds at 1 kHz came back (the device loop skips late ticks rather than
    # bursting, so a loaded machine samples a little less than 1 kHz).
    period_s = 1e-3
    assert chain.returned >= 0.1 * (STACK_DURATION_S - loop_stats.WARMUP_S) / period_s


def test_report_equals_a_reference_computation_on_the_raw_files(stack_run):
    run_dir = Path(stack_run.summary.run_dir)
    traces = np.load(run_dir / HAPTIC_TRACE_FILE)
    assert (np.load(run_dir / HAPTIC_SAMPLES_FILE)[:, 1] > 0).all()
    # Reference: plain numpy on the file, independent of the module's helpers.
    complete = traces[(traces > 0).all(axis=1)]
    first_ns = complete[:, Stage.HAPTIC_SAMPLE].min()
    kept = complete[complete[:, Stage.HAPTIC_SAMPLE] >= first_ns + loop_stats.WARMUP_S * NS_PER_S]
    analysis = stack_run.analysis
    round_trip_ns = kept[:, Stage.FEEDBACK_RENDERED] - kept[:, Stage.HAPTIC_SAMPLE]
    assert_matches_reference(analysis.round_trip_us, round_trip_ns)
    transport_ns = kept[:, Stage.PLANT_RX] - kept[:, Stage.CONTROLLER_TX]
    assert_matches_reference(analysis.hops_us["controller_to_plant"], transport_ns)


def test_floor_chain_returns_every_payload_with_the_loop_stamps(floor_run):
    assert floor_run.sent == floor_run.received > 0
    loops = loop_stats.complete_loops(floor_run.paced_traces)
    assert loops.shape[0] == floor_run.received
    assert loop_stats.non_monotonic(loops) == 0
    # The relays do no work: nothing waits between the plant's arrival and its step.
    assert (loop_stats.hop_ns(loops, loop_stats.HOPS[3]) == 0).all()
    assert floor_run.back_to_back.count == 200
    assert [floor_run.sweep[size].count for size in (64, 65536)] == [20, 20]


def test_floor_relays_run_on_the_cpus_of_the_services_they_stand_in_for(floor_run, floor_dir):
    cpu = load_config(None, []).cpu
    # SCHED_FIFO as this user gets it (root, CAP_SYS_NICE) or is refused it (nobody).
    with fifo_scheduling(cpu.fifo_priority) as outcome:
        granted = outcome.startswith("granted")
    fifo = f"SCHED_FIFO priority {cpu.fifo_priority}"
    for relay, service in FLOOR_STAND_INS.items():
        wanted = sorted(set(cpu.for_service(service, "realtime")) & os.sched_getaffinity(0))
        log = (floor_dir / "logs" / f"{relay}.log").read_text()
        if wanted:
            assert f"pinned to CPU(s) {wanted}" in log, relay
        assert (f"{fifo}\n" in log) == granted, relay
        assert (f"{fifo} refused" in log) == (not granted), relay


def test_a_floor_bracketing_the_stack_counts_both_halves(floor_run, stack_run):
    # The second half, as if run 100 s later (unset stamps stay 0).
    traces = floor_run.paced_traces
    later_traces = np.where(traces > 0, traces + 100 * NS_PER_S, 0)
    later = dataclasses.replace(floor_run, paced_parts=(later_traces,))
    both = latency.bracket(floor_run, later)
    assert both.paced.round_trip_us.count == 2 * floor_run.paced.round_trip_us.count
    assert both.sent == 2 * floor_run.sent and both.received == 2 * floor_run.received
    assert both.paced_by_part == (floor_run.paced.round_trip_us,) * 2
    # Each half loses its own warm-up: the reference is each part's loops, concatenated.
    loops = loop_stats.after_warmup(loop_stats.complete_loops(floor_run.paced_traces))
    reference_ns = np.concatenate([loop_stats.hop_ns(loops, loop_stats.ROUND_TRIP)] * 2)
    assert_matches_reference(both.paced.round_trip_us, reference_ns)
    report, raw = latency.build_report(stack_run, stack_run, both, floor_run, None)
    assert report.floor_parts_us == (floor_run.paced.round_trip_us,) * 2
    assert raw["floor"].size == reference_ns.size
    assert any("before / after the stack" in line for line in report.conclusions)


def test_report_files(stack_run, floor_run, tmp_path):
    record, raw = latency.build_report(stack_run, stack_run, floor_run, floor_run, None)
    report = record.to_json()  # the JSON the command writes
    assert latency.LatencyReport.from_json(report) == record
    for key in ("round_trip_us", "floor_us", "floor_back_to_back_us", "shm_off_round_trip_us"):
        assert set(report[key]) >= {"count", "p50", "p90", "p99", "p999", "max"}
    assert set(report["hops"]) == {hop.name for hop in loop_stats.HOPS}
    assert set(report["lost"]) >= {"haptic", "command"} and "reordered" in report
    assert set(report["rate_hz"]) == {"plant", "haptic", "controller", "hmd"}
    assert [row["bytes"] for row in report["payload_sweep"]] == [64, 65536]
    # The p50 split: the transport hops' and the other stages' p50s, summed.
    (split,) = [line for line in report["conclusions"] if line.startswith("where the p50 goes")]
    hops = report["hops"]
    transport_us = sum(hops[h.name]["p50"] for h in loop_stats.HOPS if h.kind == "transport")
    work_us = sum(hops[h.name]["p50"] for h in loop_stats.HOPS if h.kind != "transport")
    assert f"transport hops {transport_us:.0f} us" in split
    assert f"compute and wait stages {work_us:.0f} us" in split
    assert f"controller_command {hops['controller_command']['p50']:.0f}" in split
    # The stack ran with its idle CPUs polling (the default) when this user may set up
    # the pollers' idle cgroup; without that privilege (an ordinary user) every CPU is
    # reported as halting, with its poller's reason, in the machine section and the
    # conclusions.
    machine, cpus = report["machine"], sorted(os.sched_getaffinity(0))
    if idle_cgroup_writable():
        assert machine["idle_poll_cpus"] == cpus and not machine["idle_poll_failed"]
    else:
        assert machine["idle_poll_cpus"] == [] and sorted(machine["idle_poll_failed"]) == cpus
        for cpu, why in machine["idle_poll_failed"].items():
            assert why.startswith(NOT_POLLED), why
            assert f"idle CPU {cpu} halts, its poller says: {why}" in report["conclusions"]
    latency.write_json(record, tmp_path / "out.json")
    latency.write_png(record, raw, tmp_path / "out.png")
    latency.log_to_rerun(record, raw, tmp_path / "out.rrd")
    assert json.loads((tmp_path / "out.json").read_text())["hops"] == report["hops"]
    assert (tmp_path / "out.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    verify = subprocess.run(
        [str(Path(sys.executable).parent / "rerun"), "rrd", "verify", str(tmp_path / "out.rrd")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert verify.returncode == 0, verify.stderr[-2000:]


@needs_realtime_stack
def test_across_sites_with_the_stack_times_its_loop_on_each_sites_clock(tmp_path):
    """``teleop latency --across-sites --with-stack``: the floor through the routers, then
    the realtime grasp split across two sites on this host (each under its own
    supervisord, routers over mutual TLS). The loop's round trip is on the operator
    site's clock; each way comes from the clocks' offset estimated from the loop's
    stamps, which on one host is zero within the uncertainty it claims."""
    out = tmp_path / "sites.json"
    done = subprocess.run(
        [sys.executable, "-m", "teleop.cli", "latency", "--across-sites", "--with-stack",
         "--rounds", "1", "--pings", "200", "--delays-ms", "", "--run-dir", str(tmp_path),
         "--json", str(out)],
        capture_output=True, text=True, stdin=subprocess.DEVNULL, timeout=600, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(out.read_text())
    stack = report["stack"]
    print("the stack across two sites:", {k: v for k, v in stack.items() if "_us" not in k})
    assert stack["success"] and stack["loops"] > 1000
    assert abs(stack["offset_s"]) * 1e6 <= stack["offset_uncertainty_us"]
    floor_ms = report["rounds"][0]["routers"]["p50_ms"]
    assert stack["round_trip_us"]["p50"] / 1e3 > floor_ms  # the loop rides on the floor
    for way in ("operator_to_robot_us", "robot_to_operator_us"):
        assert stack[way]["p50"] > 0
    assert "| round trip (operator site's clock) |" in done.stdout
    assert "clocks' offset (robot minus operator site)" in done.stdout
