"""The one topic registry: every Zenoh key expression of a robot, built from its id.

Services take a :class:`Topics` and never spell a key string themselves, so a rename
or a new robot id is one change here. All keys live under ``teleop/<robot_id>/``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

ROOT = "teleop"  # first chunk of every key expression of the project


def _key(robot_id: str, stream: str) -> str:
    return f"{ROOT}/{robot_id}/{stream}"


@dataclass(frozen=True)
class Topics:
    """Key expressions of one robot (``robot_id`` from ``RobotConfig``)."""

    robot_id: str
    plant_state: str = field(init=False)  # plant -> all, PLANT_STATE (with contact), 1 kHz
    # plant -> observers (recorder, eye view): the same records, several per message
    plant_state_batch: str = field(init=False)
    haptic_state_batch: str = field(init=False)  # haptic -> recorder, HAPTIC_STATE batches
    force_feedback_batch: str = field(init=False)  # controller -> recorder, FORCE_FEEDBACK batches
    tool_pose: str = field(init=False)  # plant -> all, TOOL_POSE, plant.scene_rate_hz
    objects: str = field(init=False)  # plant -> recorder/operator, OBJECT_POSES
    joint_command: str = field(init=False)  # controller -> plant, JOINT_COMMAND
    control_status: str = field(init=False)  # controller -> recorder, CONTROL_STATUS
    events: str = field(init=False)  # plant/controller -> all, RUN_EVENT
    haptic_state: str = field(init=False)  # haptic -> controller, HAPTIC_STATE, 1 kHz
    hand_input: str = field(init=False)  # operator -> haptic, HAND_INPUT, 100 Hz
    force_feedback: str = field(init=False)  # controller -> haptic, FORCE_FEEDBACK, 1 kHz
    head_pose: str = field(init=False)  # hmd -> controller/operator, HEAD_POSE, 90 Hz
    teleop_status: str = field(init=False)  # controller -> recorder/operator, 100 Hz
    eye_view: str = field(init=False)  # eyeview -> recorder, EYE_VIEW, eyeview.rate_hz (SHM)
    alive_all: str = field(init=False)  # every service's liveliness token
    ready_all: str = field(init=False)  # every service's "ready" token (Service.become_ready)

    def __post_init__(self) -> None:
        if not self.robot_id or any(c in self.robot_id for c in "/*$?#"):
            raise ValueError(f"robot_id {self.robot_id!r}: non-empty, no '/', '*', '$', '?', '#'")
        streams = {
            "plant_state": "state/plant",
            "plant_state_batch": "state/plant/batch",
            "haptic_state_batch": "haptic/state/batch",
            "force_feedback_batch": "haptic/feedback/batch",
            "tool_pose": "state/tool_pose",
            "objects": "state/objects",
            "joint_command": "cmd/joint_velocity",
            "control_status": "control/status",
            "events": "events",
            "haptic_state": "haptic/state",
            "hand_input": "operator/hand",
            "force_feedback": "haptic/feedback",
            "head_pose": "hmd/pose",
            "teleop_status": "control/teleop",
            "eye_view": "view/eye",
            "alive_all": "alive/*",
            "ready_all": "ready/*",
        }
        for name, stream in streams.items():
            object.__setattr__(self, name, _key(self.robot_id, stream))

    @property
    def all_streams(self) -> str:
        """Every key of this robot (for a recorder that logs everything)."""
        return _key(self.robot_id, "**")

    def floor(self, leg: str) -> str:
        """Key of one leg of the transport-floor relay chain (``teleop latency``), e.g.
        ``teleop/arm0/floor/command``: apart from the real streams, same QoS and config."""
        if not leg or any(c in leg for c in "/*$?#"):
            raise ValueError(f"leg name {leg!r}: non-empty, one key chunk")
        return _key(self.robot_id, f"floor/{leg}")

    def alive(self, service: str, *, ready: bool = False) -> str:
        """Liveliness token key of one service, e.g. ``teleop/arm0/alive/plant``;
        ``ready``: its second token, ``teleop/arm0/ready/plant``, declared once it sees
        every peer of its stack (:meth:`teleop.bus.service.Service.become_ready`)."""
        if not service or any(c in service for c in "/*$?#"):
            raise ValueError(f"service name {service!r}: non-empty, one key chunk")
        return _key(self.robot_id, f"{'ready' if ready else 'alive'}/{service}")

    def service_of(self, alive_key: str) -> str:
        """The service name of a liveliness key (inverse of :meth:`alive`)."""
        return str(alive_key).rsplit("/", 1)[-1]
