"""Zenoh key expressions of one robot's servo system, and the table of what travels on each.

Every key is `<prefix>/<robot>/<suffix>`. With `rmw_domain_id` set, the ROS-typed topics (CDR payloads) move to
the rmw_zenoh layout `<domain_id>/<prefix>/<robot>/<suffix>/<pkg>::msg::dds_::<Type>_/<type hash>` so that ROS 2
nodes on rmw_zenoh see them as the ROS topic `/<prefix>/<robot>/<suffix>` (publishers then attach
`rmw.RmwPublisherIdentity.next_attachment()` to each sample); JSON control-plane keys do not change.

`TOPICS` is the single source of the key table in `docs/protocol.md` (a test keeps them equal).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from ddvs_service.protocol.rmw import rmw_zenoh_key

_WILDCARDS = "*$?#"
_ROS_TOKEN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclass(frozen=True)
class TopicSpec:
    """What one key carries. `priority`/`congestion` name `zenoh.Priority`/`zenoh.CongestionControl` members."""

    suffix: str
    payload: str
    ros_type: str | None
    publisher: str
    subscribers: str
    priority: str
    congestion: str
    express: bool
    delivery: str


TOPICS: dict[str, TopicSpec] = {
    "camera_image": TopicSpec(
        "camera/image", "sensor_msgs/msg/Image (CDR)", "sensor_msgs/msg/Image",
        "camera, sim", "serve, monitor, record", "DATA_HIGH", "DROP", False, "latest only (RingChannel(1))",
    ),
    "camera_info": TopicSpec(
        "camera/info", "sensor_msgs/msg/CameraInfo (CDR)", "sensor_msgs/msg/CameraInfo",
        "camera, sim (with every image)", "serve, monitor, record", "DATA", "DROP", False, "latest only",
    ),
    "servo_twist": TopicSpec(
        "servo/twist", "geometry_msgs/msg/TwistStamped (CDR), camera frame", "geometry_msgs/msg/TwistStamped",
        "serve", "bridge, sim, record", "REAL_TIME", "DROP", True, "latest only",
    ),
    "servo_status": TopicSpec(
        "servo/status", "JSON `Status`", None,
        "serve (every frame)", "monitor, record, ctl", "DATA", "DROP", False, "every sample",
    ),
    "servo_config": TopicSpec(
        "servo/config", "JSON servo configuration object", None,
        "serve (at start and on change)", "monitor, record", "DATA", "BLOCK", False, "every sample",
    ),
    "servo_state": TopicSpec(
        "servo/state", "JSON `StateSnapshot`", None,
        "serve (on every state change)", "monitor, record, ctl", "DATA", "BLOCK", False, "every sample",
    ),
    "servo_reference": TopicSpec(
        "servo/reference", "sensor_msgs/msg/Image (CDR)", "sensor_msgs/msg/Image",
        "serve (when a reference is set)", "monitor, record", "DATA", "BLOCK", False, "latest only",
    ),
    "servo_command": TopicSpec(
        "servo/command", "query: JSON `Command` → reply: JSON `Reply`", None,
        "serve (queryable)", "ctl, experiment (get)", "INTERACTIVE_HIGH", "BLOCK", False, "query/reply",
    ),
    "arm_joint_states": TopicSpec(
        "arm/joint_states", "sensor_msgs/msg/JointState (CDR)", "sensor_msgs/msg/JointState",
        "sim (arm)", "bridge, record", "REAL_TIME", "DROP", True, "latest only",
    ),
    "arm_joint_velocity": TopicSpec(
        "arm/joint_velocity", "sensor_msgs/msg/JointState (CDR), `velocity` only", "sensor_msgs/msg/JointState",
        "bridge", "sim (arm)", "REAL_TIME", "DROP", True, "latest only",
    ),
    "arm_ground_truth": TopicSpec(
        "arm/ground_truth", "JSON `GroundTruth` (evaluation only)", None,
        "sim", "record, experiment", "DATA_LOW", "DROP", False, "every sample",
    ),
    "liveliness": TopicSpec(
        "servo/alive", "liveliness token", None,
        "serve (held while running)", "monitor, bridge (stop on loss)", "DATA", "BLOCK", False, "liveliness",
    ),
}  # fmt: skip


def _validate_part(what: str, value: str) -> None:
    if not isinstance(value, str) or not value:
        raise ValueError(f"Keys.{what} = {value!r}: expected a non-empty string")
    bad = [c for c in _WILDCARDS if c in value]
    if bad:
        raise ValueError(f"Keys.{what} = {value!r} contains wildcard characters {bad}; expected a plain key")
    if value.startswith("/") or value.endswith("/") or "//" in value:
        raise ValueError(f"Keys.{what} = {value!r}: expected '/'-separated non-empty chunks, no leading/trailing '/'")


@dataclass(frozen=True)
class Keys:
    """Key expressions under `<prefix>/<robot>`; `rmw_domain_id` switches ROS-typed topics to rmw_zenoh keys."""

    prefix: str = "ddvs"
    robot: str = "robot0"
    rmw_domain_id: int | None = None

    def __post_init__(self) -> None:
        _validate_part("prefix", self.prefix)
        _validate_part("robot", self.robot)
        if self.rmw_domain_id is not None:
            for token in f"{self.prefix}/{self.robot}".split("/"):
                if not _ROS_TOKEN.match(token):
                    raise ValueError(
                        f"'{token}' is not a valid ROS name token (rmw_zenoh mode): expected [A-Za-z_][A-Za-z0-9_]*"
                    )
            rmw_zenoh_key(self.rmw_domain_id, "check", "sensor_msgs/msg/Image")  # validates the domain id

    @property
    def base(self) -> str:
        return f"{self.prefix}/{self.robot}"

    @property
    def rmw(self) -> bool:
        """True when ROS-typed topics use rmw_zenoh keys (and need `rmw` attachments)."""
        return self.rmw_domain_id is not None

    def ros_topic(self, name: str) -> str:
        """The ROS topic name of entry `name` of `TOPICS`, e.g. `/ddvs/robot0/camera/image`."""
        return f"/{self.base}/{TOPICS[name].suffix}"

    def key(self, name: str) -> str:
        """The key expression of entry `name` of `TOPICS` (rmw_zenoh layout for ROS types in rmw mode)."""
        try:
            spec = TOPICS[name]
        except KeyError:
            raise KeyError(f"unknown topic {name!r}; expected one of {', '.join(TOPICS)}") from None
        if self.rmw_domain_id is not None and spec.ros_type is not None:
            return rmw_zenoh_key(self.rmw_domain_id, self.ros_topic(name), spec.ros_type)
        return f"{self.base}/{spec.suffix}"

    @property
    def all_keys(self) -> str:
        """`<prefix>/<robot>/**`: every plain key of this robot (for recorders)."""
        return f"{self.base}/**"

    @property
    def camera_image(self) -> str:
        return self.key("camera_image")

    @property
    def camera_info(self) -> str:
        return self.key("camera_info")

    @property
    def servo_twist(self) -> str:
        return self.key("servo_twist")

    @property
    def servo_status(self) -> str:
        return self.key("servo_status")

    @property
    def servo_config(self) -> str:
        return self.key("servo_config")

    @property
    def servo_state(self) -> str:
        return self.key("servo_state")

    @property
    def servo_reference(self) -> str:
        return self.key("servo_reference")

    @property
    def servo_command(self) -> str:
        return self.key("servo_command")

    @property
    def arm_joint_states(self) -> str:
        return self.key("arm_joint_states")

    @property
    def arm_joint_velocity(self) -> str:
        return self.key("arm_joint_velocity")

    @property
    def arm_ground_truth(self) -> str:
        """Evaluation only: the true camera pose from a simulator."""
        return self.key("arm_ground_truth")

    @property
    def liveliness(self) -> str:
        """Liveliness token held by the servo service while it runs."""
        return self.key("liveliness")
