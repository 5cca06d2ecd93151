"""Key expressions, the rmw_zenoh key/attachment layout, and the documented key table."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import zenoh
import zenoh.ext
from rosbags.typesys import Stores, get_typestore

from ddvs_service.protocol import TOPICS, Keys, RmwAttachment, RmwPublisherIdentity, TruncatedMessage, rmw_zenoh_key
from ddvs_service.protocol.rmw import TYPE_HASHES, dds_type_name
from ddvs_service.protocol.ros_settings import RosSettings

DOC = Path(__file__).resolve().parent.parent / "docs" / "protocol.md"


def test_default_keys() -> None:
    keys = Keys()
    assert keys.camera_image == "ddvs/robot0/camera/image"
    assert keys.camera_info == "ddvs/robot0/camera/info"
    assert keys.servo_twist == "ddvs/robot0/servo/twist"
    assert keys.servo_status == "ddvs/robot0/servo/status"
    assert keys.servo_config == "ddvs/robot0/servo/config"
    assert keys.servo_state == "ddvs/robot0/servo/state"
    assert keys.servo_reference == "ddvs/robot0/servo/reference"
    assert keys.servo_command == "ddvs/robot0/servo/command"
    assert keys.arm_joint_states == "ddvs/robot0/arm/joint_states"
    assert keys.arm_joint_velocity == "ddvs/robot0/arm/joint_velocity"
    assert keys.arm_ground_truth == "ddvs/robot0/arm/ground_truth"
    assert keys.liveliness == "ddvs/robot0/servo/alive"
    assert Keys("lab/cell1", "ur5").servo_twist == "lab/cell1/ur5/servo/twist"
    for name in TOPICS:  # every key is a valid, wildcard-free Zenoh key expression
        assert str(zenoh.KeyExpr(keys.key(name))) == keys.key(name)


@pytest.mark.parametrize(
    ("prefix", "robot", "problem"),
    [
        ("", "r", "non-empty"),
        ("ddvs", "r*", "wildcard"),
        ("dd$s", "r", "wildcard"),
        ("a?", "r", "wildcard"),
        ("ddvs", "#r", "wildcard"),
        ("/ddvs", "r", "leading"),
        ("ddvs/", "r", "leading"),
        ("a//b", "r", "chunks"),
    ],
)
def test_invalid_parts_are_rejected(prefix: str, robot: str, problem: str) -> None:
    with pytest.raises(ValueError, match=problem):
        Keys(prefix, robot)


def test_ros_mode_switches_only_ros_typed_topics_to_ros_names() -> None:
    keys = Keys(ros=RosSettings(domain_id=7))
    assert keys.rmw and not Keys().rmw
    assert keys.camera_image == (
        "7/image_raw/sensor_msgs::msg::dds_::Image_/"
        "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"
    )
    assert keys.camera_info.startswith("7/camera_info/sensor_msgs::msg::dds_::CameraInfo_/RIHS01_")
    assert keys.servo_twist.startswith("7/servo_node/delta_twist_cmds/geometry_msgs::msg::dds_::TwistStamped_/RIHS01_")
    assert keys.arm_joint_states.startswith("7/joint_states/sensor_msgs::msg::dds_::JointState_/")
    assert keys.arm_velocity_commands.startswith(
        "7/forward_velocity_controller/commands/std_msgs::msg::dds_::Float64MultiArray_/RIHS01_")
    assert keys.servo_status == "ddvs/robot0/servo/status"  # JSON stays on the plain key
    assert Keys().ros_topic("arm_joint_states") == "/ddvs/robot0/arm/joint_states"  # plain mode: bag topic names
    with pytest.raises(ValueError, match="domain_id"):
        RosSettings(domain_id=300)


def test_ros_names_resolve_in_the_namespace_and_remap() -> None:
    ros = RosSettings(domain_id=0, namespace="/cell1/arm0",
                      topics={"camera_image": "/camera/color/image_raw", "servo_twist": "twist_cmds"})
    keys = Keys(ros=ros)
    assert keys.ros_topic("camera_image") == "/camera/color/image_raw"  # absolute: as given
    assert keys.ros_topic("camera_info") == "/cell1/arm0/camera_info"  # relative: in the namespace
    assert keys.ros_topic("servo_twist") == "/cell1/arm0/twist_cmds"
    assert keys.camera_image.startswith("0/camera/color/image_raw/sensor_msgs::msg::dds_::Image_/")
    with pytest.raises(ValueError, match="remapping of 'servo_status'"):
        Keys(ros=RosSettings(domain_id=0, topics={"servo_status": "/status"}))
    with pytest.raises(ValueError, match="not a fully qualified ROS name"):
        Keys(ros=RosSettings(domain_id=0, topics={"camera_image": "/camera/9image"}))
    with pytest.raises(ValueError, match="private names"):
        Keys(ros=RosSettings(domain_id=0, topics={"camera_image": "~/image"}))
    with pytest.raises(ValueError, match="namespace"):
        RosSettings(namespace="cell1")


def test_type_hashes_match_the_ros_definitions() -> None:
    for store in (Stores.ROS2_JAZZY, Stores.ROS2_KILTED):
        typestore = get_typestore(store)
        for ros_type, expected in TYPE_HASHES.items():
            if "/srv/" not in ros_type:  # rosbags hashes messages only
                assert typestore.hash_rihs01(ros_type) == expected, (store, ros_type)
    for ros_type, expected in TYPE_HASHES.items():  # the hashes rosidl generated into the Kilted wheels
        description = json.loads((Path(sys.prefix) / "share" / f"{ros_type}.json").read_text(encoding="utf-8"))
        assert {h["type_name"]: h["hash_string"] for h in description["type_hashes"]}[ros_type] == expected
    assert dds_type_name("sensor_msgs/msg/JointState") == "sensor_msgs::msg::dds_::JointState_"
    assert rmw_zenoh_key(0, "/a/b/", "sensor_msgs/msg/Image").startswith("0/a/b/sensor_msgs::msg::dds_::Image_/")
    assert dds_type_name("std_srvs/srv/Trigger") == "std_srvs::srv::dds_::Trigger_"


def test_attachment_layout_is_zenohs_serialization_of_the_rmw_tuple() -> None:
    gid = bytes(range(16))
    ours = RmwAttachment(42, 1_700_000_000_000_000_123, gid).encode()
    reference = zenoh.ext.z_serialize((zenoh.ext.Int64(42), zenoh.ext.Int64(1_700_000_000_000_000_123), gid))
    assert ours == reference.to_bytes() and len(ours) == 33
    assert RmwAttachment.decode(ours) == RmwAttachment(42, 1_700_000_000_000_000_123, gid)
    with pytest.raises(TruncatedMessage):
        RmwAttachment.decode(ours[:-1])
    identity = RmwPublisherIdentity()
    first, second = (RmwAttachment.decode(identity.next_attachment(5)) for _ in range(2))
    assert (first.sequence_number, second.sequence_number) == (1, 2) and first.gid == second.gid == identity.gid


def test_the_services_images_never_queue_ahead_of_its_status() -> None:
    """Zenoh fragments a sample larger than a batch (`transport/link/tx/batch_size`) over its priority's few batches
    (`queue/size`); a DROP sample pushed at that priority while they are still queued waits `wait_before_drop` (1 ms)
    for a batch, then is dropped. A reference image (320×240 mono8 is already fragmented) at the status's priority
    thus cost a loaded machine the READY status of the frame that set it. The service's images travel below it."""
    config = zenoh.Config()
    queue, batch = (json.loads(config.get_json(f"transport/link/tx/{key}")) for key in ("queue", "batch_size"))
    status = TOPICS["servo_status"]
    assert status.congestion == "DROP" and queue["congestion_control"]["drop"]["wait_before_drop"] == 1000
    assert batch < 320 * 240
    images = [name for name, spec in TOPICS.items() if spec.publisher.startswith("serve") and "Image" in spec.payload]
    assert images == ["servo_reference", "servo_residual"]
    assert all(TOPICS[name].priority != status.priority for name in images)


def test_docs_key_table_matches_the_code() -> None:
    text = DOC.read_text(encoding="utf-8")
    for spec in TOPICS.values():
        qos = f"{spec.priority}, {spec.congestion}{', express' if spec.express else ''}"
        row = f"| `<prefix>/<robot>/{spec.suffix}` | {spec.payload} | {spec.publisher} | {spec.subscribers} | {qos} |"
        assert f"{row} {spec.delivery} |" in text, f"docs/protocol.md lacks the row:\n{row} {spec.delivery} |"


def test_docs_ros2_topic_table_matches_the_code() -> None:
    text = (DOC.parent / "ros2.md").read_text(encoding="utf-8")
    for name, spec in TOPICS.items():
        if spec.ros_type is None:
            continue
        assert spec.ros_name is not None and spec.ros_qos is not None, name
        row = (f"| `{name}` | `{spec.ros_name}` | `{spec.ros_type}` | `{spec.ros_qos.encode()}` | {spec.publisher} | "
               f"{spec.subscribers} |")
        assert row in text, f"docs/ros2.md lacks the row:\n{row}"
