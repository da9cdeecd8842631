"""Benchmark: what the clearance costs path following, in process, in the same run.

Three variants of the in-process loop (plant + path-following controller, the default
path), and the plant alone as the host's floor, alternating so machine noise hits them
alike:

- ``floor``: the plant stepping on zero commands, no controller: what one simulated
  millisecond costs this host before any control (the speed of the machine, for
  comparing absolute figures between hosts);
- ``none``: the controller without a clearance model (the law before clearance);
- ``measure``: clearance measured every cycle, no avoidance (``clearance.avoid=false``);
- ``avoid``: measured and kept (the default).

Reports per variant the median CPU time per step and realtime factor (process CPU time,
so other load on the machine does not count), and the ratios to ``none`` and to the
floor.

    .venv/bin/python tests/benchmarks/clearance_cost.py --duration 20 --repeat 3
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from teleop.control.clearance import ClearanceModel
from teleop.control.kinematics import build_arm_model
from teleop.control.path import PathFollowingController
from teleop.core.config import load_config
from teleop.sim.plant import Plant, initial_configuration

VARIANTS = ("floor", "none", "measure", "avoid")


def run(variant: str, duration_s: float) -> float:
    """CPU seconds per simulated step of one in-process run of ``variant``."""
    overrides = [f"run.duration_s={duration_s}"]
    if variant == "measure":
        overrides.append("clearance.avoid=false")
    config = load_config(None, overrides)
    plant = Plant(config)
    plant.reset(initial_configuration(config))
    steps = round(duration_s / config.plant.timestep_s)
    if variant == "floor":
        zero_rad_s = np.zeros(len(config.robot.arm_joints))
        start = time.process_time()
        for _ in range(steps):
            plant.sample()
            plant.step(zero_rad_s, gripper_cmd=1.0)
        return (time.process_time() - start) / steps
    arm = build_arm_model(config.robot)
    clearance = None if variant == "none" else ClearanceModel(config, arm)
    controller = PathFollowingController(
        arm,
        config.control,
        config.path,
        config.plant.timestep_s,
        clearance=clearance,
    )
    start = time.process_time()
    for _ in range(steps):
        sample = plant.sample()
        output = controller.update(sample.q_rad, sample.qd_rad_s, sample.gripper_opening_m)
        plant.step(output.qd_ref_rad_s, gripper_cmd=1.0)
    return (time.process_time() - start) / steps


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=20.0, help="simulated s per run")
    parser.add_argument("--repeat", type=int, default=3, help="rounds of all variants")
    parser.add_argument("--json", type=Path, default=Path("runs/bench/clearance_cost.json"))
    args = parser.parse_args()
    per_step: dict[str, list[float]] = {v: [] for v in VARIANTS}
    for _ in range(args.repeat):
        for variant in VARIANTS:
            per_step[variant].append(run(variant, args.duration))
    timestep_s = load_config().plant.timestep_s
    medians = {v: statistics.median(t) for v, t in per_step.items()}
    report = {
        variant: {
            "cpu_us_per_step": medians[variant] * 1e6,
            "cpu_realtime_factor": timestep_s / medians[variant],
            "ratio_to_none": medians[variant] / medians["none"],
            "ratio_to_floor": medians[variant] / medians["floor"],
        }
        for variant in VARIANTS
    }
    for variant, figures in report.items():
        print(
            f"{variant:8s} {figures['cpu_us_per_step']:7.1f} us/step  "
            f"{figures['cpu_realtime_factor']:5.2f} x real time  "
            f"{figures['ratio_to_none']:4.2f} x none  "
            f"{figures['ratio_to_floor']:4.2f} x floor"
        )
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"duration_s": args.duration, **report}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
