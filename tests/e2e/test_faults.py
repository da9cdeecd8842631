"""Injected faults (`teleop run --kill / --freeze`): the run rides through them and its
summary says what followed each. Killed and frozen in lockstep, where the sim waits for
the controller and the outcome does not depend on how busy the machine is; one freeze
in realtime, where the plant's watchdog must hold the arm meanwhile."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from teleop.core.config import load_config

# A run that neither fails nor finishes within this long is a hang (s).
HANG_S = 600
EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_REALTIME_LOST = 0, 1, 2, 3
STEPS_PER_S = round(1 / load_config().tick_s)  # the plant steps one tick per bus period


def _teleop(run_dir: Path, *args: str) -> tuple[int, str, dict]:
    proc = subprocess.run(
        [sys.executable, "-m", "teleop.cli", "run", "path-following", "--run-dir",
         str(run_dir), "--quiet", *args],
        capture_output=True, text=True, timeout=HANG_S, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    path = run_dir / "summary.json"
    summary = json.loads(path.read_text()) if path.exists() else {}
    return proc.returncode, proc.stderr, summary


def test_a_controller_killed_then_frozen_in_lockstep_comes_back_and_the_run_completes(tmp_path):
    duration_s = 6.0
    code, err, summary = _teleop(
        tmp_path / "run", "--mode", "lockstep", "--duration", str(duration_s),
        "--kill", "controller@1.5", "--freeze", "controller@4:1",
    )  # fmt: skip
    assert code == EXIT_OK, err
    assert "service controller died" not in err  # the injected kill is no failure
    assert summary["steps"] == duration_s * STEPS_PER_S  # the whole run, no reset
    kill, freeze = summary["faults"]
    assert (kill["service"], kill["kind"], freeze["kind"]) == ("controller", "kill", "freeze")
    # Lockstep: the plant holds at each fault's instant until it is injected, so each
    # lands on its tick however busy the machine (both instants are on the tick grid).
    assert (kill["t_s"], freeze["t_s"]) == (1.5, 4.0)
    # The new controller was ready, and its commands were applied after that.
    assert kill["restart_s"] is not None and kill["resumed_s"] is not None
    assert kill["resumed_s"] >= kill["restart_s"]
    # Frozen 1 s of wall-clock time: nothing it made can be applied before the thaw.
    assert freeze["restart_s"] is None and freeze["resumed_s"] >= freeze["freeze_s"] == 1.0
    # The killed controller's counts are in the summary (its running summary, taken in).
    assert summary["restarted_services"] == {"controller": 1}
    (killed,) = summary["services"]["controller"]["earlier_incarnations"]
    assert killed["running"] and killed["pid"] != summary["services"]["controller"]["pid"]


@pytest.mark.parametrize("checkpoints", [True, False], ids=["checkpoints", "no-checkpoints"])
def test_a_killed_plant_never_passes_for_a_clean_run(tmp_path, checkpoints):
    """Killed mid-run, the plant resumes where it was from its newest checkpoint (on by
    default: sim time continues to the end of the run); without checkpoints the run fails
    saying it could not resume. Never a success that hides a run started over."""
    no_checkpoints = () if checkpoints else ("--set", "plant.checkpoint_s=0")
    code, err, summary = _teleop(
        tmp_path / "run", "--mode", "lockstep", "--duration", "4", "--kill", "plant@2",
        *no_checkpoints,
    )  # fmt: skip
    if not checkpoints:
        assert code == EXIT_FAILED, err
        assert "no checkpoint to resume from" in err, err
        assert summary["success"] is False and summary["failure"], summary.get("failure")
        return
    assert code == EXIT_OK, err
    (fault,) = summary["faults"]
    assert fault["t_s"] == 2.0  # on its tick: the plant held there until killed
    assert fault["resumed_s"] is not None and summary["steps"] == 4 * STEPS_PER_S
    (resume,) = summary["plant_resumes"]
    assert 0 < resume["step"] < 4 * STEPS_PER_S and resume["steps_lost"] >= 0


def test_a_controller_frozen_in_realtime_is_braked_on_and_resumes_after_the_thaw(tmp_path):
    code, err, summary = _teleop(
        tmp_path / "run", "--mode", "realtime", "--duration", "5", "--freeze",
        "controller@2:0.5",
    )  # fmt: skip
    # A busy machine may lose real time elsewhere in the run (exit 3): the fault's own
    # brakes are not counted against it.
    assert code in (EXIT_OK, EXIT_REALTIME_LOST), err
    (fault,) = summary["faults"]
    assert fault["brake_ms"] is not None  # the arm was held while the controller was frozen
    assert fault["resumed_s"] >= 0.5


def test_a_fault_on_an_unknown_service_is_a_usage_error_before_anything_starts(tmp_path):
    code, err, _ = _teleop(tmp_path / "run", "--mode", "lockstep", "--kill", "controler@1")
    assert code == EXIT_USAGE
    assert "did you mean controller?" in err and "Traceback" not in err
    assert not (tmp_path / "run" / "logs").exists()
