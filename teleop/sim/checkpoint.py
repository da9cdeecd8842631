"""The plant's checkpoint: what a restarted plant needs to go on with the same run.

One file in the run directory, ``plant.checkpoint``, written by the plant service and read
back by its next incarnation (a fresh run directory has none: the launcher clears it).
It is memory-mapped: a header of int64 slots and two snapshot slots.

- The header's progress mark is updated every step: the newest state sent and when, the
  newest command accepted, the operator's task-done tick. A store into a shared file
  mapping costs no system call and outlives the process (the kernel keeps the page), so
  the next incarnation knows exactly where the stream stopped: its states continue the
  same ``seq`` without a gap, and it knows how many steps of physics it lost.
- Every ``plant.checkpoint_s`` of sim time a :class:`Snapshot`: MuJoCo's full
  integration state (``mj_getState`` with ``mjSTATE_INTEGRATION``: time, positions,
  velocities, activations, the solver's warm start, controls, applied forces; about
  1.2 KB for the shipped scene) plus what the plant's loop carries across steps (the
  brake's hold, the task-done tick, the summary's counters), about 1.9 KB in all. It is
  copied into the slot not in use, then the header names that slot: a process that dies
  mid-copy leaves the previous snapshot whole (a CRC guards the rest). A copy costs a few
  microseconds; a file write and rename (``os.replace``) costs milliseconds on ext4
  (renaming over a file flushes its data), more than a 1 ms step may spend.

Nothing is synced to disk: this guards against the plant process dying, not the machine
(a machine that dies ends the run anyway).
"""

from __future__ import annotations

import hashlib
import json
import mmap
import os
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

# A snapshot's first bytes and format version: another layout is refused with a reason.
MAGIC = b"TELEOPCK"
FORMAT_VERSION = 1
# MuJoCo's state components a checkpoint holds: everything integration depends on.
STATE_SPEC = mujoco.mjtState.mjSTATE_INTEGRATION
# The file: header slots (int64), then two snapshot slots of SLOT_BYTES each.
FILE_VERSION = 1
SLOT_BYTES = 1 << 16  # a snapshot is ~2 KB; a 7-DOF or richer scene still fits
SLOT_VERSION = 0
SLOT_STATE_SEQ = 1  # newest PLANT_STATE seq sent (== its step); -1: none
SLOT_STATE_NS = 2  # when it was sent (host monotonic clock, ns)
SLOT_COMMAND_SEQ = 3  # newest JOINT_COMMAND seq accepted; -1: none
SLOT_FINISH_TICK = 4  # the operator's TASK_DONE tick; -1: none
SLOT_ACTIVE = 5  # the snapshot slot that holds the newest whole snapshot; -1: none
SLOT_LENGTH = 6  # SLOT_LENGTH + i: bytes of snapshot slot i
HEADER_SLOTS = 8
HEADER_BYTES = HEADER_SLOTS * 8
FILE_BYTES = HEADER_BYTES + 2 * SLOT_BYTES
# A fresh header: no state, no command, no task-done tick, no snapshot.
FRESH_HEADER = (FILE_VERSION, -1, 0, -1, -1, -1, 0, 0)


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be resumed from; the message says why."""


def _plain(value: Any) -> Any:
    """A numpy scalar as the Python number JSON can write."""
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} in a checkpoint")


def model_id(model: mujoco.MjModel) -> str:
    """sha256 of the compiled model (``mj_saveModel``): a checkpoint resumes only into
    the very model that wrote it (same scene file, same scene overrides)."""
    buffer = np.zeros(mujoco.mj_sizeModel(model), dtype=np.uint8)
    mujoco.mj_saveModel(model, None, buffer)
    return hashlib.sha256(buffer.tobytes()).hexdigest()


def get_state(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """MuJoCo's integration state of ``data`` (float64, ``mj_stateSize`` long)."""
    state = np.empty(mujoco.mj_stateSize(model, STATE_SPEC))
    mujoco.mj_getState(model, data, state, STATE_SPEC)
    return state


def set_state(model: mujoco.MjModel, data: mujoco.MjData, state: np.ndarray) -> None:
    """Put ``state`` (from :func:`get_state` on the same model) into ``data``."""
    expected = mujoco.mj_stateSize(model, STATE_SPEC)
    if state.shape != (expected,):
        raise CheckpointError(f"MuJoCo state of {state.size} values, this model has {expected}")
    mujoco.mj_setState(model, data, state, STATE_SPEC)


@dataclass
class Snapshot:
    """One checkpoint: the physics and the plant loop's own state after ``step``.

    ``loop`` holds the loop's scalars and counters by name
    (:meth:`teleop.sim.stepping.PlantStepCore.snapshot` decides them); ``hold_q_rad`` is
    the brake's hold position (None: not braking).
    """

    model_id: str
    step: int
    t_ns: int  # when it was taken (host monotonic clock)
    mujoco_state: np.ndarray
    hold_q_rad: np.ndarray | None = None
    loop: dict[str, Any] = field(default_factory=dict)

    def encode(self) -> bytes:
        """MAGIC, a u32 header length, the JSON header, then the float64 arrays."""
        arrays = [self.mujoco_state]
        if self.hold_q_rad is not None:
            arrays.append(self.hold_q_rad)
        body = b"".join(np.ascontiguousarray(a, dtype="<f8").tobytes() for a in arrays)
        header = {
            "version": FORMAT_VERSION,
            "model_id": self.model_id,
            "step": self.step,
            "t_ns": self.t_ns,
            "state_size": int(self.mujoco_state.size),
            "hold_size": None if self.hold_q_rad is None else int(self.hold_q_rad.size),
            "loop": self.loop,
            "body_crc32": zlib.crc32(body),
        }
        text = json.dumps(header, separators=(",", ":"), default=_plain).encode()
        return MAGIC + len(text).to_bytes(4, "little") + text + body

    @classmethod
    def decode(cls, data: bytes) -> Snapshot:
        """The snapshot in ``data``; :class:`CheckpointError` if it is not a whole one."""
        if not data.startswith(MAGIC):
            raise CheckpointError("not a plant checkpoint (bad magic)")
        start = len(MAGIC) + 4
        length = int.from_bytes(data[len(MAGIC) : start], "little")
        try:
            header = json.loads(data[start : start + length])
        except ValueError as exc:
            raise CheckpointError(f"unreadable header: {exc}") from None
        if header.get("version") != FORMAT_VERSION:
            raise CheckpointError(f"format version {header.get('version')}, need {FORMAT_VERSION}")
        body = data[start + length :]
        if zlib.crc32(body) != header["body_crc32"]:
            raise CheckpointError("damaged (checksum mismatch)")
        values = np.frombuffer(body, dtype="<f8")
        n_state, n_hold = header["state_size"], header["hold_size"]
        if values.size != n_state + (n_hold or 0):
            raise CheckpointError("damaged (body size)")
        return cls(
            model_id=header["model_id"],
            step=int(header["step"]),
            t_ns=int(header["t_ns"]),
            mujoco_state=values[:n_state].copy(),
            hold_q_rad=None if n_hold is None else values[n_state:].copy(),
            loop=header["loop"],
        )


@dataclass(frozen=True)
class Progress:
    """Where the plant's previous incarnation stopped (the file's progress mark)."""

    state_seq: int = -1
    state_ns: int = 0
    command_seq: int = -1
    finish_tick: int = -1

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class CheckpointStore:
    """``plant.checkpoint`` (see the module's docstring), memory-mapped.

    :attr:`marks` is a numpy view of the header: ``marks[SLOT_STATE_SEQ] = seq`` is the
    whole cost of a progress update. ``path=None``: everything lives in memory only
    (tests, runs without a run directory). The mapping lasts as long as the process (a
    Zenoh callback may still hold a view of it while the service closes).
    """

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self.found = False  # a previous incarnation's file was there (a restart)
        self.writes = 0
        self.bytes_per_write = 0
        if path is None:
            self._buffer: mmap.mmap | bytearray = bytearray(FILE_BYTES)
        else:
            self.found = path.exists()
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
            try:
                if os.fstat(fd).st_size != FILE_BYTES:
                    os.ftruncate(fd, FILE_BYTES)  # a damaged file's header is checked below
                self._buffer = mmap.mmap(fd, FILE_BYTES)
            finally:
                os.close(fd)
        self.marks = np.frombuffer(self._buffer, dtype=np.int64, count=HEADER_SLOTS)
        if not self.found:
            self.marks[:] = FRESH_HEADER

    def progress(self) -> Progress:
        """The progress mark as it is on file (the previous incarnation's, on a restart)."""
        m = self.marks
        return Progress(
            state_seq=int(m[SLOT_STATE_SEQ]),
            state_ns=int(m[SLOT_STATE_NS]),
            command_seq=int(m[SLOT_COMMAND_SEQ]),
            finish_tick=int(m[SLOT_FINISH_TICK]),
        )

    def load(self, expected_model_id: str) -> Snapshot | None:
        """The newest whole snapshot (None: none was taken), if it belongs to
        ``expected_model_id``; else :class:`CheckpointError` with the reason."""
        m = self.marks
        if int(m[SLOT_VERSION]) != FILE_VERSION:
            raise CheckpointError(f"{self.path}: not a checkpoint file of version {FILE_VERSION}")
        active = int(m[SLOT_ACTIVE])
        if active < 0:
            return None
        if active > 1 or not 0 < int(m[SLOT_LENGTH + active]) <= SLOT_BYTES:
            raise CheckpointError(f"{self.path}: damaged header")
        start = HEADER_BYTES + active * SLOT_BYTES
        length = int(m[SLOT_LENGTH + active])
        snapshot = Snapshot.decode(bytes(self._buffer[start : start + length]))
        if snapshot.model_id != expected_model_id:
            raise CheckpointError(
                f"{self.path} was written for another model "
                f"({snapshot.model_id[:12]}, this one is {expected_model_id[:12]})"
            )
        return snapshot

    def save(self, snapshot: Snapshot) -> None:
        """Copy ``snapshot`` into the slot not in use, then name it in the header."""
        data = snapshot.encode()
        if len(data) > SLOT_BYTES:
            raise CheckpointError(f"a snapshot of {len(data)} bytes exceeds {SLOT_BYTES}")
        slot = 1 - max(int(self.marks[SLOT_ACTIVE]), 0)
        start = HEADER_BYTES + slot * SLOT_BYTES
        self._buffer[start : start + len(data)] = data
        self.marks[SLOT_LENGTH + slot] = len(data)
        self.marks[SLOT_ACTIVE] = slot  # the one store that makes it the checkpoint
        self.writes += 1
        self.bytes_per_write = len(data)
