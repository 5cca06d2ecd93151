"""Zenoh key expressions of one robot's servo system, and the table of what travels on each.

Every key is `<prefix>/<robot>/<suffix>`. In ROS 2 mode (`RosSettings.domain_id` set, docs/ros2.md) the ROS-typed
topics (CDR payloads) move to rmw_zenoh keys under ROS names, `<domain_id>/<ROS name>/<pkg>::msg::dds_::<Type>_/
<type hash>`, where the ROS name is the row's `ros_name` resolved in the ROS namespace or its remapping; publishers
then attach `rmw.RmwPublisherIdentity.next_attachment()` to each sample and every endpoint declares its graph token
(`endpoints.Endpoints`). JSON control-plane keys do not change.

`TOPICS` is the single source of the key tables in `docs/protocol.md` and `docs/ros2.md` (tests keep them equal).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ddvs_service.protocol.rmw import rmw_zenoh_key
from ddvs_service.protocol.ros_graph import LATEST_QOS, SENSOR_DATA_QOS, RosQos
from ddvs_service.protocol.ros_settings import RosSettings

_WILDCARDS = "*$?#"


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
    ros_name: str | None = None  # default ROS name in ROS 2 mode (relative: under the ROS namespace)
    ros_qos: RosQos | None = None  # the QoS its graph tokens announce in ROS 2 mode


TOPICS: dict[str, TopicSpec] = {
    "camera_image": TopicSpec(
        "camera/image", "sensor_msgs/msg/Image (CDR)", "sensor_msgs/msg/Image",
        "camera, sim", "serve, monitor, record", "DATA_HIGH", "DROP", False, "latest only (RingChannel(1))",
        "image_raw", SENSOR_DATA_QOS,
    ),
    "camera_image_rect": TopicSpec(
        "camera/image_rect", "sensor_msgs/msg/Image (CDR), rectified: intrinsics from the camera info's P",
        "sensor_msgs/msg/Image", "camera (--publish rect), image_proc", "serve (camera.images rect), monitor, record",
        "DATA_HIGH", "DROP", False, "latest only (RingChannel(1))", "image_rect", SENSOR_DATA_QOS,
    ),
    "camera_image_compressed": TopicSpec(
        "camera/image/compressed", "sensor_msgs/msg/CompressedImage (CDR), JPEG or PNG of camera/image",
        "sensor_msgs/msg/CompressedImage", "camera (--compress), image_transport",
        "serve (camera.transport compressed), monitor, record", "DATA_HIGH", "DROP", False,
        "latest only (RingChannel(1))", "image_raw/compressed", SENSOR_DATA_QOS,
    ),
    "camera_image_rect_compressed": TopicSpec(
        "camera/image_rect/compressed", "sensor_msgs/msg/CompressedImage (CDR), JPEG or PNG of camera/image_rect",
        "sensor_msgs/msg/CompressedImage", "camera (--publish rect --compress), image_transport",
        "serve (camera.images rect, camera.transport compressed), monitor, record", "DATA_HIGH", "DROP", False,
        "latest only (RingChannel(1))", "image_rect/compressed", SENSOR_DATA_QOS,
    ),
    "camera_info": TopicSpec(
        "camera/info", "sensor_msgs/msg/CameraInfo (CDR)", "sensor_msgs/msg/CameraInfo",
        "camera, sim (with every image)", "serve, monitor, record", "DATA", "DROP", False, "latest only",
        "camera_info", SENSOR_DATA_QOS,
    ),
    "servo_twist": TopicSpec(
        "servo/twist", "geometry_msgs/msg/TwistStamped (CDR), camera frame", "geometry_msgs/msg/TwistStamped",
        "serve", "bridge, sim, record", "REAL_TIME", "DROP", True, "latest only",
        "servo_node/delta_twist_cmds", LATEST_QOS,
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
        "serve (when a reference is set)", "monitor, record", "DATA_LOW", "BLOCK", False, "latest only",
        "ddvs/reference", LATEST_QOS,
    ),
    "servo_residual": TopicSpec(
        "servo/residual", "sensor_msgs/msg/Image (CDR), 32FC1: the registration's residual over the ROI",
        "sensor_msgs/msg/Image", "serve (only while subscribed, ≤ 5 Hz)", "monitor --foxglove, record", "DATA_LOW",
        "DROP", False, "latest only", "ddvs/residual", LATEST_QOS,
    ),
    "servo_command": TopicSpec(
        "servo/command", "query: JSON `Command` → reply: JSON `Reply`", None,
        "serve (queryable)", "ctl, experiment (get)", "INTERACTIVE_HIGH", "BLOCK", False, "query/reply",
    ),
    "arm_joint_states": TopicSpec(
        "arm/joint_states", "sensor_msgs/msg/JointState (CDR)", "sensor_msgs/msg/JointState",
        "sim (arm)", "bridge, record", "REAL_TIME", "DROP", True, "latest only",
        "joint_states", LATEST_QOS,
    ),
    "arm_joint_velocity": TopicSpec(
        "arm/joint_velocity", "sensor_msgs/msg/JointState (CDR), `velocity` only", "sensor_msgs/msg/JointState",
        "bridge", "sim (arm)", "REAL_TIME", "DROP", True, "latest only",
        "ddvs/joint_velocity", LATEST_QOS,
    ),
    "arm_velocity_commands": TopicSpec(
        "arm/velocity_commands", "std_msgs/msg/Float64MultiArray (CDR), rad/s in the configured joint order",
        "std_msgs/msg/Float64MultiArray", "bridge (ROS 2 mode)", "sim (arm, ROS 2 mode)", "REAL_TIME", "DROP", True,
        "latest only", "forward_velocity_controller/commands", LATEST_QOS,
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

CAMERA_IMAGES = ("camera_image", "camera_image_rect", "camera_image_compressed", "camera_image_rect_compressed")
"""The rows a camera's frames may arrive on: raw or rectified, as Image or CompressedImage (docs/cameras.md)."""


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
    """Key expressions under `<prefix>/<robot>`; `ros.domain_id` switches ROS-typed topics to rmw_zenoh keys."""

    prefix: str = "ddvs"
    robot: str = "robot0"
    ros: RosSettings = field(default_factory=RosSettings)

    def __post_init__(self) -> None:
        _validate_part("prefix", self.prefix)
        _validate_part("robot", self.robot)
        for row in self.ros.topics:
            if row not in TOPICS or TOPICS[row].ros_type is None:
                ros_rows = [n for n, spec in TOPICS.items() if spec.ros_type is not None]
                raise ValueError(f"ROS topic remapping of {row!r}: expected one of {', '.join(ros_rows)}")
        if self.ros.enabled:
            for row, spec in TOPICS.items():
                if spec.ros_type is not None:
                    self.ros_topic(row)  # validates every ROS name now, not at the first use

    @property
    def base(self) -> str:
        return f"{self.prefix}/{self.robot}"

    @property
    def rmw(self) -> bool:
        """True in ROS 2 mode: ROS-typed topics use rmw_zenoh keys (and need `rmw` attachments and graph tokens)."""
        return self.ros.enabled

    def ros_topic(self, name: str) -> str:
        """The ROS topic name of row `name` of `TOPICS`: in ROS 2 mode its ROS name (remapped, resolved in the
        namespace; `/image_raw` by default for the camera), otherwise `/<prefix>/<robot>/<suffix>` (bag topics)."""
        spec = TOPICS[name]
        if spec.ros_type is None or spec.ros_name is None:
            raise ValueError(f"{name!r} carries JSON, not a ROS message: it has no ROS topic")
        if not self.ros.enabled:
            return f"/{self.base}/{spec.suffix}"
        return self.ros.resolve(self.ros.topics.get(name, spec.ros_name))

    def key(self, name: str) -> str:
        """The key expression of entry `name` of `TOPICS` (rmw_zenoh layout for ROS types in ROS 2 mode)."""
        try:
            spec = TOPICS[name]
        except KeyError:
            raise KeyError(f"unknown topic {name!r}; expected one of {', '.join(TOPICS)}") from None
        if self.ros.domain_id is not None and spec.ros_type is not None:
            return rmw_zenoh_key(self.ros.domain_id, self.ros_topic(name), spec.ros_type)
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
    def arm_velocity_commands(self) -> str:
        return self.key("arm_velocity_commands")

    @property
    def arm_ground_truth(self) -> str:
        """Evaluation only: the true camera pose from a simulator."""
        return self.key("arm_ground_truth")

    @property
    def liveliness(self) -> str:
        """Liveliness token held by the servo service while it runs."""
        return self.key("liveliness")
