"""``teleop latency --across-sites``: real routers (two processes), a real answering
end, the network emulator between the routers; a short measurement."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

DELAY_MS = 20.0
PINGS = 200


def latency(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "teleop.cli", "latency", *args],
        capture_output=True, text=True, stdin=subprocess.DEVNULL, timeout=240, check=False,
    )  # fmt: skip


def test_the_round_trip_across_two_sites_direct_routed_and_delayed(tmp_path: Path):
    out = tmp_path / "sites.json"
    done = latency("--across-sites", "--rounds", "1", "--pings", str(PINGS),
                   "--delays-ms", f"{DELAY_MS:g}", "--json", str(out))  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(out.read_text())
    (entry,) = report["rounds"]
    assert entry["direct"]["received"] == entry["routers"]["received"] == PINGS
    (delayed,) = report["delays"]
    assert delayed["received"] == PINGS and delayed["delay_ms"] == DELAY_MS
    # The emulator holds each byte the delay each way (how much more is the machine's: a
    # figure for the report, not a test).
    assert delayed["p50_ms"] >= 2 * DELAY_MS
    assert 0 < entry["direct"]["p50_ms"] < delayed["p50_ms"]  # no emulator on that path
    assert report["lost"] == 0
    assert "| routers + netem | 20 ms |" in done.stdout


def test_across_sites_refuses_the_stack_runs_options(tmp_path: Path):
    done = latency("--across-sites", "--png", str(tmp_path / "x.png"), "--duration", "5")
    assert done.returncode == 2
    assert "one-host stack run's: drop --duration, --png" in done.stderr
    done = latency("--delays-ms", "10")
    assert done.returncode == 2 and "with --across-sites only" in done.stderr
    done = latency("--with-stack")
    assert done.returncode == 2 and "with --across-sites only" in done.stderr
    done = latency("--across-sites", "--delays-ms", "10,-1")
    assert done.returncode == 2 and "delays must be finite and >= 0 ms" in done.stderr
