"""The outside examples (examples/) against a stack of another protocol version: they
stop at its first record and say which version it speaks, instead of waiting out their
time-out on records they cannot read. A real Zenoh session plays the stack."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh

from teleop.bus.messages import FORCE_FEEDBACK, PLANT_STATE, PROTOCOL_VERSION
from tests.integration.receiving import TIMEOUT_S, free_endpoint

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
OTHER_VERSION = PROTOCOL_VERSION - 1


@pytest.mark.parametrize(
    ("example", "peers", "stream", "schema"),
    [
        ("outside_controller.py", ("plant", "recorder"), "state/plant", PLANT_STATE),
        ("outside_haptic.py", ("plant", "controller", "hmd", "operator", "recorder"),
         "haptic/feedback", FORCE_FEEDBACK),
    ],
)  # fmt: skip
def test_an_example_stops_at_a_stack_of_another_protocol_version(
    tmp_path, example, peers, stream, schema
):
    endpoint = free_endpoint()
    stack = zenoh.Config()
    stack.insert_json5("listen/endpoints", json.dumps([endpoint]))
    stack.insert_json5("scouting/multicast/enabled", "false")
    client = tmp_path / "client.json5"
    client.write_text(json.dumps({
        "mode": "peer",
        "connect": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "metadata": {"robot_id": "arm0"},
    }))  # fmt: skip
    record = schema.new()
    data = bytearray(record.tobytes())
    struct.pack_into("<H", data, 0, OTHER_VERSION)  # the header's version field
    session = zenoh.open(stack)
    tokens = [session.liveliness().declare_token(f"teleop/arm0/alive/{p}") for p in peers]
    process = subprocess.Popen(
        [sys.executable, str(EXAMPLES / example), str(client)],
        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        publisher = session.declare_publisher(f"teleop/arm0/{stream}")
        deadline = time.monotonic() + TIMEOUT_S
        while process.poll() is None and time.monotonic() < deadline:
            publisher.put(bytes(data))  # until the client has linked and read one
            time.sleep(0.05)
        assert process.poll() is not None, f"{example} still waits after {TIMEOUT_S} s"
        _, stderr = process.communicate(timeout=10)
    finally:
        if process.poll() is None:
            process.kill()
        for token in tokens:
            token.undeclare()
        session.close()
    assert process.returncode == 1
    assert f"protocol version {OTHER_VERSION}, this" in stderr
