"""Scenario runs and their summaries: what a user launches with ``teleop run``.

The in-process run couples the plant and the controller in one loop with no bus:
the reference against which the service runs are compared (same seed, same
``final_state_sha256`` in lockstep).
"""

from __future__ import annotations

import collections
import sys
import time
from collections.abc import Callable

import numpy as np

from teleop.control.clearance import ClearanceModel
from teleop.control.kinematics import build_arm_model
from teleop.control.path import PathFollowingController, PathMetrics
from teleop.core.config import Config
from teleop.core.criteria import TaskFigures, judge_task
from teleop.sim.plant import Plant, initial_configuration

# Progress lines on long runs: one every this fraction of the run.
PROGRESS_FRACTION = 0.1

ProgressFn = Callable[[float, float], None]


def print_progress(fraction: float, sim_time_s: float) -> None:
    """Default progress report on stderr."""
    print(f"  {fraction:4.0%}  sim t = {sim_time_s:6.1f} s", file=sys.stderr, flush=True)


def run_path_following_inprocess(
    config: Config, progress: ProgressFn | None = print_progress
) -> dict[str, object]:
    """Experiment 1 with plant and controller in one process; returns the summary.
    ValueError for a teleoperated scenario (its hand and devices run as services)."""
    if not config.run.follows_path:
        raise ValueError(f"in process: an autonomous scenario, not {config.run.scenario}")
    plant = Plant(config)
    plant.reset(initial_configuration(config))
    arm = build_arm_model(config.robot)
    controller = PathFollowingController(
        arm,
        config.control,
        config.path,
        period_s=config.tick_s,
        clearance=ClearanceModel(config, arm),
    )
    metrics = PathMetrics.for_config(config)
    steps = round(config.run.duration_s / config.tick_s)
    report_every = max(1, int(steps * PROGRESS_FRACTION))
    wall_start = time.perf_counter()
    # Step k applies the command answering state k - delay, as the lockstep plant does.
    delay = config.plant.lockstep_delay_steps
    in_flight: collections.deque[np.ndarray] = collections.deque()
    for k in range(steps):
        sample = plant.sample()
        output = controller.update(sample.q_rad, sample.qd_rad_s, sample.gripper_opening_m)
        metrics.add(sample.sim_time_ns * 1e-9, output)
        in_flight.append(output.qd_ref_rad_s.copy())
        if k < delay:
            plant.step_before_commands()
        else:
            plant.step(in_flight.popleft(), gripper_cmd=1.0)
        if progress is not None and (k + 1) % report_every == 0:
            progress((k + 1) / steps, plant.sample().sim_time_ns * 1e-9)
    # The final state is measured too, as the controller service does with the last
    # state the plant publishes (its command, like those still in flight, is never applied).
    final = plant.sample()
    last = controller.update(final.q_rad, final.qd_rad_s, final.gripper_opening_m)
    metrics.add(final.sim_time_ns * 1e-9, last)
    wall_s = time.perf_counter() - wall_start
    # Every step after the delay applied the controller's command.
    figures = {**metrics.summary(), "commands_applied": steps - delay}
    return {
        "scenario": config.run.scenario,
        "mode": "inprocess",
        "duration_s": config.run.duration_s,
        "seed": config.run.seed,
        "settle_s": config.run.settle_s,
        "compensation": config.control.compensation,
        **figures,
        # The task's criteria (teleop.core.criteria) and what the motion itself reported.
        **judge_task(
            config.run.scenario, TaskFigures.from_json(figures), metrics.problems()
        ).to_json(),
        "events": [
            {"event": e.event.name, "sim_time_s": e.sim_time_s, "value": e.value}
            for e in metrics.events
        ],
        "steps": steps,
        "commands_clamped": plant.clamped_steps,
        "commands_clamped_by_reason": plant.clamped_by_reason(),
        "wall_s": wall_s,
        "realtime_factor": config.run.duration_s / wall_s,
        "final_state_sha256": plant.state_sha256(),
    }
