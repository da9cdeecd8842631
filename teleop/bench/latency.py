"""End-to-end latency of the bilateral loop, hop by hop, against the transport's floor.

``teleop latency`` (:func:`measure`) runs, in one command so that every figure is taken
on the same machine in the same minutes:

1. the transport floor (:mod:`teleop.bench.relay`): a bare relay chain of Python processes
   with the loop's four legs, paced at the device rate, then back to back, then a
   payload sweep, with shared memory on;
2. the realtime teleoperation stack under supervisord (every service and the recorder,
   the scripted operator moving: ``deploy/scenarios/latency.toml``) for ``duration_s``;
3. the same stack with shared memory off (TCP loopback), then the floor chain and the
   sweep with shared memory off;
4. the stack with the loop's old timing (the plant applies the newest command at its own
   1 kHz tick, the haptic device renders at its next step), to show what the event-driven
   loop gains.

Every figure comes from raw stamps (``Stage``, monotonic ns): the haptic service keeps
the trace of every rendered feedback (``haptic.trace.npy``), the floor origin the trace
of every returned payload. A hop is the difference of two stamps of one trace; the
round trip is ``FEEDBACK_RENDERED - HAPTIC_SAMPLE``: handle sampled -> controller ->
plant (command in a physics step) -> plant state -> controller -> force set on the
handle's motors (:mod:`teleop.bench.loop_stats`).

The figures are typed records (the loop's, :mod:`teleop.bench.loop_stats`; the services'
counters, :mod:`teleop.bench.run_counts`; :class:`LatencyReport`); JSON is written and
read only by their ``to_json``/``from_json``. This module runs the measurements and
writes the report.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from teleop.bench.loop_stats import (
    HOPS,
    PERCENTILES,
    ROUND_TRIP,
    ChainAccounting,
    FloorRatio,
    LatencyStats,
    LoopAnalysis,
    after_warmup,
    analyse,
    chain_accounting,
    complete_loops,
    hop_ns,
    hops_from_json,
    hops_json,
    overhead,
    stats_us,
    warm_loops,
)
from teleop.bench.relay import RELAYS, FloorOrigin, floor_provider, unmeasurable_reason
from teleop.bench.run_counts import (
    DeadlineMisses,
    HapticMisses,
    LostCounts,
    PlantMisses,
    ReorderedCounts,
    ServiceRates,
    ShedCounts,
    cpu_share,
    deadline_misses,
    service_rates,
    shed_counters,
    stream_counters,
)
from teleop.bus.messages import EYE_VIEW, PLANT_STATE
from teleop.bus.service import fifo_scheduling
from teleop.bus.session import close_session, open_session, wait_alive
from teleop.bus.topics import Topics
from teleop.core.clock import NS_PER_S, NS_PER_US
from teleop.core.config import Config, EyeViewConfig, load_config
from teleop.core.net import LoopbackPorts
from teleop.core.rundir import HAPTIC_SAMPLES_FILE, HAPTIC_TRACE_FILE, SHED_FILE_SUFFIX
from teleop.core.summary import RunSummary
from teleop.run.stack import (
    ALIVE_TIMEOUT_S,
    SERVICE_ENVIRONMENT,
    idle_poll_cpus,
    idle_poll_programs,
    loopback_endpoint,
    peer_mesh,
    run_on_services,
    service_command,
)
from teleop.run.supervise import Program, Stack

# Samples of the first second of a run are start-up (imports warming, links opening,
# One eye-view frame at the default size (record + RGB pixels, see EyeViewConfig).
EYE_VIEW_FRAME_BYTES = EYE_VIEW.frame_bytes(EyeViewConfig().width_px, EyeViewConfig().height_px)
# The payload sweep, bytes: small record, a page, big records, 1 MiB, one eye-view frame.
SWEEP_SIZES_BYTES = (64, 4096, 65536, 1 << 20, EYE_VIEW_FRAME_BYTES)
# Round trips per payload size (back to back) and the time allowed for one size (s).
DEFAULT_SWEEP_COUNT = 200
SWEEP_BUDGET_S = 10.0
# Back-to-back floor: round trips, and how long one may take before it counts as lost (s).
DEFAULT_BACK_TO_BACK_COUNT = 2000
RETURN_TIMEOUT_S = 1.0
# Floor payloads thrown away before measuring (links and pools warm up).
FLOOR_WARMUP_COUNT = 50
# Baselines (floor, SHM-off stack, old timing) last at most this long by default (s).
DEFAULT_BASELINE_MAX_S = 20.0
# The scenario that keeps the operator moving for the whole run.
LATENCY_SCENARIO_FILE = "latency.toml"
# Histogram bins of the figure and the recording (log-spaced, 10 us .. 1 s).
FIGURE_BINS_US = np.logspace(1, 6, 151)
# The PNG's histograms: bins per decade, and the factor the axis extends past the data.
FIGURE_BINS_PER_DECADE = 30
FIGURE_MARGIN = 1.2


ProgressFn = Callable[[str], None]


# -- running the stack --------------------------------------------------------------------


@dataclass(frozen=True)
class StackRun:
    """One run of the realtime stack: its summary, raw stamps and their analysis."""

    label: str
    summary: RunSummary
    traces: np.ndarray
    samples: np.ndarray
    shed_ns: np.ndarray  # HAPTIC_SAMPLE stamps of the samples services shed on purpose
    analysis: LoopAnalysis


def stack_overrides(duration_s: float, extra: Sequence[str] = ()) -> list[str]:
    """Overrides of a latency run of the stack: realtime teleoperation, moving operator."""
    return [
        *extra,
        'run.scenario="grasp"',
        'run.mode="realtime"',
        f"run.duration_s={duration_s}",
        f'operator.scenario_file="{LATENCY_SCENARIO_FILE}"',
    ]


SHM_OFF = ("bus.shm=false", 'bus.zenoh_config="local-noshm.json5"')
OLD_TIMING = ("plant.apply_on_arrival=false", "haptic.render_on_arrival=false")


def run_stack(
    label: str,
    config_file: Path | None,
    overrides: Sequence[str],
    duration_s: float,
    run_dir: Path,
) -> StackRun:
    """Run the realtime stack for ``duration_s`` in ``run_dir``; read its raw stamps."""
    all_overrides = stack_overrides(duration_s, overrides)
    config = load_config(config_file, all_overrides)
    for stale in (
        run_dir / HAPTIC_TRACE_FILE,
        run_dir / HAPTIC_SAMPLES_FILE,
        *run_dir.glob(f"*{SHED_FILE_SUFFIX}"),
    ):
        stale.unlink(missing_ok=True)
    summary = run_on_services(config, config_file, all_overrides, run_dir, progress=None)
    traces = np.load(run_dir / HAPTIC_TRACE_FILE)
    samples = np.load(run_dir / HAPTIC_SAMPLES_FILE)
    shed = [np.load(path).reshape(-1) for path in sorted(run_dir.glob(f"*{SHED_FILE_SUFFIX}"))]
    shed_ns = np.concatenate([np.zeros(0, np.int64), *shed])
    return StackRun(label, RunSummary.from_json(summary), traces, samples, shed_ns, analyse(traces))


# -- running the floor --------------------------------------------------------------------


@dataclass(frozen=True)
class FloorRun:
    """The relay chain's measurements of one bus setting (SHM on or off).

    ``paced_parts``: the raw traces of each paced run (one, or two when the floor brackets
    the stack: :func:`bracket`); ``paced``: their analysis, each part after its own
    warm-up.
    """

    label: str
    paced: LoopAnalysis
    back_to_back: LatencyStats
    sweep: Mapping[int, LatencyStats]  # by payload size (bytes)
    paced_parts: tuple[np.ndarray, ...]
    sent: int
    received: int

    @property
    def paced_traces(self) -> np.ndarray:
        """The raw traces of every paced part, one after the other."""
        return np.concatenate(self.paced_parts)

    @property
    def paced_by_part(self) -> tuple[LatencyStats, ...]:
        """Each paced part's round trip on its own (us)."""
        return tuple(analyse(part).round_trip_us for part in self.paced_parts)


def bracket(before: FloorRun, after: FloorRun) -> FloorRun:
    """One paced floor from the runs before and after the stack (the sweep and the
    back-to-back figures are ``before``'s): on a host whose speed drifts over minutes,
    the floor then spans the same minutes as the stack it is compared with."""
    parts = (*before.paced_parts, *after.paced_parts)
    return replace(
        before,
        paced=analyse(*parts),
        paced_parts=parts,
        sent=before.sent + after.sent,
        received=before.received + after.received,
    )


def run_floor(
    label: str,
    config_file: Path | None,
    overrides: Sequence[str],
    run_dir: Path,
    *,
    paced_s: float,
    back_to_back_count: int,
    sweep_sizes: Sequence[int],
    sweep_count: int,
) -> FloorRun:
    """The bare relay chain under supervisord: paced, back to back, then the sweep.

    Each relay runs on the CPUs and under the scheduling of the service whose place it
    takes (:data:`teleop.bench.relay.FLOOR_STAND_INS`). Every process of the chain holds
    an SHM pool of the size the origin's came out with (within the locked-memory limit);
    a sweep size the pools cannot carry is not sent, and its entry says why
    (``not_measured``).
    """
    run_dir = run_dir.absolute()
    run_dir.mkdir(parents=True, exist_ok=True)
    config = load_config(config_file, overrides)
    ports = LoopbackPorts()  # the run's ports, held until it ends (closed by the with)
    endpoint = loopback_endpoint(ports, tls=False)
    relay_overrides = [*overrides, f'bus.endpoint="{endpoint}"']
    bus = replace(config.bus, endpoint=endpoint, gossip=False)  # the mesh's listener
    topics = Topics(config.robot.robot_id)
    period_ns = round(config.tick_s * NS_PER_S)
    payload_bytes = PLANT_STATE.size  # the loop's largest record
    # The origin plays the haptic service: same scheduling (its Zenoh threads too).
    fifo_priority = config.cpu.fifo_priority_for("haptic", config.run.mode)
    with ports, fifo_scheduling(fifo_priority):
        session = open_session(bus, listen=True)
        origin: FloorOrigin | None = None
        try:
            provider, pool = floor_provider(bus)
            if pool is not None and pool.pool_bytes:
                relay_overrides.append(f"bus.shm_pool_bytes={pool.pool_bytes}")
            origin = FloorOrigin(session, topics, provider)
            programs = _floor_programs(config, config_file, relay_overrides, run_dir, ports)
            with Stack(run_dir, programs):
                wait_alive(session, topics, [r.name for r in RELAYS], ALIVE_TIMEOUT_S)
                seq = origin.back_to_back(
                    FLOOR_WARMUP_COUNT, payload_bytes, 1, RETURN_TIMEOUT_S, SWEEP_BUDGET_S
                )
                origin.reset()
                seq = origin.paced(period_ns, paced_s, payload_bytes, seq)
                origin.wait_returned(seq - 1, RETURN_TIMEOUT_S)
                paced_traces = origin.trace_log.rows.copy()
                sent, received = origin.sent, origin.received
                origin.reset()
                seq = origin.back_to_back(
                    back_to_back_count, payload_bytes, seq, RETURN_TIMEOUT_S, SWEEP_BUDGET_S
                )
                b2b_traces = origin.trace_log.rows.copy()
                sweep: dict[int, LatencyStats] = {}
                for size in sweep_sizes:
                    why = unmeasurable_reason(size, bus, pool)
                    if why:
                        sweep[size] = LatencyStats(0, not_measured=why)
                        continue
                    origin.reset()
                    seq = origin.back_to_back(
                        FLOOR_WARMUP_COUNT // 5, size, seq, RETURN_TIMEOUT_S, SWEEP_BUDGET_S
                    )
                    origin.reset()
                    seq = origin.back_to_back(
                        sweep_count, size, seq, RETURN_TIMEOUT_S, SWEEP_BUDGET_S
                    )
                    loops = complete_loops(origin.trace_log.rows)
                    sweep[size] = stats_us(hop_ns(loops, ROUND_TRIP))
        finally:
            if origin is not None:
                origin.close()
            close_session(session)
    back_to_back = stats_us(hop_ns(complete_loops(b2b_traces), ROUND_TRIP))
    return FloorRun(
        label, analyse(paced_traces), back_to_back, sweep, (paced_traces,), sent, received
    )


def _floor_programs(
    config: Config,
    config_file: Path | None,
    relay_overrides: Sequence[str],
    run_dir: Path,
    ports: LoopbackPorts,
) -> list[Program]:
    """The floor's supervisord programs: the relays, linked by an explicit mesh as the
    stack's services are (their ports taken from ``ports``), and the idle pollers the
    stack runs."""
    mesh = peer_mesh([relay.name for relay in RELAYS], None, ports)
    programs = []
    for relay in RELAYS:
        command = service_command(
            relay.name,
            run_dir,
            config_file,
            [*relay_overrides, *mesh[relay.name]],
            module=("teleop.bench.relay", relay.name),
        )
        programs.append(
            Program(name=relay.name, command=command, environment=dict(SERVICE_ENVIRONMENT))
        )
    return programs + idle_poll_programs(idle_poll_cpus(config), run_dir)


# -- the report ---------------------------------------------------------------------------


def _loadavg() -> tuple[float, ...]:
    return tuple(round(x, 2) for x in os.getloadavg())


@dataclass(frozen=True)
class SweepRow:
    """One payload size's round trip (4 legs, back to back) with SHM and over TCP (us);
    ``tcp_us`` None: the TCP floor did not send this size."""

    size_bytes: int
    shm_us: LatencyStats
    tcp_us: LatencyStats | None
    tcp_over_shm_p50: float | None
    shm_faster: bool

    def to_json(self) -> dict[str, Any]:
        return {
            "bytes": self.size_bytes,
            "shm_us": self.shm_us.to_json(),
            "tcp_us": {} if self.tcp_us is None else self.tcp_us.to_json(),
            "tcp_over_shm_p50": self.tcp_over_shm_p50,
            "shm_faster": self.shm_faster,
        }

    @classmethod
    def from_json(cls, content: Mapping[str, Any]) -> SweepRow:
        tcp = content["tcp_us"]
        return cls(
            size_bytes=content["bytes"],
            shm_us=LatencyStats.from_json(content["shm_us"]),
            tcp_us=LatencyStats.from_json(tcp) if tcp else None,
            tcp_over_shm_p50=content["tcp_over_shm_p50"],
            shm_faster=content["shm_faster"],
        )


def sweep_table(shm: FloorRun, tcp: FloorRun) -> tuple[SweepRow, ...]:
    """Per payload size: round trip (4 legs, back to back) with SHM and over TCP."""
    rows = []
    for size, on in shm.sweep.items():
        off = tcp.sweep.get(size)
        ratio = None
        if on.p50_us and off is not None and off.p50_us:
            ratio = off.p50_us / on.p50_us
        rows.append(SweepRow(size, on, off, ratio, ratio is not None and ratio > 1.0))
    return tuple(rows)


@dataclass(frozen=True)
class Machine:
    """The host of a report: CPUs, load averages (1, 5, 15 min) before and after (before:
    None outside :func:`measure`), the CPUs kept polling and those whose poller failed
    (CPU -> its status), as the stack's run summary gives them."""

    cpus: int | None
    loadavg_after: tuple[float, ...]
    idle_poll_cpus: tuple[int, ...] | None
    idle_poll_failed: Mapping[str, str] | None
    loadavg_before: tuple[float, ...] | None = None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "cpus": self.cpus,
            "loadavg_after": list(self.loadavg_after),
            "idle_poll_cpus": None if self.idle_poll_cpus is None else list(self.idle_poll_cpus),
            "idle_poll_failed": None
            if self.idle_poll_failed is None
            else dict(self.idle_poll_failed),
        }
        if self.loadavg_before is not None:
            out["loadavg_before"] = list(self.loadavg_before)
        return out

    @classmethod
    def from_json(cls, content: Mapping[str, Any]) -> Machine:
        polled, before = content.get("idle_poll_cpus"), content.get("loadavg_before")
        return cls(
            cpus=content.get("cpus"),
            loadavg_after=tuple(content.get("loadavg_after", ())),
            idle_poll_cpus=None if polled is None else tuple(polled),
            idle_poll_failed=content.get("idle_poll_failed"),
            loadavg_before=None if before is None else tuple(before),
        )


@dataclass(frozen=True)
class LatencyReport:
    """The ``teleop latency`` report: the stack's loop against the transport floor (SHM on
    and off), the services' counters, the payload sweep and the findings in words; the
    run's own fields (``duration_s`` to ``rrd``) are None outside :func:`measure` and the
    command. Written and read as JSON by :meth:`to_json` and :meth:`from_json` only."""

    round_trip_us: LatencyStats
    hops_us: Mapping[str, LatencyStats]
    floor_us: LatencyStats
    floor_parts_us: tuple[LatencyStats, ...]
    floor_hops_us: Mapping[str, LatencyStats]
    floor_back_to_back_us: LatencyStats
    floor_sent: int
    floor_received: int
    shm_off_round_trip_us: LatencyStats
    shm_off_hops_us: Mapping[str, LatencyStats]
    floor_shm_off_us: LatencyStats
    floor_shm_off_back_to_back_us: LatencyStats
    overhead: Mapping[str, FloorRatio]  # ``round_trip`` and each hop
    lost: LostCounts
    reordered: ReorderedCounts
    shed: ShedCounts
    chain: ChainAccounting
    non_monotonic: int
    rates: ServiceRates
    cpu_share: Mapping[str, float | None]
    deadline_misses: DeadlineMisses
    payload_sweep: tuple[SweepRow, ...]
    dropped_messages: int | None
    machine: Machine
    old_timing_round_trip_us: LatencyStats | None = None
    old_timing_hops_us: Mapping[str, LatencyStats] | None = None
    conclusions: tuple[str, ...] = ()
    duration_s: float | None = None
    baseline_duration_s: float | None = None
    date_utc: str | None = None
    wall_s: float | None = None
    run_dir: str | None = None
    rrd: str | None = None  # the Rerun recording of the figures

    def to_json(self) -> dict[str, Any]:
        """The JSON object the command writes (the run's fields only where set)."""
        out: dict[str, Any] = {
            "round_trip_us": self.round_trip_us.to_json(),
            "hops": hops_json(self.hops_us),
            "floor_us": self.floor_us.to_json(),
            "floor_parts_us": [part.to_json() for part in self.floor_parts_us],
            "floor_hops": hops_json(self.floor_hops_us),
            "floor_back_to_back_us": self.floor_back_to_back_us.to_json(),
            "floor_sent": self.floor_sent,
            "floor_received": self.floor_received,
            "shm_off_round_trip_us": self.shm_off_round_trip_us.to_json(),
            "shm_off_hops": hops_json(self.shm_off_hops_us),
            "floor_shm_off_us": self.floor_shm_off_us.to_json(),
            "floor_shm_off_back_to_back_us": self.floor_shm_off_back_to_back_us.to_json(),
            "overhead": {name: ratio.to_json() for name, ratio in self.overhead.items()},
            "lost": self.lost.to_json(),
            "reordered": self.reordered.to_json(),
            "shed": self.shed.to_json(),
            "chain": self.chain.to_json(),
            "non_monotonic": self.non_monotonic,
            "rate_hz": self.rates.to_json(),
            "cpu_share": dict(self.cpu_share),
            "deadline_misses": self.deadline_misses.to_json(),
            "payload_sweep": [row.to_json() for row in self.payload_sweep],
            "dropped_messages": self.dropped_messages,
            "machine": self.machine.to_json(),
        }
        if self.old_timing_round_trip_us is not None:
            out["old_timing_round_trip_us"] = self.old_timing_round_trip_us.to_json()
        if self.old_timing_hops_us is not None:
            out["old_timing_hops"] = hops_json(self.old_timing_hops_us)
        out["conclusions"] = list(self.conclusions)
        for name in ("duration_s", "baseline_duration_s", "date_utc", "wall_s", "run_dir", "rrd"):
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        return out

    @classmethod
    def from_json(cls, content: Mapping[str, Any]) -> LatencyReport:
        """The record of a report as :meth:`to_json` writes it."""
        old, old_hops = content.get("old_timing_round_trip_us"), content.get("old_timing_hops")
        misses = content["deadline_misses"]
        return cls(
            round_trip_us=LatencyStats.from_json(content["round_trip_us"]),
            hops_us=hops_from_json(content["hops"]),
            floor_us=LatencyStats.from_json(content["floor_us"]),
            floor_parts_us=tuple(LatencyStats.from_json(p) for p in content["floor_parts_us"]),
            floor_hops_us=hops_from_json(content["floor_hops"]),
            floor_back_to_back_us=LatencyStats.from_json(content["floor_back_to_back_us"]),
            floor_sent=content["floor_sent"],
            floor_received=content["floor_received"],
            shm_off_round_trip_us=LatencyStats.from_json(content["shm_off_round_trip_us"]),
            shm_off_hops_us=hops_from_json(content["shm_off_hops"]),
            floor_shm_off_us=LatencyStats.from_json(content["floor_shm_off_us"]),
            floor_shm_off_back_to_back_us=LatencyStats.from_json(
                content["floor_shm_off_back_to_back_us"]
            ),
            overhead={name: FloorRatio(**r) for name, r in content["overhead"].items()},
            lost=LostCounts(**content["lost"]),
            reordered=ReorderedCounts(**content["reordered"]),
            shed=ShedCounts(**content["shed"]),
            chain=ChainAccounting(**content["chain"]),
            non_monotonic=content["non_monotonic"],
            rates=ServiceRates(**{f"{k}_hz": v for k, v in content["rate_hz"].items()}),
            cpu_share=dict(content["cpu_share"]),
            deadline_misses=DeadlineMisses(
                PlantMisses(**misses["plant"]), HapticMisses(**misses["haptic"])
            ),
            payload_sweep=tuple(SweepRow.from_json(row) for row in content["payload_sweep"]),
            dropped_messages=content["dropped_messages"],
            machine=Machine.from_json(content["machine"]),
            old_timing_round_trip_us=None if old is None else LatencyStats.from_json(old),
            old_timing_hops_us=None if old_hops is None else hops_from_json(old_hops),
            conclusions=tuple(content.get("conclusions", ())),
            duration_s=content.get("duration_s"),
            baseline_duration_s=content.get("baseline_duration_s"),
            date_utc=content.get("date_utc"),
            wall_s=content.get("wall_s"),
            run_dir=content.get("run_dir"),
            rrd=content.get("rrd"),
        )


def conclusions(report: LatencyReport) -> list[str]:
    """The report's findings in words (what the numbers say, no judgement beyond them)."""
    out = []
    rt, floor = report.round_trip_us, report.floor_us
    ratio = report.overhead["round_trip"]
    if rt.p50_us is not None and floor.p50_us is not None:
        out.append(
            f"round trip p50 {rt.p50_us:.0f} us, p99 {rt.p99_us:.0f} us; paced floor p50 "
            f"{floor.p50_us:.0f} us, p99 {floor.p99_us:.0f} us (p99 ratio "
            f"{_fmt(ratio.p99_ratio)}); back-to-back floor p99 "
            f"{_fmt(report.floor_back_to_back_us.p99_us)} us"
        )
    parts = report.floor_parts_us
    if len(parts) > 1:
        out.append(
            "paced floor before / after the stack: p50 "
            + " / ".join(_fmt_us(part.p50_us) for part in parts)
            + " us, p99 "
            + " / ".join(_fmt_us(part.p99_us) for part in parts)
            + " us"
        )
    out += where_the_time_goes(report)
    old = report.old_timing_round_trip_us
    if old is not None and old.p50_us is not None and rt.p50_us is not None:
        out.append(
            f"old timing (plant tick + device step) round trip p50 {old.p50_us:.0f} us, "
            f"p99 {old.p99_us:.0f} us: the event-driven loop's p50 is "
            f"{rt.p50_us / old.p50_us:.2f}x the old timing's"
        )
    for row in report.payload_sweep:
        if row.size_bytes < 1 << 20 and row.size_bytes != EYE_VIEW_FRAME_BYTES:
            continue  # the sizes the issue asks about: 1 MiB and one eye-view frame
        what = f"{row.size_bytes} B" + (
            " (eye-view frame)" if row.size_bytes == EYE_VIEW_FRAME_BYTES else ""
        )
        shm_p50 = row.shm_us.p50_us
        tcp_p50 = None if row.tcp_us is None else row.tcp_us.p50_us
        if row.tcp_over_shm_p50 is not None:
            verdict = "faster" if row.shm_faster else "NOT faster"
            out.append(
                f"{what}: SHM is {verdict} than TCP loopback (p50 {shm_p50:.0f} vs "
                f"{tcp_p50:.0f} us, {row.tcp_over_shm_p50:.2f}x)"
            )
        elif row.shm_us.not_measured:
            out.append(f"{what}: not measured over SHM ({row.shm_us.not_measured})")
        else:  # a side where no payload of this size came back at all
            missing = [side for side, p50 in (("SHM", shm_p50), ("TCP", tcp_p50)) if p50 is None]
            out.append(f"{what}: no payload came back over {' or '.join(missing)}")
    polled = report.machine.idle_poll_cpus
    failed = report.machine.idle_poll_failed or {}
    if polled:
        out.append(
            f"idle CPUs polled (cpu.idle_poll): {', '.join(map(str, polled))}; the services' "
            "CPU shares leave the pollers out"
        )
    elif not failed:
        out.append("idle CPUs halt (cpu.idle_poll off)")
    out += [f"idle CPU {cpu} halts, its poller says: {why}" for cpu, why in failed.items()]
    lost = report.lost
    out.append(
        f"lost: haptic {lost.haptic}, command {lost.command}, feedback "
        f"{lost.feedback}; reordered: {report.reordered.total}; samples that never came back: "
        f"{report.chain.missing} of {report.chain.samples} (shed while behind: "
        f"{report.shed.total})"
    )
    return out


def where_the_time_goes(report: LatencyReport) -> list[str]:
    """The round trip's p50 split into what the transport floor accounts for and what the
    services add: the transport hops' ratios to the floor's, the compute and wait
    stages' p50s (none of which the bare relay chain has)."""
    hops, ratios = report.hops_us, report.overhead
    if any(h.name not in hops or hops[h.name].p50_us is None for h in HOPS):
        return []
    p50_us = {h.name: hops[h.name].p50_us or 0.0 for h in HOPS}
    transport = [h.name for h in HOPS if h.kind == "transport"]
    work = [h for h in HOPS if h.kind != "transport"]
    transport_ratios = [ratios[name].p50_ratio for name in transport]
    spread = [r for r in transport_ratios if r is not None]
    work_us = sum(p50_us[h.name] for h in work)
    line = f"where the p50 goes: transport hops {sum(p50_us[n] for n in transport):.0f} us"
    if spread:
        line += f" ({min(spread):.2f}-{max(spread):.2f}x the floor's)"
    line += (
        f", compute and wait stages {work_us:.0f} us ("
        + ", ".join(f"{h.name} {p50_us[h.name]:.0f}" for h in work)
        + ")"
    )
    return [line]


def _fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f}"


def _fmt_us(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.0f}"


def measure(
    config_file: Path | None,
    overrides: Sequence[str],
    run_dir: Path,
    duration_s: float,
    *,
    baseline_s: float | None = None,
    sweep_sizes: Sequence[int] = SWEEP_SIZES_BYTES,
    sweep_count: int = DEFAULT_SWEEP_COUNT,
    back_to_back_count: int = DEFAULT_BACK_TO_BACK_COUNT,
    old_timing: bool = True,
    progress: ProgressFn | None = None,
) -> tuple[LatencyReport, dict[str, np.ndarray]]:
    """Run every measurement; return (report, raw round-trip samples by series, ns)."""
    run_dir = Path(run_dir).absolute()
    base_s = baseline_s if baseline_s is not None else min(duration_s, DEFAULT_BASELINE_MAX_S)
    say = progress or (lambda text: None)
    load_before = _loadavg()
    started = time.monotonic()
    floor_kwargs = {
        "paced_s": base_s,
        "back_to_back_count": back_to_back_count,
        "sweep_sizes": sweep_sizes,
        "sweep_count": sweep_count,
    }
    # The paced floor brackets the stack, half before and half after it: this host's
    # wake-up costs drift over minutes, and the p99 ratio compares like with like only
    # when the floor spans the stack's minutes (the paced floor's p99 alone varies
    # several-fold between consecutive runs).
    half_s = base_s / 2
    say(f"floor, SHM on: relay chain paced {half_s:g} s, back to back, payload sweep")
    before = run_floor(
        "floor_shm", config_file, overrides, run_dir / "floor-shm",
        **{**floor_kwargs, "paced_s": half_s},
    )  # fmt: skip
    say(f"stack, SHM on: {duration_s:g} s of realtime teleoperation")
    stack = run_stack("stack", config_file, overrides, duration_s, run_dir / "stack-shm")
    say(f"floor, SHM on: relay chain paced {half_s:g} s after the stack")
    after = run_floor(
        "floor_shm_after", config_file, overrides, run_dir / "floor-shm-after",
        paced_s=half_s, back_to_back_count=0, sweep_sizes=(), sweep_count=0,
    )  # fmt: skip
    floor = bracket(before, after)
    say(f"stack, SHM off: {base_s:g} s")
    stack_tcp = run_stack(
        "stack_shm_off", config_file, [*overrides, *SHM_OFF], base_s, run_dir / "stack-tcp"
    )
    say("floor, SHM off: paced, back to back, payload sweep")
    floor_tcp = run_floor(
        "floor_tcp", config_file, [*overrides, *SHM_OFF], run_dir / "floor-tcp", **floor_kwargs
    )
    old = None
    if old_timing:
        say(f"stack, old timing (plant tick, device step): {base_s:g} s")
        old = run_stack(
            "old_timing", config_file, [*overrides, *OLD_TIMING], base_s, run_dir / "stack-old"
        )
    report, raw = build_report(stack, stack_tcp, floor, floor_tcp, old)
    report = replace(
        report,
        duration_s=duration_s,
        baseline_duration_s=base_s,
        date_utc=datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
        machine=replace(report.machine, loadavg_before=load_before),
        wall_s=time.monotonic() - started,
        run_dir=str(run_dir),
    )
    return report, raw


def build_report(
    stack: StackRun,
    stack_tcp: StackRun,
    floor: FloorRun,
    floor_tcp: FloorRun,
    old: StackRun | None,
) -> tuple[LatencyReport, dict[str, np.ndarray]]:
    """The report and the raw round trips (ns) by series, from the runs."""
    lost, reordered = stream_counters(stack.summary)
    report = LatencyReport(
        round_trip_us=stack.analysis.round_trip_us,
        hops_us=stack.analysis.hops_us,
        floor_us=floor.paced.round_trip_us,
        floor_parts_us=floor.paced_by_part,
        floor_hops_us=floor.paced.hops_us,
        floor_back_to_back_us=floor.back_to_back,
        floor_sent=floor.sent,
        floor_received=floor.received,
        shm_off_round_trip_us=stack_tcp.analysis.round_trip_us,
        shm_off_hops_us=stack_tcp.analysis.hops_us,
        floor_shm_off_us=floor_tcp.paced.round_trip_us,
        floor_shm_off_back_to_back_us=floor_tcp.back_to_back,
        overhead=overhead(stack.analysis, floor.paced),
        lost=lost,
        reordered=reordered,
        shed=shed_counters(stack.summary),
        chain=chain_accounting(stack.samples, stack.traces, stack.shed_ns),
        non_monotonic=stack.analysis.non_monotonic,
        rates=service_rates(stack.summary),
        cpu_share=cpu_share(stack.summary),
        deadline_misses=deadline_misses(stack.summary),
        payload_sweep=sweep_table(floor, floor_tcp),
        dropped_messages=stack.summary.dropped_messages,
        machine=Machine(
            cpus=os.cpu_count(),
            loadavg_after=_loadavg(),
            idle_poll_cpus=stack.summary.idle_poll_cpus,
            idle_poll_failed=stack.summary.idle_poll_failed,
        ),
        old_timing_round_trip_us=None if old is None else old.analysis.round_trip_us,
        old_timing_hops_us=None if old is None else old.analysis.hops_us,
    )
    report = replace(report, conclusions=tuple(conclusions(report)))
    raw = {
        "stack": hop_ns(after_warmup(complete_loops(stack.traces)), ROUND_TRIP),
        "floor": hop_ns(warm_loops(*floor.paced_parts), ROUND_TRIP),
        "stack_shm_off": hop_ns(after_warmup(complete_loops(stack_tcp.traces)), ROUND_TRIP),
    }
    if old is not None:
        raw["old_timing"] = hop_ns(after_warmup(complete_loops(old.traces)), ROUND_TRIP)
    return report, raw


# -- output -------------------------------------------------------------------------------


def write_json(report: LatencyReport, path: Path) -> None:
    """The report as JSON at ``path``."""
    content = report.to_json()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(content, indent=2) + "\n")


def fitted_bins_us(raw: Mapping[str, np.ndarray]) -> np.ndarray:
    """Log-spaced histogram bins (us) from just below the smallest to just above the
    largest sample of ``raw`` (ns arrays), FIGURE_BINS_PER_DECADE per decade: the axis
    fits the data instead of FIGURE_BINS_US's fixed 10 us - 1 s."""
    values = [v for v in raw.values() if v.size]
    if not values:
        return FIGURE_BINS_US
    low_us = min(float(v.min()) for v in values) / NS_PER_US / FIGURE_MARGIN
    high_us = max(float(v.max()) for v in values) / NS_PER_US * FIGURE_MARGIN
    low_us = max(low_us, 1e-3)
    decades = max(np.log10(high_us / low_us), 0.1)
    return np.logspace(
        np.log10(low_us), np.log10(high_us), round(decades * FIGURE_BINS_PER_DECADE) + 1
    )


def write_png(report: LatencyReport, raw: Mapping[str, np.ndarray], path: Path) -> None:
    """Round-trip histograms (stack and baselines), per-hop p50/p99 against the floor,
    and the payload sweep, in one figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(18, 5.5))
    ax = axes[0]
    bins_us = fitted_bins_us(raw)
    for name, values_ns in raw.items():
        if values_ns.size:
            ax.hist(values_ns / NS_PER_US, bins=bins_us, histtype="step", label=name)
    ax.set_xscale("log")
    ax.set_xlim(bins_us[0], bins_us[-1])
    ax.set_yscale("log")
    ax.set_xlabel("round trip, haptic sample -> force rendered (us)")
    ax.set_ylabel("samples")
    ax.set_title("Round trip histograms")
    ax.legend()

    ax = axes[1]
    names = [hop.name for hop in HOPS]
    x = np.arange(len(names))
    width = 0.2
    for i, (series, key) in enumerate(
        (
            (report.hops_us, "p50"),
            (report.floor_hops_us, "p50"),
            (report.hops_us, "p99"),
            (report.floor_hops_us, "p99"),
        )  # fmt: skip
    ):
        values = [series[n].percentile_us(key) or 0.0 for n in names]
        label = ("stack " if series is report.hops_us else "floor ") + key
        ax.bar(x + (i - 1.5) * width, values, width, label=label)
    ax.set_yscale("symlog", linthresh=10)
    ax.set_xticks(x, names, rotation=45, ha="right")
    ax.set_ylabel("us")
    ax.set_title("Per hop: stack vs transport floor", pad=28)
    # Above the bars, not over them.
    ax.legend(loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=4, fontsize=8, frameon=False)

    ax = axes[2]
    sweep = report.payload_sweep
    if sweep:
        sizes = [row.size_bytes for row in sweep]
        order = np.argsort(sizes)
        for side, label in (("shm", "SHM"), ("tcp", "TCP loopback")):
            figures = [sweep[i].shm_us if side == "shm" else sweep[i].tcp_us for i in order]
            p50 = [(f and f.p50_us) or math.nan for f in figures]
            p99 = [(f and f.p99_us) or math.nan for f in figures]
            xs = [sizes[i] for i in order]
            line = ax.plot(xs, p50, marker="o", label=f"{label} p50")[0]
            ax.plot(
                xs, p99, marker="x", linestyle="--", color=line.get_color(), label=f"{label} p99"
            )
        ax.axvline(EYE_VIEW_FRAME_BYTES, color="grey", linewidth=0.8)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("payload (bytes); grey: eye-view frame")
        ax.set_ylabel("round trip, 4 legs, back to back (us)")
        ax.set_title("Payload sweep")
        ax.legend()
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def log_to_rerun(report: LatencyReport, raw: Mapping[str, np.ndarray], path: Path) -> None:
    """The same figures into a Rerun recording (application ``zenoh-teleop``): one bar
    chart per round-trip histogram and the percentiles of every hop, stack and floor."""
    import rerun as rr

    from teleop.viz.entities import APPLICATION_ID

    rec = rr.RecordingStream(APPLICATION_ID)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rec.save(path)
    for name, values_ns in raw.items():
        counts, _ = np.histogram(values_ns / NS_PER_US, bins=FIGURE_BINS_US)
        rec.log(f"latency/histogram/{name}", rr.BarChart(counts), static=True)
    series = {"stack": report.hops_us, "floor": report.floor_hops_us}
    for origin, hops in series.items():
        for hop_name, figures in hops.items():
            for key in PERCENTILES:
                value_us = figures.percentile_us(key)
                if value_us is not None:
                    rec.log(
                        f"latency/{origin}/{hop_name}/{key}_us",
                        rr.Scalars(value_us),
                        static=True,
                    )
    rec.log(
        "latency/report",
        rr.TextDocument("\n".join(report.conclusions), media_type="text/markdown"),
        static=True,
    )
    rec.flush()
    rec.disconnect()


def print_progress(text: str) -> None:
    """Progress lines on stderr (the report itself goes to stdout)."""
    print(f"  {text}", file=sys.stderr, flush=True)


def config_of(config_file: Path | None, overrides: Sequence[str]) -> Config:
    """The config a latency run uses (validates the user's overrides up front)."""
    return load_config(config_file, stack_overrides(1.0, overrides))
