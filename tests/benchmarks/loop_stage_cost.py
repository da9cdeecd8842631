"""Benchmark: each stage of the bilateral loop in the real services, warm and cold caches.

``teleop latency`` measures the stages in the running stack: there each costs 3-10x what
the same code takes in a tight loop. Thread CPU time equals wall time across them (so no
waiting), and the other processes that run on the core between two
wake-ups evict the service's code and data from the caches. This script measures that
directly and without the stack's noise: one process holds a plant, a controller and a
haptic service (real objects, each with its own Zenoh session and robot id, so nothing
routes between them) and passes the loop's records from one to the next through the
same code the Zenoh callbacks run (``teleop.bus.session.deliver``: decode, then the service's
callback). Each period: the device samples, the controller answers with a command, the
plant steps it, the controller turns the state into a force, the device renders it.

The stage times come from the records' own stamps, exactly as the latency report's
hops (``teleop.bench.latency.HOPS``), so they include the decode. "warm": the periods run
back to back; "cold": before each stage the process streams through a buffer larger
than the caches (``--evict-mib``), as the other services of the stack do in between.
The ratio cold / warm is what running among other processes costs; the cold figures
are the ones to cut (the stack's in-service stages lie between the two).

    .venv/bin/python tests/benchmarks/loop_stage_cost.py --periods 600 --rounds 3 \\
        --json runs/bench/loop_stage_cost.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from services.controller import ControllerService
from services.haptic import HapticService
from services.plant import PlantService
from teleop.bench.latency import stack_overrides
from teleop.bench.loop_stats import HOPS
from teleop.bus.messages import FORCE_FEEDBACK, HAPTIC_STATE, JOINT_COMMAND, PLANT_STATE
from teleop.bus.service import Service, ServiceOptions
from teleop.bus.session import deliver
from teleop.core.config import Config, load_config
from teleop.core.net import free_loopback_port
from teleop.sim.pacing import DeviceClockPacer

# The loop's stages this replay covers: the latency report's compute and wait hops.
STAGES = tuple(hop for hop in HOPS if hop.kind in ("compute", "wait"))
# Bytes between two cache lines touched by the eviction (x86: 64 B lines).
CACHE_LINE_BYTES = 64
# Periods run before any is counted (the first ones warm up the interpreter and Zenoh).
WARMUP_PERIODS = 100


class Evictor:
    """Streams through a buffer larger than the caches, one write per cache line."""

    def __init__(self, mib: float) -> None:
        self._buffer = np.zeros(int(mib * (1 << 20)) // 8)
        self._stride = CACHE_LINE_BYTES // self._buffer.itemsize

    def __call__(self) -> None:
        self._buffer[:: self._stride] += 1.0


def service_config(name: str) -> Config:
    """The latency run's realtime teleoperation config, with a robot id and a port of the
    service's own (no routing between the three)."""
    port = free_loopback_port()
    return load_config(
        None,
        [
            *stack_overrides(duration_s=3600.0),
            f'robot.robot_id="bench-{name}"',
            f'bus.endpoint="tcp/127.0.0.1:{port}"',
        ],
    )


# A shed age no stage of this replay reaches (ns).
NEVER_SHED_NS = 3600 * 10**9


class Loop:
    """The three loop services in one process, driven period by period through the
    callbacks their subscribers would run."""

    def __init__(self) -> None:
        listen = ServiceOptions(listen=True)
        self.plant = PlantService(service_config("plant"), listen)
        self.controller = ControllerService(service_config("controller"), listen)
        self.haptic = HapticService(service_config("haptic"), listen)
        self.services: tuple[Service, ...] = (self.plant, self.controller, self.haptic)
        for service in self.services:
            service.open()
        # Stages are driven one by one here, with a cache eviction between them that can
        # outlast the realtime shed age: nothing may be shed as too old, every stage runs.
        for inbound in (
            self.plant.loop.core.command_in,
            self.controller.core.haptic_in,
            self.controller.core.state_in,
            self.haptic.loop.feedback_in,
        ):
            inbound.shed_age_ns = NEVER_SHED_NS
        # Nor may the controller take the plant for silent (it then commands no motion).
        self.controller.core.state_silent_ns = NEVER_SHED_NS
        pacer = self.plant.loop.pacer
        assert isinstance(pacer, DeviceClockPacer), "the latency run's plant paces on arrival"
        self.pacer = pacer
        pacer.core.begin_run(None)
        pacer.begin()
        pacer.core.publish_state()  # state 0: the first sample is answered on it
        pacer.core.prepare_next_step()
        state = pacer.core.state_rec.tobytes()
        deliver(
            state,
            time.monotonic_ns(),
            PLANT_STATE,
            self.controller._on_state,
            self.controller.drops,
        )

    def period(self, between: Callable[[], None]) -> np.ndarray:
        """One period; ``between`` runs before each stage. The trace of its loop (the
        feedback's stamps as rendered, which carry the whole chain's)."""
        controller, plant, haptic = self.controller, self.plant, self.haptic
        between()  # the device samples the handle on the plant's grid
        deadline_ns = self.pacer.grid.next_ns if self.pacer.grid is not None else 0
        loop = haptic.loop
        with loop.cond:
            # As step_realtime does, its tick ending now: the render grid a feedback
            # arriving later is rendered on (from the servo period after it came).
            now_ns = time.monotonic_ns()
            loop._step(max(loop._state_seq, 0), 0, None, now_ns - loop.tick_ns, deadline_ns)
            loop._last_deadline_ns = now_ns
        sample = loop.record.tobytes()
        between()
        cycles = controller.core.cycles
        deliver(
            sample, time.monotonic_ns(), HAPTIC_STATE, controller.core.on_haptic, controller.drops
        )
        if controller.core.cycles == cycles:
            core = controller.core
            raise RuntimeError(
                "the controller did not answer the sample (shed, or the plant taken for "
                f"silent: {core.plant_silent_samples} such samples)"
            )
        command = controller.core._command.tobytes()
        between()
        deliver(command, time.monotonic_ns(), JOINT_COMMAND, plant._on_command, plant.drops)
        state = self.pacer.core.state_rec.tobytes()
        between()
        deliver(state, time.monotonic_ns(), PLANT_STATE, controller._on_state, controller.drops)
        feedback = controller.core._feedback.tobytes()
        between()
        before = len(loop.trace_log)
        deliver(feedback, time.monotonic_ns(), FORCE_FEEDBACK, haptic._on_feedback(0), haptic.drops)
        if len(loop.trace_log) == before:
            raise RuntimeError("the feedback was not rendered: a stage shed its input")
        return loop.trace_log.rows[-1]

    def close(self) -> None:
        for service in self.services:
            service.close()


def run_periods(loop: Loop, periods: int, between: Callable[[], None]) -> dict[str, float]:
    """Median microseconds of each stage over ``periods`` counted periods."""
    for _ in range(WARMUP_PERIODS):
        loop.period(between)
    traces = np.array([loop.period(between) for _ in range(periods)])
    return {
        hop.name: float(np.median(traces[:, hop.end] - traces[:, hop.start])) / 1e3
        for hop in STAGES
    }


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--periods", type=int, default=600, help="counted periods per run")
    parser.add_argument("--rounds", type=int, default=3, help="warm and cold runs, alternating")
    parser.add_argument("--evict-mib", type=float, default=16.0, help="eviction buffer (MiB)")
    parser.add_argument("--json", type=Path, default=Path("runs/bench/loop_stage_cost.json"))
    args = parser.parse_args()
    if args.periods < 1 or args.rounds < 1 or args.evict_mib <= 0:
        parser.error("--periods, --rounds and --evict-mib must be positive")
    os.environ.setdefault("RERUN_ANALYTICS", "0")
    loop = Loop()
    evict = Evictor(args.evict_mib)
    runs: dict[str, list[dict[str, float]]] = {"warm": [], "cold": []}
    try:
        for round_index in range(args.rounds):
            for mode, between in (("warm", lambda: None), ("cold", evict)):
                runs[mode].append(run_periods(loop, args.periods, between))
                print(f"round {round_index + 1}/{args.rounds} {mode}: "
                      + ", ".join(f"{k} {v:.1f}" for k, v in runs[mode][-1].items()) + " us",
                      flush=True)  # fmt: skip
    finally:
        loop.close()
    result: dict[str, Any] = {"periods": args.periods, "rounds": args.rounds,
                              "evict_mib": args.evict_mib, "loadavg": os.getloadavg(),
                              "stages_us": {}}  # fmt: skip
    print(f"{'stage (median us)':22s} {'warm':>8s} {'cold':>8s} {'cold/warm':>10s}")
    for hop in STAGES:
        warm = statistics.median(r[hop.name] for r in runs["warm"])
        cold = statistics.median(r[hop.name] for r in runs["cold"])
        result["stages_us"][hop.name] = {"warm": warm, "cold": cold, "cold_over_warm": cold / warm}
        print(f"{hop.name:22s} {warm:8.1f} {cold:8.1f} {cold / warm:10.2f}")
    total_warm = sum(v["warm"] for v in result["stages_us"].values())
    total_cold = sum(v["cold"] for v in result["stages_us"].values())
    result["total_us"] = {"warm": total_warm, "cold": total_cold}
    print(f"{'all stages':22s} {total_warm:8.1f} {total_cold:8.1f} {total_cold / total_warm:10.2f}")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
