"""ROS 2's own message classes and serializer (the Kilted `ros-rclpy[fastrtps]` wheels) as the reference for our codecs.

`serialize`/`deserialize` are rclpy's (rmw_fastrtps typesupport on Fast-CDR, the reader rmw_zenoh uses too).
`fields(msg)` flattens either an rclpy message or one of ours to the same plain dict, so the two compare with `==`.
`random_message(typename, rng)` draws an rclpy message inside the ROS contract our types enforce (image data of
height × step bytes in a supported encoding; JointState arrays empty or one value per name); strings have no NUL
(rosidl strings are C strings).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from geometry_msgs.msg import TwistStamped as RosTwistStamped
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CameraInfo as RosCameraInfo
from sensor_msgs.msg import Image as RosImage
from sensor_msgs.msg import JointState as RosJointState
from std_msgs.msg import Float64MultiArray as RosFloat64MultiArray
from std_msgs.msg import MultiArrayDimension

from ddvs_service.protocol import (
    ENCODINGS,
    CameraInfo,
    Image,
    JointState,
    TwistStamped,
    decode_camera_info,
    decode_image,
    decode_joint_state,
    decode_twist_stamped,
    encode_camera_info,
    encode_image,
    encode_joint_state,
    encode_twist_stamped,
)
from ddvs_service.protocol.ros import Float64MultiArray, decode_float64_multi_array, encode_float64_multi_array

ROS_CLASSES: dict[str, type] = {
    "sensor_msgs/msg/Image": RosImage,
    "sensor_msgs/msg/CameraInfo": RosCameraInfo,
    "geometry_msgs/msg/TwistStamped": RosTwistStamped,
    "sensor_msgs/msg/JointState": RosJointState,
    "std_msgs/msg/Float64MultiArray": RosFloat64MultiArray,
}
CODECS: dict[str, tuple[Any, Any]] = {
    "sensor_msgs/msg/Image": (encode_image, decode_image),
    "sensor_msgs/msg/CameraInfo": (encode_camera_info, decode_camera_info),
    "geometry_msgs/msg/TwistStamped": (encode_twist_stamped, decode_twist_stamped),
    "sensor_msgs/msg/JointState": (encode_joint_state, decode_joint_state),
    "std_msgs/msg/Float64MultiArray": (encode_float64_multi_array, decode_float64_multi_array),
}


def serialize(msg: Any) -> bytes:
    return bytes(serialize_message(msg))


def deserialize(payload: bytes, typename: str) -> Any:
    return deserialize_message(payload, ROS_CLASSES[typename])


def _floats(values: Any) -> list[float]:
    return [float(v) for v in values]


def _header(h: Any) -> tuple[int, int, str]:
    return (int(h.stamp.sec), int(h.stamp.nanosec), str(h.frame_id))


def fields(msg: Any) -> dict[str, Any]:
    """The message's fields as plain Python values (floats compared exactly; NaN never drawn)."""
    if isinstance(msg, Float64MultiArray):
        return {"dims": [tuple(d) for d in msg.dims], "offset": msg.data_offset, "data": _floats(msg.data)}
    if isinstance(msg, RosFloat64MultiArray):
        return {"dims": [(d.label, d.size, d.stride) for d in msg.layout.dim], "offset": msg.layout.data_offset,
                "data": _floats(msg.data)}
    out: dict[str, Any] = {"header": _header(msg.header)}
    if isinstance(msg, Image | RosImage):
        out |= {"size": (msg.height, msg.width, msg.step), "encoding": msg.encoding,
                "is_bigendian": int(msg.is_bigendian), "data": bytes(np.asarray(msg.data, dtype=np.uint8))}
    elif isinstance(msg, CameraInfo | RosCameraInfo):
        roi = msg.roi
        out |= {"size": (msg.height, msg.width), "model": msg.distortion_model, "d": _floats(msg.d),
                "k": _floats(msg.k), "r": _floats(msg.r), "p": _floats(msg.p),
                "binning": (msg.binning_x, msg.binning_y),
                "roi": (roi.x_offset, roi.y_offset, roi.height, roi.width, bool(roi.do_rectify))}
    elif isinstance(msg, TwistStamped):
        out["twist"] = _floats(msg.vector)
    elif isinstance(msg, RosTwistStamped):
        t = msg.twist
        out["twist"] = _floats([t.linear.x, t.linear.y, t.linear.z, t.angular.x, t.angular.y, t.angular.z])
    elif isinstance(msg, JointState | RosJointState):
        out |= {"name": list(msg.name), "position": _floats(msg.position), "velocity": _floats(msg.velocity),
                "effort": _floats(msg.effort)}
    else:
        raise TypeError(f"no field view for {type(msg).__name__}")
    return out


# --- random messages ---------------------------------------------------------------------------------------------

_ALPHABET = [*"abcXYZ_019 /:-", "é", "ß", "中", "😀"]


def _text(rng: np.random.Generator, max_len: int) -> str:
    return "".join(rng.choice(_ALPHABET, size=int(rng.integers(0, max_len + 1))))


def _values(rng: np.random.Generator, n: int) -> list[float]:
    """Finite doubles over many decades, with exact zeros and negative zeros mixed in."""
    v = rng.standard_normal(n) * 10.0 ** rng.integers(-300, 300, n)
    v[rng.random(n) < 0.1] = 0.0
    v[rng.random(n) < 0.05] = -0.0
    return v.tolist()


def _stamp(msg: Any, rng: np.random.Generator) -> None:
    msg.header.stamp.sec = int(rng.integers(-(2**31), 2**31))
    msg.header.stamp.nanosec = int(rng.integers(0, 1_000_000_000))
    msg.header.frame_id = _text(rng, 12)


def random_image(rng: np.random.Generator) -> RosImage:
    m = RosImage()
    _stamp(m, rng)
    m.encoding = str(rng.choice(sorted(ENCODINGS)))
    fmt = ENCODINGS[m.encoding]
    m.height, m.width = int(rng.integers(0, 9)), int(rng.integers(0, 9))
    m.step = m.width * fmt.bytes_per_pixel + fmt.dtype.itemsize * int(rng.integers(0, 3))
    m.is_bigendian = int(rng.integers(0, 2))
    m.data = rng.integers(0, 256, m.height * m.step, dtype=np.uint8).tobytes()
    return m


def random_camera_info(rng: np.random.Generator) -> RosCameraInfo:
    m = RosCameraInfo()
    _stamp(m, rng)
    m.height, m.width = (int(x) for x in rng.integers(0, 2**32, 2))
    m.distortion_model = str(rng.choice(["plumb_bob", "rational_polynomial", "equidistant", "", _text(rng, 20)]))
    m.d = _values(rng, int(rng.integers(0, 15)))
    m.k, m.r, m.p = _values(rng, 9), _values(rng, 9), _values(rng, 12)
    m.binning_x, m.binning_y = (int(x) for x in rng.integers(0, 2**32, 2))
    m.roi.x_offset, m.roi.y_offset, m.roi.height, m.roi.width = (int(x) for x in rng.integers(0, 2**32, 4))
    m.roi.do_rectify = bool(rng.integers(0, 2))
    return m


def random_twist(rng: np.random.Generator) -> RosTwistStamped:
    m = RosTwistStamped()
    _stamp(m, rng)
    v = _values(rng, 6)
    m.twist.linear.x, m.twist.linear.y, m.twist.linear.z = v[:3]
    m.twist.angular.x, m.twist.angular.y, m.twist.angular.z = v[3:]
    return m


def random_joint_state(rng: np.random.Generator) -> RosJointState:
    m = RosJointState()
    _stamp(m, rng)
    n = int(rng.integers(0, 10))
    m.name = [_text(rng, 10) for _ in range(n)]
    m.position, m.velocity, m.effort = (_values(rng, n) if rng.random() < 0.6 else [] for _ in range(3))
    return m


def random_float64_multi_array(rng: np.random.Generator) -> RosFloat64MultiArray:
    m = RosFloat64MultiArray()
    for _ in range(int(rng.integers(0, 4))):
        d = MultiArrayDimension()
        d.label, d.size, d.stride = _text(rng, 8), int(rng.integers(0, 2**32)), int(rng.integers(0, 2**32))
        m.layout.dim.append(d)
    m.layout.data_offset = int(rng.integers(0, 2**32))
    m.data = _values(rng, int(rng.integers(0, 10)))
    return m


RANDOM = {
    "sensor_msgs/msg/Image": random_image,
    "sensor_msgs/msg/CameraInfo": random_camera_info,
    "geometry_msgs/msg/TwistStamped": random_twist,
    "sensor_msgs/msg/JointState": random_joint_state,
    "std_msgs/msg/Float64MultiArray": random_float64_multi_array,
}
