"""Recovery end to end: services killed mid-task under supervisord, the run goes on.

The kills run in lockstep, so the test is deterministic however busy the machine: the
plant waits for every answer, and a restart only stretches the wall time. One stack for
two kills: the plant (resumes from its checkpoint) and, later, the operator (takes the
task up where the world is).
"""

from __future__ import annotations

import signal
from pathlib import Path

from teleop.bus.messages import Event
from teleop.core.config import load_config
from teleop.run.stack import run_on_services
from teleop.run.supervise import Stack
from teleop.viz.rrd import Recording
from teleop.viz.stream_writers import event_text

# Phases of deploy/scenarios/grasp.toml during which the cube is held.
HOLDING_PHASES = ("lift", "carry")


def test_a_plant_then_an_operator_killed_mid_grasp_both_take_the_task_up(tmp_path: Path):
    run_dir = tmp_path / "run"
    overrides = ['run.scenario="grasp"', 'run.mode="lockstep"', "run.seed=0"]
    config = load_config(None, overrides)
    killed: dict[str, str] = {}

    def progress(line: str) -> None:  # the launcher's progress lines name the phase
        if "plant" not in killed and any(f" {phase}" in line for phase in HOLDING_PHASES):
            Stack.attach(run_dir).signal_program("plant", signal.SIGKILL)
            killed["plant"] = line
        elif "plant" in killed and "operator" not in killed and line.endswith(" carry"):
            Stack.attach(run_dir).signal_program("operator", signal.SIGKILL)
            killed["operator"] = line

    summary = run_on_services(
        config, None, overrides, run_dir, progress, restarts_expected=("plant", "operator")
    )
    assert killed.keys() == {"plant", "operator"}, f"killed only {killed}"
    assert summary["success"] and summary["object_in_box"] and summary["failure"] is None
    # The new operator took the task up where the world was: the cube in the gripper,
    # lifted, not yet over the bin (no start over: the cube was never dropped).
    operator = summary["services"]["operator"]
    assert operator["resumed"]["name"] == "carry", operator["resumed"]
    # Both killed processes' counts are in the run's summary (their running summaries).
    assert summary["restarted_services"] == {"plant": 1, "operator": 1}
    (killed_operator,) = operator["earlier_incarnations"]
    assert killed_operator["running"] and killed_operator["decisions"] > 0
    (resume,) = summary["plant_resumes"]
    # Lost: the steps since the newest checkpoint on file (its writer may be one behind).
    period_steps = round(config.plant.checkpoint_s / config.tick_s)
    assert 0 <= resume["steps_lost"] <= 2 * period_steps
    assert resume["wall_gap_s"] > 0
    # Sim time went on: the run's steps count on past the restart, none twice.
    assert summary["steps"] > resume["step"] > 0
    # The recording has the restart, at the step the plant resumed.
    recording = Recording(summary["rrd"])
    rows = [row for rows in recording.column("events", "TextLog:text").values() for row in rows]
    texts = [text for row in rows for text in row]
    expected = event_text(Event.RESUMED, resume["step"], resume["steps_lost"])
    assert expected in texts, texts
