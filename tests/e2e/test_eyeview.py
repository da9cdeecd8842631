"""The eye view in a real services run: frames reach the recorder over shared memory (or
the socket without it) and land in the .rrd."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from teleop.core.config import load_config
from teleop.viz import entities as ent
from tests.e2e.outcome import assert_ran
from tests.integration.test_recorder import read_rrd

RUN_TIMEOUT_S = 300


def _run(tmp_path: Path, name: str, *overrides: str) -> dict:
    out = tmp_path / f"{name}.json"
    sets = [arg for o in overrides for arg in ("--set", o)]
    result = subprocess.run(
        [
            sys.executable, "-m", "teleop.cli", "run", "path-following", "--mode", "realtime",
            "--duration", "2", "--set", "run.settle_s=1", *sets,
            "--run-dir", str(tmp_path / name), "--summary-json", str(out), "--quiet",
        ],
        capture_output=True, text=True, timeout=RUN_TIMEOUT_S, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    summary = json.loads(out.read_text()) if out.exists() else None
    assert_ran(result.returncode, summary, result.stderr)
    return summary


def test_frames_reach_the_recorder_over_shared_memory_and_land_in_the_rrd(tmp_path):
    summary = _run(tmp_path, "shm", "eyeview.rate_hz=20")
    eye = summary["eye_view"]
    assert eye["frames_published"] > 0
    assert eye["frames_received"] == eye["frames_published"]
    assert eye["frames_received_shm"] == eye["frames_received"]  # every one over SHM
    assert summary["dropped_messages"] == 0
    latency = eye["latency_ms"]["publish_to_received_ms"]
    assert latency["count"] == eye["frames_received"] and latency["p50"] > 0

    data = read_rrd(Path(summary["rrd"]))
    cols = data[ent.ENTITY_EYE_VIEW]
    blobs = cols["EncodedImage:blob"]
    assert len(blobs) == eye["frames_received"]
    assert all(m == ["image/jpeg"] for m in cols["EncodedImage:media_type"])
    config = load_config()
    image = Image.open(io.BytesIO(bytes(blobs[0][0])))
    assert image.size == (config.eyeview.width_px, config.eyeview.height_px)
    # Logged at the plant's sim time of the state each frame shows (whole plant ticks,
    # within the run), not at arrival time.
    sim_ns = np.array(cols[ent.TIMELINE_SIM])
    step_ns = round(config.tick_s * 1e9)
    assert np.all(sim_ns % step_ns == 0) and sim_ns.max() <= 2 * 10**9
    assert len(set(cols[ent.TIMELINE_SOURCE])) == len(blobs)


def test_without_shared_memory_the_frames_come_over_the_socket(tmp_path):
    """The SHM assertion above can fail: with SHM off the same frames arrive inline.

    Also logs them raw (``jpeg_quality=0``): RGB images of the configured size."""
    summary = _run(tmp_path, "noshm", "bus.shm=false", "eyeview.jpeg_quality=0")
    eye = summary["eye_view"]
    assert eye["frames_received"] > 0
    assert eye["frames_received_shm"] == 0
    buffers = read_rrd(Path(summary["rrd"]))[ent.ENTITY_EYE_VIEW]["Image:buffer"]
    assert len(buffers) == eye["frames_received"]
    cfg = load_config().eyeview
    assert {len(b[0]) for b in buffers} == {cfg.width_px * cfg.height_px * 3}
