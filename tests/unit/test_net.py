"""The run's loopback ports (teleop.core.net): distinct, held until released, and still
open to the listener they are meant for."""

from __future__ import annotations

import socket

import pytest

from teleop.core.net import LOOPBACK, LoopbackPorts


def _bind(port: int, *, reuse: bool) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    if reuse:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        s.bind((LOOPBACK, port))
    except OSError:
        s.close()
        raise
    return s


def test_ports_taken_for_one_run_are_distinct():
    with LoopbackPorts() as ports:
        taken = [ports.take() for _ in range(200)]
    assert len(set(taken)) == len(taken)


def test_a_held_port_is_refused_to_other_binds_until_released():
    ports = LoopbackPorts()
    port = ports.take()
    with pytest.raises(OSError):  # another launcher's check, or any program
        _bind(port, reuse=False)
    others = [_bind(0, reuse=True) for _ in range(200)]  # programs' own ephemeral listeners
    try:
        assert port not in {s.getsockname()[1] for s in others}
    finally:
        for s in others:
            s.close()
    ports.close()
    _bind(port, reuse=False).close()


def test_the_process_given_a_held_port_can_listen_there():
    with LoopbackPorts() as ports:
        port = ports.take()
        listener = _bind(port, reuse=True)  # as Zenoh's and Rust's listeners bind
        try:
            listener.listen()
            with socket.create_connection((LOOPBACK, port), timeout=2.0):
                pass
        finally:
            listener.close()
