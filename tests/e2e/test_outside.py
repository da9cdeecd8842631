"""Services left out of the stack (``--without``) and run from outside: the clients of
examples/, written from docs/protocol.md alone, as real processes against real stacks.

Each test prints the figures the protocol's outside clients are judged by (command or
sample rate, braking, drops, outcome); ``pytest -s`` shows them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import IO

import pytest

from teleop.core.config import load_config
from teleop.core.net import free_loopback_port
from tests.e2e.outcome import assert_ran, needs_realtime_stack

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
CONFIG_LINE = "zenoh config:"  # the join instructions' line naming the client's config file
# A joint of the example's path starts this far from it (rad, CENTRE_OFFSET_RAD there):
# converged means the error after its settling time is a tenth of that at most.
START_ERROR_RAD = 0.1
CONVERGED_RAD = START_ERROR_RAD / 10
TIMEOUT_S = 600


def _drain(stream: IO[str], lines: list[str]) -> None:
    for line in stream:
        lines.append(line)


def _config_path(stack: subprocess.Popen, stderr: list[str]) -> Path:
    """Read the stack's stderr up to the line naming the outside client's Zenoh config;
    keep reading the rest in the background (a full pipe would block the stack)."""
    assert stack.stderr is not None
    for line in stack.stderr:
        stderr.append(line)
        if CONFIG_LINE in line:
            threading.Thread(target=_drain, args=(stack.stderr, stderr), daemon=True).start()
            return Path(line.split(CONFIG_LINE)[1].split()[0])
    raise AssertionError("no join instructions:\n" + "".join(stderr[-50:]))


def run_with_client(
    tmp_path: Path,
    name: str,
    teleop_args: list[str],
    client: str,
    *client_args: str,
    fifo: bool = False,
) -> tuple[dict, dict, int]:
    """``teleop run ...`` with one service left out and ``examples/<client>`` in its place;
    (run summary, the client's own summary, teleop's exit code). ``fifo``: the client runs
    SCHED_FIFO at the stack's loops' priority, as the join instructions ask in realtime."""
    out = tmp_path / f"{name}.json"
    command = [sys.executable, "-m", "teleop.cli", "run", *teleop_args, "--run-dir",
               str(tmp_path / name), "--summary-json", str(out), "--quiet"]  # fmt: skip
    stderr: list[str] = []
    with subprocess.Popen(
        command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        text=True,
    ) as stack:  # fmt: skip
        config = _config_path(stack, stderr)
        assert config.is_file()
        chrt = ["chrt", "-f", str(load_config().cpu.fifo_priority)] if fifo else []
        joined = subprocess.run(
            [*chrt, sys.executable, str(EXAMPLES / client), str(config), *client_args],
            capture_output=True, text=True, timeout=TIMEOUT_S, stdin=subprocess.DEVNULL,
        )  # fmt: skip
        code = stack.wait(timeout=TIMEOUT_S)
    assert joined.returncode == 0, joined.stderr[-3000:]
    assert out.exists(), "".join(stderr[-50:])
    return json.loads(out.read_text()), json.loads(joined.stdout.splitlines()[-1]), code


def assert_clean(summary: dict, outside: str) -> None:
    assert summary["outside"] == [outside]
    assert summary["dropped_messages"] == 0
    assert summary["unlinked_peers"] == {}
    assert outside not in summary["services"]  # no summary of its own: it ran outside


def test_outside_controller_follows_its_path_in_lockstep_deterministically(tmp_path):
    args = ["path-following", "--mode", "lockstep", "--duration", "5", "--without", "controller"]
    # Both at once (lockstep results do not depend on the load; the stacks mostly wait).
    with ThreadPoolExecutor(max_workers=2) as pool:
        runs = [
            pool.submit(run_with_client, tmp_path, name, args, "outside_controller.py")
            for name in ("a", "b")
        ]
        (first, client, code), (second, _, _) = (run.result() for run in runs)
    print("outside controller:", json.dumps(client), "plant:", first["steps"], "steps,",
          first["commands_applied"], "applied,", first["stale_commands"], "stale")  # fmt: skip
    assert code == 0
    assert_clean(first, "controller")
    assert client["finished"] and client["last_state_handled"] and client["bad_records"] == 0
    assert client["tracking_error_max_rad"] < CONVERGED_RAD
    # Every state answered once (states 0..steps); the plant applied the answers to
    # states 0..steps - d - 1 (d = lockstep_delay_steps), none went stale, none braked.
    delay = load_config().plant.lockstep_delay_steps
    assert client["states_received"] == client["commands_sent"] == first["steps"] + 1
    assert first["commands_applied"] == first["steps"] - delay
    assert first["stale_commands"] == 0 and client["braking_states"] == 0
    assert first["path_error_rms_m"] is None  # the stack's controller did not run
    assert first["final_state_sha256"] == second["final_state_sha256"]


@needs_realtime_stack
def test_outside_haptic_device_lets_the_operator_put_the_cube_in_the_bin(tmp_path):
    """A 1 kHz device loop beside the stack's SCHED_FIFO loops: run as the join
    instructions say (SCHED_FIFO; the CI runs as root), else its periods slip on 2 cores."""
    args = ["grasp", "--mode", "realtime", "--seed", "0", "--without", "haptic"]
    summary, client, code = run_with_client(
        tmp_path, "grasp", args, "outside_haptic.py", fifo=os.geteuid() == 0
    )
    print("outside haptic:", json.dumps(client), "plant:", summary["steps"], "steps,",
          summary["commands_applied"], "applied,", summary["stale_commands"], "brakes",
          "success:", summary["success"], "verdict:", summary["realtime_verdict"])  # fmt: skip
    if summary["realtime_verdict"] == "lost" and not summary["success"]:
        # The machine did not keep the 1 kHz beside an outside 1 kHz loop (seen on 2
        # cores: 11-19 % of the device periods skipped, 100-200 watchdog brakes, and one
        # run in five failed): the run says so and why, and the task's outcome is then
        # the machine's (as test_grasp's realtime test).
        assert summary["realtime_problems"], summary
        pytest.skip(f"the run lost real time: {'; '.join(summary['realtime_problems'])}")
    assert_ran(code, summary)
    assert summary["success"] and summary["object_in_box"]
    assert [p["name"] for p in summary["phases"]][-1] == "retreat"
    assert_clean(summary, "haptic")
    assert summary["max_device_force_n"] is None  # the device's own figure: outside
    assert client["samples_sent"] > 0 and summary["commands_applied"] > 0


def test_a_service_that_never_joins_fails_the_run_after_the_timeout(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "teleop.cli", "run", "path-following", "--mode", "lockstep",
         "--duration", "1", "--without", "controller", "--without-timeout", "2",
         "--run-dir", str(tmp_path / "run"), "--quiet"],
        capture_output=True, text=True, timeout=TIMEOUT_S, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    assert result.returncode == 1
    assert "controller" in result.stderr and "not ready after 2 s" in result.stderr
    assert (tmp_path / "run" / "outside" / "controller.json5").is_file()


@pytest.mark.parametrize("command", ["run", "up"])
def test_without_a_service_the_stack_does_not_run_is_refused(tmp_path, command):
    args = ["path-following"] if command == "run" else []
    result = subprocess.run(
        [sys.executable, "-m", "teleop.cli", command, *args, "--without", "haptic",
         "--run-dir", str(tmp_path / "run")],
        capture_output=True, text=True, timeout=TIMEOUT_S, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    assert result.returncode == 2
    assert "--without haptic: not a service of this stack" in result.stderr


def test_up_without_controller_waits_for_it_then_runs_on_its_commands(tmp_path):
    run_dir = tmp_path / "up"
    endpoint = f'bus.endpoint="tcp/127.0.0.1:{free_loopback_port()}"'  # not 7447: CI
    teleop = [sys.executable, "-m", "teleop.cli"]
    with subprocess.Popen(
        [*teleop, "up", "--without", "controller", "--run-dir", str(run_dir), "--set", endpoint],
        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    ) as up:  # fmt: skip
        try:
            config = _config_path(up, [])
            # A realtime stack runs until stopped: the client stops after 3 s of its own.
            client = subprocess.run(
                [sys.executable, str(EXAMPLES / "outside_controller.py"), str(config),
                 "--timeout", "3"],
                capture_output=True, text=True, timeout=TIMEOUT_S, stdin=subprocess.DEVNULL,
            )  # fmt: skip
            assert up.wait(timeout=TIMEOUT_S) == 0
        finally:
            subprocess.run([*teleop, "down", "--run-dir", str(run_dir)], timeout=TIMEOUT_S)
    report = json.loads(client.stdout.splitlines()[-1])
    print("outside controller, realtime:", json.dumps(report))
    assert not report["finished"]  # `teleop up` has no end
    assert report["commands_sent"] == report["states_received"] > 0
    assert report["bad_records"] == 0
