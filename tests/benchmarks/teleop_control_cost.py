"""Benchmark: the cost of one teleoperation control cycle, against the numpy baseline.

The controller service runs, per haptic sample (1 kHz), the operator's rate command
(``teleop_reference``) and ``TeleopController.update``, and per plant state the force
feedback (``feedback_components`` + ``device_force``). This script times them in the
current tree ("fast") and in the baseline commit (the numpy/SVD implementation, loaded
from git into private modules), in the same run and alternating, on the same recorded
states, and checks that both give the same outputs. A third replay ("prepared") runs the
current tree split as the service can run it: ``TeleopController.prepare`` on the joint
state first (off the critical path: the plant state arrives before the handle sample),
then the rate command, ``update(..., terms=...)`` and the force feedback; its outputs must
equal the fast replay's bit for bit.

The states are recorded once, closed loop: the baseline controller drives the MuJoCo
plant through three segments (a free 3D motion with a clutch phase, a push into a
virtual obstacle in range, a stretch towards the elbow singularity). Both
implementations then replay them open loop from a fresh controller, so their outputs
agree to rounding unless the mathematics differ.

    .venv/bin/python tests/benchmarks/teleop_control_cost.py --rounds 7 \\
        --json runs/bench/teleop_control_cost.json

Reports, per segment and part, the median over rounds of the per-call median (us), the
ratio baseline / fast, the largest output deviations, and the load average; for the
split: prepare alone, update with prepared terms alone and the critical-path cycle
(reference + update(terms) + feedback), with the ratios full update / update(terms) and
fast cycle / prepared cycle.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import gc
import importlib
import json
import math
import os
import statistics
import subprocess
import sys
import time
import types
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from teleop.control import feedback, rate
from teleop.control import teleop as teleop_control
from teleop.control.kinematics import ArmModel, build_arm_model, tool_position_and_jacobian
from teleop.core.config import Config, SceneConfig, load_config
from teleop.sim.plant import Plant, initial_configuration
from teleop.sim.proximity import (
    ObstacleProximity,
    ProximitySample,
    apply_scene_overrides,
    body_names,
)

# The baseline: the commit with the numpy/SVD control cycle, compared in the same run.
BASELINE_REV = "c3b27db80a4ab51a194820217ab9f407d213752d"
# Outputs must agree to this, relative to the largest magnitude of the field over the run.
RELATIVE_TOLERANCE = 1e-10
# View yaw (rad) of the free segment: the rate command and the feedback rotate.
FREE_YAW_RAD = 0.3
# A stretched arm, tool outward along -x (wrist_2 = 0), condition number ~8.
STRETCHED_Q_RAD = (0.0, -1.5708, 0.8, -0.8, 0.0, 0.0)
# Steps replayed untimed before each segment (first calls, caches, allocator).
WARMUP_STEPS = 300
PARTS = ("reference", "update", "feedback", "cycle")
# Timed only in the prepared replay, before the others (its "update" is update(terms=...)
# alone and its "cycle" leaves prepare out: what remains on the critical path).
PREPARE = "prepare"


@dataclass(frozen=True)
class Step:
    """What the controller service has at one cycle (world frame, SI)."""

    q_rad: np.ndarray
    qd_rad_s: np.ndarray
    handle_d_m: np.ndarray  # device frame
    yaw_rad: float
    clutch: bool
    obstacle: ProximitySample
    world_f_gripper_n: np.ndarray
    held_mass_kg: float


@dataclass(frozen=True)
class Implementation:
    name: str
    teleop_control: types.ModuleType
    feedback: types.ModuleType
    prepared: bool = False  # prepare() then update(terms=...), timed apart
    # Where its teleop_reference lives (the baseline's teleop_control module has it).
    rate: types.ModuleType | None = None

    @property
    def reference(self) -> Callable[..., np.ndarray]:
        return (self.rate or self.teleop_control).teleop_reference


def output_fields(out: Any) -> dict[str, Any]:
    """A control output's fields by name: the baseline's is a dataclass, the current one a
    NamedTuple."""
    if dataclasses.is_dataclass(out):
        return {f.name: getattr(out, f.name) for f in dataclasses.fields(out)}
    return dict(out._asdict())


def parts_of(impl: Implementation) -> tuple[str, ...]:
    return (PREPARE, *PARTS) if impl.prepared else PARTS


# The baseline predates the layered package: the modules it imports, by their old names.
OLD_LAYOUT = {
    "teleop.config": "teleop.core.config",
    "teleop.kinematics": "teleop.control.kinematics",
    "teleop.control": "teleop.control.path",
    "teleop.teleop_control": "teleop.control.teleop",
    "teleop.feedback": "teleop.control.feedback",
    "teleop.proximity": "teleop.sim.proximity",
}


@contextlib.contextmanager
def _old_layout(baseline: dict[str, types.ModuleType]) -> Iterator[None]:
    """While the baseline's source runs, its imports by old name find the baseline's own
    modules loaded so far (``baseline``, by old name), else the current ones."""
    saved = {old: sys.modules.get(old) for old in OLD_LAYOUT}
    for old, new in OLD_LAYOUT.items():
        sys.modules[old] = baseline.get(old) or importlib.import_module(new)
    try:
        yield
    finally:
        for old, module in saved.items():
            if module is None:
                sys.modules.pop(old, None)
            else:
                sys.modules[old] = module


def _module_from_git(
    rev: str, path: str, name: str, baseline: dict[str, types.ModuleType]
) -> types.ModuleType:
    source = subprocess.run(
        ["git", "show", f"{rev}:{path}"], check=True, capture_output=True, text=True
    ).stdout
    module = types.ModuleType(name)
    sys.modules[name] = module  # dataclasses look their module up
    with _old_layout(baseline):
        exec(compile(source, f"{rev[:10]}:{path}", "exec"), module.__dict__)  # noqa: S102
    return module


# The baseline's modules (teleop/<name>.py at BASELINE_REV) and the current ones they are.
BASELINE_MODULES = {
    "kinematics": "teleop.control.kinematics",
    "control": "teleop.control.path",
    "teleop_control": "teleop.control.teleop",
    "feedback": "teleop.control.feedback",
}


def load_baseline(rev: str) -> Implementation:
    """The baseline's teleop_control and feedback, with what they import from the
    project's kinematics, control and teleop_control modules bound to the baseline's
    versions too (so no later change of those files speeds the baseline up)."""
    modules: dict[str, types.ModuleType] = {}
    for name in BASELINE_MODULES:
        loaded = {f"teleop.{n}": m for n, m in modules.items()}
        modules[name] = _module_from_git(rev, f"teleop/{name}.py", f"baseline_{name}", loaded)
    return Implementation("baseline", modules["teleop_control"], modules["feedback"])


def record_segment(
    cfg: Config,
    arm: ArmModel,
    baseline: Implementation,
    q0_rad: np.ndarray,
    handle_of_t: Callable[[float], tuple[np.ndarray, bool]],
    yaw_rad: float,
    steps: int,
    scene: SceneConfig | None = None,
) -> list[Step]:
    """Drive the plant with the baseline controller; keep every cycle's inputs."""
    plant = Plant(cfg)
    if scene is not None:
        apply_scene_overrides(plant.model, scene, cfg.robot)
    plant.reset(np.asarray(q0_rad, dtype=float))
    proximity = ObstacleProximity(plant.model, plant.data, cfg.robot)
    ctl = baseline.teleop_control.TeleopController(
        arm, cfg.teleop, cfg.control, cfg.plant.timestep_s, body_names(plant.model)
    )
    recorded = []
    for k in range(steps):
        sample = plant.sample()
        handle_d_m, clutch = handle_of_t(k * cfg.plant.timestep_s)
        obstacle = proximity.closest()
        v_ref = baseline.teleop_control.teleop_reference(handle_d_m, yaw_rad, clutch, cfg.teleop)
        out = ctl.update(sample.q_rad, sample.qd_rad_s, v_ref, obstacle, 1.0, clutch)
        contact_n, _ = plant.gripper_contact_force()
        recorded.append(
            Step(sample.q_rad, sample.qd_rad_s, handle_d_m, yaw_rad, clutch, obstacle,
                 contact_n, 0.0)
        )  # fmt: skip
        plant.step(out.qd_ref_rad_s, out.gripper_cmd)
    return recorded


def free_handle(t_s: float) -> tuple[np.ndarray, bool]:
    """A constant offset, a circle asking beyond the speed cap, a clutch, then rest."""
    if t_s < 0.5:
        return np.array([0.02, -0.03, 0.012]), False
    if t_s < 1.5:
        phase = 2.0 * math.pi * (t_s - 0.5)
        return np.array([0.06 * math.cos(phase), 0.06 * math.sin(phase), -0.01]), False
    if t_s < 1.7:
        return np.array([0.03, 0.0, 0.0]) * (1.7 - t_s) / 0.2, True
    return np.zeros(3), False


def record_trajectories(
    cfg: Config, arm: ArmModel, baseline: Implementation
) -> dict[str, tuple[Config, list[Step]]]:
    """The three segments and the configuration each runs with."""
    start = initial_configuration(cfg)[: arm.n_joints]
    probe = Plant(cfg)
    probe.reset(start)
    tool_p = probe.tool_pose()[0]
    in_front = SceneConfig(
        obstacle_p_m=(tuple((tool_p + [0.15, 0.0, 0.0]).tolist()),), obstacle_radius_m=(0.05,)
    )
    push = np.array([0.05, 0.0, 0.0])  # beyond the cap: 0.25 m/s forward
    outward = np.array([-0.05, 0.0, 0.0])
    # The tool points outward there: hold that orientation rather than turning it down.
    outward_cfg = dataclasses.replace(
        cfg, teleop=dataclasses.replace(cfg.teleop, approach_down=False)
    )
    return {
        "free": (cfg, record_segment(cfg, arm, baseline, start, free_handle, FREE_YAW_RAD, 2000)),
        "obstacle": (
            cfg,
            record_segment(cfg, arm, baseline, start, lambda t: (push, False), 0.0, 1500, in_front),
        ),
        "near_singular": (
            outward_cfg,
            record_segment(
                outward_cfg,
                arm,
                baseline,
                np.array(STRETCHED_Q_RAD),
                lambda t: (outward, False),
                0.0,
                1500,
            ),  # fmt: skip
        ),
    }


def steps_below_singular_value_threshold(arm: ArmModel, steps: list[Step]) -> int:
    """States where the 6D least squares takes its adaptive damping (sigma_min < threshold)."""
    count = 0
    for s in steps:
        jacobian = tool_position_and_jacobian(arm, s.q_rad)[1]
        sigma_min = np.linalg.svd(jacobian, compute_uv=False)[-1]
        count += bool(sigma_min < teleop_control.SINGULAR_VALUE_THRESHOLD)
    return count


class Replay:
    """One implementation replaying the recorded steps from a fresh controller, with
    its own Pinocchio scratch data: outputs and per-call times (ns) of each part."""

    def __init__(
        self, impl: Implementation, cfg: Config, arm: ArmModel, names: tuple[str, ...]
    ) -> None:
        self.impl = impl
        self.cfg = cfg
        arm = dataclasses.replace(arm, data=arm.model.createData())
        self.controller = impl.teleop_control.TeleopController(
            arm, cfg.teleop, cfg.control, cfg.plant.timestep_s, names
        )
        self.times: dict[str, list[int]] = {part: [] for part in parts_of(impl)}
        self.outputs: list[dict] = []

    def run(self, steps: list[Step]) -> None:
        fb, cfg, ctl = self.impl.feedback, self.cfg, self.controller
        clock = time.perf_counter_ns
        prepared = self.impl.prepared
        for s in steps:
            if prepared:
                t_prepare = clock()
                terms = ctl.prepare(s.q_rad, s.qd_rad_s)
                self.times[PREPARE].append(clock() - t_prepare)
            t0 = clock()
            v_ref = self.impl.reference(s.handle_d_m, s.yaw_rad, s.clutch, cfg.teleop)
            t1 = clock()
            if prepared:
                out = ctl.update(s.q_rad, s.qd_rad_s, v_ref, s.obstacle, 1.0, s.clutch, terms)
            else:
                out = ctl.update(s.q_rad, s.qd_rad_s, v_ref, s.obstacle, 1.0, s.clutch)
            t2 = clock()
            components = fb.feedback_components(
                s.world_f_gripper_n, s.held_mass_kg, s.obstacle, s.handle_d_m, cfg.teleop
            )
            device_f_n = fb.device_force(components, s.yaw_rad, cfg.teleop, cfg.haptic)
            t3 = clock()
            self.times["reference"].append(t1 - t0)
            self.times["update"].append(t2 - t1)
            self.times["feedback"].append(t3 - t2)
            self.times["cycle"].append(t3 - t0)
            fields = output_fields(out)
            fields["v_ref"] = v_ref
            fields["device_f_n"] = device_f_n
            fields["world_robot_f_n"] = components.world_robot_f_n
            fields["device_workspace_f_n"] = components.device_workspace_f_n
            self.outputs.append(fields)


def replay_alternating(
    impls: tuple[Implementation, ...],
    cfg: Config,
    arm: ArmModel,
    names: tuple[str, ...],
    steps: list[Step],
    chunk: int,
) -> dict[str, Replay]:
    """Replay every implementation over the steps, alternating every ``chunk`` steps so
    that load changes on the machine hit them alike (each keeps its own state)."""
    replays = {impl.name: Replay(impl, cfg, arm, names) for impl in impls}
    gc.collect()
    gc.disable()
    try:
        for k in range(0, len(steps), chunk):
            for replay in replays.values():
                replay.run(steps[k : k + chunk])
    finally:
        gc.enable()
    return replays


def deviations(baseline: list[dict], fast: list[dict]) -> dict[str, dict[str, float]]:
    """Per output field: largest |fast - baseline| and that over the field's largest
    magnitude in the run (booleans as 0/1; a differing non-finite value counts as inf)."""
    result = {}
    for name in baseline[0]:
        old = np.array([np.asarray(o[name], dtype=float) for o in baseline])
        new = np.array([np.asarray(o[name], dtype=float) for o in fast])
        finite = np.isfinite(old)
        if not np.array_equal(finite, np.isfinite(new)) or np.any(old[~finite] != new[~finite]):
            result[name] = {"max_abs": math.inf, "max_relative": math.inf}
            continue
        diff = float(np.max(np.abs(new[finite] - old[finite]), initial=0.0))
        scale = float(np.max(np.abs(old[finite]), initial=0.0))
        result[name] = {"max_abs": diff, "max_relative": diff / scale if scale > 0 else diff}
    return result


def identical(expected: list[dict], actual: list[dict]) -> bool:
    """Every output field of every step equal bit for bit (the lockstep hash's view)."""
    return all(
        np.asarray(e[name]).tobytes() == np.asarray(a[name]).tobytes()
        for e, a in zip(expected, actual, strict=True)
        for name in e
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=7, help="replays of each implementation")
    parser.add_argument("--chunk", type=int, default=50, help="steps between alternations")
    parser.add_argument("--baseline-rev", default=BASELINE_REV, help="git revision to compare")
    parser.add_argument("--json", type=Path, default=Path("runs/bench/teleop_control_cost.json"))
    args = parser.parse_args()
    load_before = os.getloadavg()
    cfg = load_config(None, ["run.scenario=grasp"])
    arm = build_arm_model(cfg.robot)
    baseline = load_baseline(args.baseline_rev)
    fast = Implementation("fast", teleop_control, feedback, rate=rate)
    prepared = Implementation("prepared", teleop_control, feedback, prepared=True, rate=rate)
    impls = (baseline, fast, prepared)
    trajectories = record_trajectories(cfg, arm, baseline)
    names = body_names(Plant(cfg).model)

    medians: dict[str, dict[str, dict[str, list[float]]]] = {
        segment: {impl.name: {part: [] for part in parts_of(impl)} for impl in impls}
        for segment in trajectories
    }
    report_segments = {}
    agree = True
    for segment, (segment_cfg, steps) in trajectories.items():
        outputs = {}
        warmup = steps[:WARMUP_STEPS]
        replay_alternating(impls, segment_cfg, arm, names, warmup, args.chunk)
        for r in range(args.rounds):
            order = impls if r % 2 == 0 else impls[::-1]
            replays = replay_alternating(order, segment_cfg, arm, names, steps, args.chunk)
            for name, replay in replays.items():
                outputs[name] = replay.outputs
                for part, times in replay.times.items():
                    medians[segment][name][part].append(statistics.median(times) / 1e3)
        deviation = deviations(outputs["baseline"], outputs["fast"])
        worst = max(d["max_relative"] for d in deviation.values())
        prepared_identical = identical(outputs["fast"], outputs["prepared"])
        agree = agree and worst <= RELATIVE_TOLERANCE and prepared_identical
        summary = {
            impl: {part: statistics.median(values) for part, values in parts.items()}
            for impl, parts in medians[segment].items()
        }
        base_out = outputs["baseline"]
        report_segments[segment] = {
            "steps": len(steps),
            "obstacle_active_steps": sum(bool(o["obstacle_active"]) for o in base_out),
            "singularity_slowdown_steps": sum(
                o["speed_scale"] < 1.0 and o["cond"] > segment_cfg.teleop.singularity_slowdown_cond
                for o in base_out
            ),
            "damped_steps": steps_below_singular_value_threshold(arm, steps),
            "max_cond": max(o["cond"] for o in base_out),
            "median_us": summary,
            "ratio_baseline_over_fast": {
                part: summary["baseline"][part] / summary["fast"][part] for part in PARTS
            },
            # Full update() over update(terms=...) alone, and the fast cycle over the
            # prepared one (prepare left out: it runs before the handle sample).
            "ratio_fast_over_prepared": {
                part: summary["fast"][part] / summary["prepared"][part] for part in PARTS
            },
            "prepared_outputs_identical": prepared_identical,
            "per_round_median_us": medians[segment],
            "max_relative_deviation": worst,
            "deviation": deviation,
        }
        print(f"{segment}: " + ", ".join(
            f"{part} {summary['baseline'][part]:.1f} -> {summary['fast'][part]:.1f} us "
            f"(x{summary['baseline'][part] / summary['fast'][part]:.2f})" for part in PARTS
        ) + f"; max relative deviation {worst:.1e}")  # fmt: skip
        split = summary["prepared"]
        print(f"  prepared: prepare {split[PREPARE]:.1f} us, update(terms) "
              f"{split['update']:.1f} us vs update() {summary['fast']['update']:.1f} us "
              f"(x{summary['fast']['update'] / split['update']:.2f}), cycle "
              f"{split['cycle']:.1f} vs {summary['fast']['cycle']:.1f} us "
              f"(x{summary['fast']['cycle'] / split['cycle']:.2f}); "
              f"outputs identical: {prepared_identical}")  # fmt: skip
    report = {
        "baseline_rev": args.baseline_rev,
        "rounds": args.rounds,
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "cpu_count": os.cpu_count(),
        "relative_tolerance": RELATIVE_TOLERANCE,
        "outputs_agree": agree,
        "segments": report_segments,
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    print(f"load average {load_before[0]:.2f} -> {report['load_average_after'][0]:.2f}; "
          f"outputs agree: {agree}; written {args.json}")  # fmt: skip
    return 0 if agree else 1


if __name__ == "__main__":
    sys.exit(main())
