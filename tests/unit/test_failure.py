"""The failure block of a service that dies, crash-loops or never comes alive."""

from __future__ import annotations

from pathlib import Path

import pytest

from teleop.run.failure import (
    ProgramWatch,
    ServiceFailed,
    hint_for,
    last_lines,
    program_log_text,
)

SHM_LOG = """2026-11-25 10:28:57 eyeview INFO teleop.bus.service: pinned to CPU(s) [1]
Traceback (most recent call last):
  File "/repo/shm/provider.py", line 41, in get_provider
    provider = ShmProvider.default_backend(pool_bytes)
zenoh.ZError: Unable to create POSIX shm segment: OS error 12 at segment.rs:85.
"""


def _watch(logs: dict[str, str]) -> ProgramWatch:
    return ProgramWatch(lambda name: Path(f"/run/logs/{name}.log"), lambda p: logs[p.stem])


def _info(name: str, state: str, pid: int, **extra: object) -> dict[str, object]:
    return {"name": name, "statename": state, "pid": pid, **extra}


@pytest.mark.parametrize(
    ("log", "cause"),
    [
        (SHM_LOG, "locked-memory limit"),
        ("OSError: [Errno 98] Address already in use", "port"),
        ("Can not create a new TCP listener bound to tcp/127.0.0.1:7447", "port"),
        ("RuntimeError: Failed to find Rerun Viewer executable in PATH.", "viewer"),
    ],
)
def test_known_causes_get_a_hint(log, cause):
    assert cause in hint_for(log)


def test_an_unknown_cause_gets_no_hint_but_still_its_log():
    assert hint_for("ValueError: something new") == ""
    block = ServiceFailed("plant", "exited with code 1", Path("/x.log"), "a\n\nValueError: x\n")
    assert "hint" not in block.block() and "ValueError: x" in block.block()


def test_the_block_names_the_service_quotes_the_exception_and_gives_the_log_path():
    failed = ServiceFailed("eyeview", "exited with code 1", Path("/run/logs/eyeview.log"), SHM_LOG)
    block = failed.block()
    assert block.startswith("service eyeview exited with code 1")
    assert "OS error 12" in block
    assert "log:  /run/logs/eyeview.log" in block
    assert "hint: a shared-memory pool exceeds the locked-memory limit" in block


def test_the_block_quotes_only_the_last_lines():
    text = "\n".join(f"line {i}" for i in range(100))
    assert last_lines(text, 3) == "line 97\nline 98\nline 99"


def test_running_programs_pass_and_a_failed_state_fails_at_once():
    watch = _watch({"plant": "", "recorder": "boom\n"})
    watch.check([_info("plant", "RUNNING", 10), _info("recorder", "STARTING", 11)])
    with pytest.raises(ServiceFailed) as failed:
        watch.check([_info("plant", "RUNNING", 10), _info("recorder", "BACKOFF", 0)])
    assert failed.value.service == "recorder" and "BACKOFF" in failed.value.what


def test_a_restart_between_two_polls_is_a_crash_even_if_the_state_looks_fine():
    watch = _watch({"recorder": "Failed to find Rerun Viewer executable in PATH\n"})
    watch.check([_info("recorder", "RUNNING", 11)])
    with pytest.raises(ServiceFailed) as failed:
        watch.check([_info("recorder", "RUNNING", 12)])
    assert "restarted" in failed.value.what and "viewer" in failed.value.hint


def test_an_exit_code_is_reported():
    watch = _watch({"plant": "SystemExit: 2\n"})
    with pytest.raises(ServiceFailed, match="exited with code 2"):
        watch.check([_info("plant", "EXITED", 0, exitstatus=2)])


def test_an_empty_log_is_replaced_by_what_supervisord_said_about_the_program(tmp_path):
    log = tmp_path / "logs" / "controller.log"
    log.parent.mkdir()
    log.write_text("")
    supervisord_log = tmp_path / "supervisord.log"
    supervisord_log.write_text(
        "2026-11-25 11:49:13,354 INFO spawned: 'controller' with pid 30607\n"
        "2026-11-25 11:49:13,360 INFO spawned: 'plant' with pid 30608\n"
        "2026-11-25 11:49:13,774 WARN exited: controller (terminated by SIGKILL; not expected)\n"
    )
    text = program_log_text(log, supervisord_log)
    assert text.splitlines() == [
        "supervisord: 2026-11-25 11:49:13,354 INFO spawned: 'controller' with pid 30607",
        "supervisord: 2026-11-25 11:49:13,774 WARN exited: controller (terminated by SIGKILL;"
        " not expected)",
    ]
