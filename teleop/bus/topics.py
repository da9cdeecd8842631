"""The topic registry: every Zenoh key expression of a robot, built from its id.

Services take a :class:`Topics` and never spell a key string themselves. The keys come
from the graph description (:data:`teleop.bus.graph.STREAMS`), so a rename or a new
stream is one change there; all keys live under ``teleop/<robot_id>/``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from teleop.bus.graph import ALIVE_TOKEN, PROTOCOL_TOKEN, READY_TOKEN, RELEASED_TOKEN, ROOT, STREAMS

__all__ = ["ROOT", "Topics"]


def _key(robot_id: str, stream: str) -> str:
    return f"{ROOT}/{robot_id}/{stream}"


@dataclass(frozen=True)
class Topics:
    """Key expressions of one robot (``robot_id`` from ``RobotConfig``): one attribute per
    stream of the graph (what each carries: teleop/bus/graph.py, docs/protocol.md)."""

    robot_id: str
    plant_state: str = field(init=False)
    plant_state_batch: str = field(init=False)
    tool_pose: str = field(init=False)
    objects: str = field(init=False)
    joint_command: str = field(init=False)
    control_status: str = field(init=False)
    plant_events: str = field(init=False)
    operator_events: str = field(init=False)
    controller_events: str = field(init=False)
    haptic_state: str = field(init=False)
    haptic_state_batch: str = field(init=False)
    hand_input: str = field(init=False)
    force_feedback: str = field(init=False)
    force_feedback_batch: str = field(init=False)
    head_pose: str = field(init=False)
    teleop_status: str = field(init=False)
    eye_view: str = field(init=False)
    alive_all: str = field(init=False)  # every service's liveliness token
    ready_all: str = field(init=False)  # every service's "ready" token
    protocol_all: str = field(init=False)  # the protocol version tokens
    released_all: str = field(init=False)  # the launcher's lockstep release tokens

    def __post_init__(self) -> None:
        if not self.robot_id or any(c in self.robot_id for c in "/*$?#"):
            raise ValueError(f"robot_id {self.robot_id!r}: non-empty, no '/', '*', '$', '?', '#'")
        for stream in STREAMS:
            object.__setattr__(self, stream.name, _key(self.robot_id, stream.key))
        object.__setattr__(self, "alive_all", _key(self.robot_id, f"{ALIVE_TOKEN}/*"))
        object.__setattr__(self, "ready_all", _key(self.robot_id, f"{READY_TOKEN}/*"))
        object.__setattr__(self, "protocol_all", _key(self.robot_id, f"{PROTOCOL_TOKEN}/*"))
        object.__setattr__(self, "released_all", _key(self.robot_id, f"{RELEASED_TOKEN}/*"))

    def alive(self, service: str, *, ready: bool = False) -> str:
        """Liveliness token key of one service, e.g. ``teleop/arm0/alive/plant``;
        ``ready``: its second token, ``teleop/arm0/ready/plant``, declared once it sees
        every peer of its stack (:meth:`teleop.bus.service.Service.become_ready`)."""
        if not service or any(c in service for c in "/*$?#"):
            raise ValueError(f"service name {service!r}: non-empty, one key chunk")
        return _key(self.robot_id, f"{READY_TOKEN if ready else ALIVE_TOKEN}/{service}")

    def protocol(self, version: int) -> str:
        """Liveliness token key of a protocol version, e.g. ``teleop/arm0/protocol/8``."""
        return _key(self.robot_id, f"{PROTOCOL_TOKEN}/{int(version)}")

    def released(self, sim_ns: int) -> str:
        """Liveliness token key releasing a lockstep plant held at sim instant ``sim_ns``
        (and before), e.g. ``teleop/arm0/released/1500000000``."""
        if sim_ns < 0:
            raise ValueError(f"sim instant {sim_ns} ns: not before the run's start")
        return _key(self.robot_id, f"{RELEASED_TOKEN}/{int(sim_ns)}")

    def released_ns_of(self, key: str) -> int | None:
        """The sim instant (ns) of a release token's key (:meth:`released`'s inverse);
        None for a key that is not one (its last chunk not a plain decimal number)."""
        prefix, _, chunk = str(key).rpartition("/")
        if prefix != _key(self.robot_id, RELEASED_TOKEN) or not (
            chunk.isascii() and chunk.isdigit()
        ):
            return None
        return int(chunk)

    def service_of(self, alive_key: str) -> str:
        """The service name of a liveliness key (inverse of :meth:`alive`)."""
        return str(alive_key).rsplit("/", 1)[-1]


# Every stream of the graph has its attribute, and every attribute its stream.
_ATTRIBUTES = {f.name for f in fields(Topics)} - {
    "robot_id",
    "alive_all",
    "ready_all",
    "protocol_all",
    "released_all",
}
assert _ATTRIBUTES == {s.name for s in STREAMS}, sorted(_ATTRIBUTES ^ {s.name for s in STREAMS})
