"""The plant's checkpoint: what a restarted plant needs to go on with the same run.

Two files in the run directory, both written by the plant service and read back by its
next incarnation (a fresh run directory has neither: the launcher clears them):

- ``plant.checkpoint`` (:class:`Snapshot`), every ``plant.checkpoint_s`` of sim time:
  MuJoCo's full integration state (``mj_getState`` with ``mjSTATE_INTEGRATION``: time,
  positions, velocities, actuator activations, the constraint solver's warm start,
  controls, applied forces; about 1.2 KB for the shipped scene) plus what the plant's
  loop carries across steps (step number, the operator's task-done tick, the brake's
  hold, the counters of the summary). Taken and encoded in the step (a few us), written
  by a thread of its own: a write and rename costs 0.5 ms and up to 15 ms on ext4 (it
  flushes the data of a file renamed over another), far more than a step may spend.
  Written atomically (a temporary file, then ``os.replace``), so a reader sees the
  previous checkpoint or the new one, never half.
- ``plant.progress`` (:class:`ProgressMark`), updated every step: a few integers in a
  memory-mapped file (the newest state sent, when, the newest command accepted, the
  task-done tick). A store into a shared file mapping costs no system call and survives
  the process (the kernel keeps the page), so the next incarnation knows exactly where
  the stream stopped: its states continue the same ``seq`` without a gap, and it knows
  how many steps of physics after the checkpoint were lost.

Neither file is synced to disk: they guard against the plant process dying, not the
machine (a machine that dies ends the run anyway).
"""

from __future__ import annotations

import hashlib
import json
import logging
import mmap
import os
import threading
import time
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

logger = logging.getLogger(__name__)

# The checkpoint file's first bytes and format version: another file, or another layout,
# is refused with a reason rather than misread.
MAGIC = b"TELEOPCK"
FORMAT_VERSION = 1
# MuJoCo's state components a checkpoint holds: everything integration depends on.
STATE_SPEC = mujoco.mjtState.mjSTATE_INTEGRATION
# The progress mark's slots (int64 each) and their meaning.
PROGRESS_VERSION = 1
# Checkpoint writes whose duration the store keeps (the newest ones).
WRITE_TIMES_KEPT = 1000
PROGRESS_SLOTS = 5
SLOT_VERSION = 0
SLOT_STATE_SEQ = 1  # newest PLANT_STATE seq sent (== its step); -1: none
SLOT_STATE_NS = 2  # when it was sent (host monotonic clock, ns)
SLOT_COMMAND_SEQ = 3  # newest JOINT_COMMAND seq accepted; -1: none
SLOT_FINISH_TICK = 4  # the operator's TASK_DONE tick; -1: none


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

    ``loop`` holds the loop's scalars and counters by name (:meth:`PlantLoop.snapshot`
    decides them); ``hold_q_rad`` is the brake's hold position (None: not braking).
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
    """Where the plant's previous incarnation stopped (:class:`ProgressMark`)."""

    state_seq: int = -1
    state_ns: int = 0
    command_seq: int = -1
    finish_tick: int = -1

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class ProgressMark:
    """A few int64 slots in a memory-mapped file (see the module's docstring).

    :attr:`slots` is a numpy view of the mapping: ``slots[SLOT_STATE_SEQ] = seq`` is the
    whole cost of an update. ``path=None``: the slots live in memory only (tests, runs
    without a run directory). The mapping lasts as long as the process (a callback may
    still hold a view of it while the service closes).
    """

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self._map: mmap.mmap | None = None
        if path is None:
            self.slots = np.zeros(PROGRESS_SLOTS, dtype=np.int64)
        else:
            size = PROGRESS_SLOTS * 8
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
            try:
                os.ftruncate(fd, size)
                self._map = mmap.mmap(fd, size)
            finally:
                os.close(fd)
            self.slots = np.frombuffer(self._map, dtype=np.int64)
        self.slots[:] = [PROGRESS_VERSION, -1, 0, -1, -1]

    @staticmethod
    def read(path: Path) -> Progress | None:
        """What a previous incarnation left in ``path`` (None: no usable mark)."""
        try:
            raw = Path(path).read_bytes()
        except OSError:
            return None
        if len(raw) != PROGRESS_SLOTS * 8:
            return None
        slots = np.frombuffer(raw, dtype=np.int64)
        if slots[SLOT_VERSION] != PROGRESS_VERSION:
            return None
        return Progress(
            state_seq=int(slots[SLOT_STATE_SEQ]),
            state_ns=int(slots[SLOT_STATE_NS]),
            command_seq=int(slots[SLOT_COMMAND_SEQ]),
            finish_tick=int(slots[SLOT_FINISH_TICK]),
        )


class CheckpointStore:
    """The checkpoint and progress files of one plant, and the thread that writes the
    checkpoints (:meth:`submit`; :meth:`close` writes the last one and joins it)."""

    def __init__(self, checkpoint_path: Path, progress_path: Path) -> None:
        self.checkpoint_path = Path(checkpoint_path)
        self.progress_path = Path(progress_path)
        self.writes = 0
        self.failed_writes = 0
        self.bytes_per_write = 0
        self.write_us: list[float] = []  # the newest writes' durations
        self._cond = threading.Condition()
        self._pending: bytes | None = None
        self._closed = False
        self._thread: threading.Thread | None = None

    def exists(self) -> bool:
        """Whether a previous incarnation of this run left a checkpoint."""
        return self.checkpoint_path.exists()

    def submit(self, snapshot: Snapshot) -> None:
        """Encode ``snapshot`` now and have the writer thread write it (a newer one
        replaces one still waiting)."""
        data = snapshot.encode()
        with self._cond:
            if self._closed:
                return
            if self._thread is None:
                self._thread = threading.Thread(
                    target=self._write_loop, name="checkpoint-writer", daemon=True
                )
                self._thread.start()
            self._pending = data
            self._cond.notify()

    def _write_loop(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending is not None or self._closed)
                data, self._pending = self._pending, None
            if data is not None:
                self.save(data)
            elif self._closed:
                return

    def save(self, data: bytes) -> None:
        """Write an encoded snapshot atomically (tmp file, then rename over the old one);
        a failure is logged (first one) and counted, the next write tries again."""
        start_ns = time.perf_counter_ns()
        tmp = self.checkpoint_path.with_name(self.checkpoint_path.name + ".tmp")
        try:
            with open(tmp, "wb") as f:
                f.write(data)
            os.replace(tmp, self.checkpoint_path)
        except OSError as exc:
            self.failed_writes += 1
            if self.failed_writes == 1:
                logger.error("cannot write the checkpoint %s: %s", self.checkpoint_path, exc)
            return
        self.writes += 1
        self.bytes_per_write = len(data)
        self.write_us.append((time.perf_counter_ns() - start_ns) / 1e3)
        del self.write_us[:-WRITE_TIMES_KEPT]

    def close(self) -> None:
        """Write what is pending, stop the writer thread. Safe to call twice."""
        with self._cond:
            self._closed = True
            self._cond.notify()
            thread = self._thread
        if thread is not None:
            thread.join()

    def load(self, expected_model_id: str) -> Snapshot:
        """The checkpoint on file, if it belongs to ``expected_model_id``; else
        :class:`CheckpointError` with the reason."""
        try:
            data = self.checkpoint_path.read_bytes()
        except OSError as exc:
            raise CheckpointError(f"cannot read {self.checkpoint_path}: {exc}") from None
        snapshot = Snapshot.decode(data)
        if snapshot.model_id != expected_model_id:
            raise CheckpointError(
                f"{self.checkpoint_path} was written for another model "
                f"({snapshot.model_id[:12]}, this one is {expected_model_id[:12]})"
            )
        return snapshot

    def progress(self) -> Progress | None:
        """The previous incarnation's progress mark (None: none usable)."""
        return ProgressMark.read(self.progress_path)

    def open_progress(self) -> ProgressMark:
        """This incarnation's progress mark (read :meth:`progress` first: this resets it)."""
        return ProgressMark(self.progress_path)
