"""ROS 2 message definitions (`ros2msg` text) of the types ddvs records and serves, in the form rosbag2 stores them.

rosbag2 (`rosbag2_storage_mcap`) writes a channel's schema as the `.msg` text of its type followed, for every type it
depends on, by a line of 80 `=`, a line `MSG: <package>/<Type>` and that type's `.msg` text; readers (`rosbags`,
`mcap_ros2`, Foxglove) rebuild the CDR layout from it. The field lines below are those of the ROS 2 (Humble …
Kilted) `.msg` files without their comments; `tests/test_bag.py` checks them against the `rosbags` type store.
"""

from __future__ import annotations

SEPARATOR = "=" * 80

MSG_TEXT: dict[str, str] = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "sensor_msgs/msg/Image": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\n"
        "uint8[] data\n"
    ),
    "sensor_msgs/msg/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "sensor_msgs/msg/RegionOfInterest": (
        "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"
    ),
    "sensor_msgs/msg/CameraInfo": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\nfloat64[9] k\n"
        "float64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\nRegionOfInterest roi\n"
    ),
    "sensor_msgs/msg/JointState": (
        "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n"
    ),
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Twist": "Vector3 linear\nVector3 angular\n",
    "geometry_msgs/msg/TwistStamped": "std_msgs/Header header\nTwist twist\n",
}
"""`.msg` text (no comments) of every type, keyed by the full ROS 2 name `<package>/msg/<Type>`."""

DEPENDENCIES: dict[str, tuple[str, ...]] = {
    "std_msgs/msg/Header": ("builtin_interfaces/msg/Time",),
    "sensor_msgs/msg/Image": ("std_msgs/msg/Header",),
    "sensor_msgs/msg/CompressedImage": ("std_msgs/msg/Header",),
    "sensor_msgs/msg/CameraInfo": ("std_msgs/msg/Header", "sensor_msgs/msg/RegionOfInterest"),
    "sensor_msgs/msg/JointState": ("std_msgs/msg/Header",),
    "geometry_msgs/msg/Twist": ("geometry_msgs/msg/Vector3",),
    "geometry_msgs/msg/TwistStamped": ("std_msgs/msg/Header", "geometry_msgs/msg/Twist"),
}
"""The types each type's fields use directly."""


def _closure(ros_type: str) -> list[str]:
    """Every type `ros_type` depends on, directly or not, depth first, each once."""
    seen: list[str] = []

    def visit(name: str) -> None:
        for dep in DEPENDENCIES.get(name, ()):
            if dep not in seen:
                seen.append(dep)
                visit(dep)

    visit(ros_type)
    return seen


def message_definition(ros_type: str) -> str:
    """The full `ros2msg` schema text of `ros_type` (e.g. `sensor_msgs/msg/Image`) with its dependent types."""
    if ros_type not in MSG_TEXT:
        raise KeyError(f"no message definition for {ros_type!r}; known: {', '.join(sorted(MSG_TEXT))}")
    parts = [MSG_TEXT[ros_type]]
    for dep in _closure(ros_type):
        package, _, name = dep.split("/")
        parts.append(f"{SEPARATOR}\nMSG: {package}/{name}\n{MSG_TEXT[dep]}")
    return "".join(parts)
