"""Two sites on two test hosts (tests/e2e/hosts.py): the robot site (``teleop up --site
robot``) in the robot host's network namespace, the operator site (``--join`` the
handed-over file) in the operator host's, each under its own supervisord, their routers
linked over mutual TLS; or, for a run of two robots, three: the second robot's site
(``--site robot --join`` its own file) in a third host's namespace, its router linked to
the first robot's. Optionally the operator site on a clock of its own (a time
namespace), and the routers' link through the network emulator (``teleop.bench.netem``,
run in the robot host's namespace) with a delay or cuts. Used by the e2e tests and the
benchmarks of a run across hosts.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from teleop.bench.sites import wait_plant_end
from teleop.bus.access import write_run_credentials
from teleop.bus.service import read_summary
from teleop.run.sites import OPERATOR_BUNDLE_FILE, robot_bundle_file
from teleop.run.supervise import Stack
from tests.e2e.hosts import Host
from tests.e2e.users import HANG_S

# The robot router's port, and the network emulator's in front of it (same host).
SITE_PORT = 7447
PROXY_PORT = 7448
PROXY_REPORT_FILE = "netem.json"
PROXY_FIFO_PRIORITY = 50  # above the stack's loops (cpu.fifo_priority)
# When the two-site run's robot router is killed (simulated s into the run).
ROUTER_KILL_AT_SIM_S = 6.0


class TwoSites:
    """A run split across two hosts: the robot site in the robot host's namespace, the
    operator site in the operator host's; with ``strangers`` (:meth:`start`), the robot's
    router killed mid-run and back, then strangers dialling the robot router from the
    operator's host while it runs. ``link``: the network emulator's arguments
    (``--delay-ms 25``, ``--cut 15:0.5``...), the routers then linked through it. A
    context manager: both sites (and the emulator) are stopped on exit."""

    def __init__(
        self,
        robot: Host,
        operator: Host,
        tmp_path: Path,
        *,
        mode: str = "lockstep",
        operator_clock_ahead_s: int = 0,
        link: Sequence[str] | None = None,
        second_robot: Host | None = None,
    ) -> None:
        self.robot, self.operator, self.tmp_path = robot, operator, tmp_path
        # A run of two robots: the second robot's site on this host (its own run dir).
        self.second_robot = second_robot
        self.second_dir = tmp_path / "second_robot"
        self.mode = mode
        # The operator site in a time namespace of its own: its monotonic clock this far
        # ahead of the robot site's (two hosts share no clock).
        self.operator_clock = (
            ["unshare", "--time", "--monotonic", str(operator_clock_ahead_s), "--fork"]
            if operator_clock_ahead_s
            else []
        )
        self.robot_dir, self.operator_dir = tmp_path / "robot", tmp_path / "operator"
        self.site_endpoint = f"tls/{robot.address}:{SITE_PORT}"
        self.link = link
        self.proxy: subprocess.Popen | None = None
        self.proxy_report: dict[str, Any] = {}
        self.teleop = [sys.executable, "-m", "teleop.cli"]
        self.robot_up = self.operator_up = self.robot_status = ""
        self.killed_router_pid = 0
        self.strangers: dict[str, dict] = {}
        self.second_robot_status = ""
        self.summaries: dict[str, dict] = {}

    def __enter__(self) -> TwoSites:
        return self

    def __exit__(self, *exc_info: object) -> None:
        for run_dir in (self.operator_dir, self.second_dir, self.robot_dir):
            if (run_dir / "supervisord.conf").exists():
                subprocess.run([*self.teleop, "down", "--run-dir", str(run_dir)], timeout=120)
        self._stop_proxy()

    def _start_proxy(self) -> str:
        """The network emulator in the robot host's namespace, in front of its router;
        the endpoint the operator site connects to."""
        assert self.link is not None
        address = self.robot.address
        # The emulator stands for the network, which no process of the stack competes
        # with for the CPU: above the loops' SCHED_FIFO priority where this may (root),
        # else its late timers would be the link's jitter.
        network = ["chrt", "--fifo", str(PROXY_FIFO_PRIORITY)] if os.geteuid() == 0 else []
        self.proxy = subprocess.Popen(
            self.robot.argv([*network, sys.executable, "-m", "teleop.bench.netem",
                             "--listen", f"{address}:{PROXY_PORT}",
                             "--target", f"{address}:{SITE_PORT}",
                             "--report", str(self.tmp_path / PROXY_REPORT_FILE), *self.link]),
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=(self.tmp_path / "netem.log").open("w"),
        )  # fmt: skip
        deadline = time.monotonic() + 30
        log = self.tmp_path / "netem.log"
        while "Ctrl-C stops" not in log.read_text():
            assert self.proxy.poll() is None, f"the network emulator exited: {log.read_text()}"
            assert time.monotonic() < deadline, "the network emulator did not start"
            time.sleep(0.05)
        return f"tls/{address}:{PROXY_PORT}"

    def _stop_proxy(self) -> None:
        """Stop the emulator (it writes its report as it stops) and read the report."""
        if self.proxy is None or self.proxy.poll() is not None:
            return
        self.proxy.send_signal(signal.SIGTERM)
        self.proxy.wait(timeout=30)
        with contextlib.suppress(OSError, ValueError):
            self.proxy_report = json.loads((self.tmp_path / PROXY_REPORT_FILE).read_text())

    def _up(
        self, host: Host, args: Sequence[str], clock: Sequence[str] = ()
    ) -> subprocess.CompletedProcess:
        up = subprocess.run(
            host.argv([*clock, *self.teleop, "up", *args]),
            capture_output=True, text=True, timeout=180, stdin=subprocess.DEVNULL,
        )  # fmt: skip
        assert up.returncode == 0, up.stderr[-3000:]
        return up

    def start(self, settings: Sequence[str], *, strangers: bool = True) -> None:
        """Both sites up (the bundle handed over as scp would: the file only, its mode
        kept); with ``strangers``, the robot's router killed and back once the run is
        :data:`ROUTER_KILL_AT_SIM_S` in (records in flight through it are lost with it),
        and the strangers' attempts after."""
        self.tmp_path.mkdir(parents=True, exist_ok=True)
        up = self._up(self.robot, ["--mode", self.mode, "--site", "robot", "--site-listen",
                                   self.site_endpoint, "--run-dir", str(self.robot_dir),
                                   *settings])  # fmt: skip
        self.robot_up = up.stdout + up.stderr
        if self.second_robot is not None:
            bundle = self.tmp_path / "handed-over-arm1.json"
            shutil.copy2(self.robot_dir / robot_bundle_file("arm1"), bundle)
            self._up(self.second_robot, ["--site", "robot", "--join", str(bundle),
                                         "--run-dir", str(self.second_dir)])  # fmt: skip
        self._join()
        if not strangers:
            return
        # The robot's router killed mid-run: supervisord brings it back, and the
        # operator's router links to the new one.
        self._wait_sim_time(ROUTER_KILL_AT_SIM_S)
        stack = Stack.attach(self.robot_dir)
        self.killed_router_pid = stack.pid("robot_router")
        stack.signal_program("robot_router", signal.SIGKILL)
        deadline = time.monotonic() + 60
        while stack.status()["robot_router"] != "RUNNING" or (
            stack.pid("robot_router") == self.killed_router_pid
        ):
            assert time.monotonic() < deadline, "the robot's router did not come back"
            time.sleep(0.2)
        others = write_run_credentials(
            self.tmp_path / "other", ["operator_router"], ("arm0",), tls=True
        )
        self.strangers = {
            "another run's certificate": stranger_at(
                self.operator, self.site_endpoint, others["operator_router"]
            ),
            "no credentials": stranger_at(self.operator, self.site_endpoint, None),
        }
        status = subprocess.run(
            [*self.teleop, "status", "--run-dir", str(self.robot_dir)],
            capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL,
        )  # fmt: skip
        self.robot_status = status.stdout

    def _wait_sim_time(self, sim_s: float) -> None:
        """Until the plant's summary so far (written every 2 s while it runs) says it
        has simulated ``sim_s``."""
        deadline = time.monotonic() + HANG_S
        while time.monotonic() < deadline:
            summary = read_summary(self.robot_dir, "plant")
            if summary is not None and summary.get("sim_time_s", 0.0) >= sim_s:
                return
            time.sleep(0.2)
        raise AssertionError(f"the plant did not reach {sim_s} s of simulated time")

    def _join(self) -> None:
        """The operator site up, from the robot site's bundle (through the emulator when
        the link has one)."""
        bundle = self.tmp_path / "handed-over.json"
        shutil.copy2(self.robot_dir / OPERATOR_BUNDLE_FILE, bundle)
        via = ["--connect", self._start_proxy()] if self.link is not None else []
        up = self._up(self.operator, ["--site", "operator", "--join", str(bundle),
                                      "--run-dir", str(self.operator_dir), *via],
                      self.operator_clock)  # fmt: skip
        self.operator_up = up.stdout + up.stderr

    def finish_robots(self, robot_ids: Sequence[str], timeout_s: float) -> None:
        """A run of a robot site per robot: wait for each robot's plant (on its own
        site), stop every site, read the plants' and the hub's recorder's summaries."""
        dirs = [self.robot_dir, self.second_dir]
        for robot_id, run_dir in zip(robot_ids, dirs, strict=True):
            name = f"plant-{robot_id}"
            self.summaries[name] = wait_plant_end(run_dir, timeout_s, name)
        status = subprocess.run(
            [*self.teleop, "status", "--run-dir", str(self.second_dir)],
            capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL,
        )  # fmt: skip
        self.second_robot_status = status.stdout
        self.__exit__()
        self.summaries["recorder"] = json.loads(
            (self.robot_dir / "recorder.summary.json").read_text()
        )

    def finish(self) -> None:
        """Wait for the plant to finish, stop both sites, read every service's summary."""
        self.summaries["plant"] = wait_plant_end(self.robot_dir, HANG_S)
        self.__exit__()
        for run_dir, names in (
            (self.robot_dir, ["controller", "recorder", "robot_router"]),
            (self.operator_dir, ["haptic", "hmd", "operator", "operator_router"]),
        ):
            for name in names:
                self.summaries[name] = json.loads((run_dir / f"{name}.summary.json").read_text())


def stranger_at(host: Host, endpoint: str, credentials: Path | None) -> dict:
    """What a session dialling ``endpoint`` from ``host`` linked to and saw in 3 s: with
    another run's ``credentials``, or none at all."""
    script = (
        "import dataclasses, json, time\n"
        "from teleop.bus import session as bus\n"
        "from teleop.core.config import BusConfig\n"
        f"config = dataclasses.replace(BusConfig(endpoint={endpoint!r}), gossip=False, "
        f"credentials_file={str(credentials or '')!r})\n"
        "s = bus.open_session(config, listen=False)\n"
        "got = []\n"
        "sub = s.declare_subscriber('teleop/**', lambda sample: got.append(1))\n"
        "time.sleep(3)\n"
        "print(json.dumps({'routers': [str(z) for z in s.info.routers_zid()], "
        "'peers': [str(z) for z in s.info.peers_zid()], 'samples': len(got)}))\n"
        "sub.undeclare(); s.close()\n"
    )
    result = subprocess.run(
        host.argv([sys.executable, "-c", script]),
        capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    return json.loads(result.stdout.splitlines()[-1])
