"""ROS 2 CDR codecs: byte identity with rosbags, messages serialised by real rclpy (the Kilted wheels) decode to the
same fields and ours deserialize in rclpy, round trips, zero-copy image decoding, layout validation."""

from __future__ import annotations

import numpy as np
import pytest
import ros_reference as ros
from hypothesis import given, settings
from hypothesis import strategies as st
from rosbags.typesys import Stores, get_typestore

from ddvs_service.camera import Intrinsics
from ddvs_service.protocol import (
    ENCODINGS,
    CameraInfo,
    Header,
    Image,
    InconsistentMessage,
    JointState,
    MessageTooLarge,
    RegionOfInterest,
    Time,
    TruncatedMessage,
    TwistStamped,
    UnsupportedEncoding,
    decode_camera_info,
    decode_image,
    decode_joint_state,
    decode_twist_stamped,
    encode_camera_info,
    encode_image,
    encode_joint_state,
    encode_twist_stamped,
    image_from_array,
)
from ddvs_service.protocol.ros import Float64MultiArray, decode_float64_multi_array, encode_float64_multi_array

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types

# --- conversion to rosbags' message classes (the reference serializer) ----------------------------------------------


def rb_header(h: Header):
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=h.stamp.sec, nanosec=h.stamp.nanosec), frame_id=h.frame_id
    )


def rb_image(m: Image):
    return T["sensor_msgs/msg/Image"](
        header=rb_header(m.header),
        height=m.height,
        width=m.width,
        encoding=m.encoding,
        is_bigendian=m.is_bigendian,
        step=m.step,
        data=np.array(m.data),
    )


def rb_camera_info(m: CameraInfo):
    roi = m.roi
    return T["sensor_msgs/msg/CameraInfo"](
        header=rb_header(m.header),
        height=m.height,
        width=m.width,
        distortion_model=m.distortion_model,
        d=m.d,
        k=m.k,
        r=m.r,
        p=m.p,
        binning_x=m.binning_x,
        binning_y=m.binning_y,
        roi=T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=roi.x_offset, y_offset=roi.y_offset, height=roi.height, width=roi.width, do_rectify=roi.do_rectify
        ),
    )


def rb_twist(m: TwistStamped):
    v3 = T["geometry_msgs/msg/Vector3"]
    return T["geometry_msgs/msg/TwistStamped"](
        header=rb_header(m.header),
        twist=T["geometry_msgs/msg/Twist"](linear=v3(*m.linear), angular=v3(*m.angular)),
    )


def rb_joint_state(m: JointState):
    return T["sensor_msgs/msg/JointState"](
        header=rb_header(m.header), name=m.name, position=m.position, velocity=m.velocity, effort=m.effort
    )


def rb_float64_multi_array(m: Float64MultiArray):
    dim = T["std_msgs/msg/MultiArrayDimension"]
    dims = [dim(label=label, size=size, stride=stride) for label, size, stride in m.dims]
    layout = T["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=m.data_offset)
    return T["std_msgs/msg/Float64MultiArray"](layout=layout, data=m.data)


# --- strategies -------------------------------------------------------------------------------------------------------

floats = st.floats(allow_nan=False, allow_infinity=False, width=64)
times = st.builds(Time, st.integers(-(2**31), 2**31 - 1), st.integers(0, 999_999_999))
headers = st.builds(Header, times, st.text(max_size=12))


@st.composite
def images(draw):
    encoding = draw(st.sampled_from(sorted(ENCODINGS)))
    fmt = ENCODINGS[encoding]
    height, width = draw(st.integers(0, 6)), draw(st.integers(0, 6))
    step = width * fmt.bytes_per_pixel + fmt.dtype.itemsize * draw(st.integers(0, 3))
    data = draw(st.binary(min_size=height * step, max_size=height * step))
    return Image(draw(headers), height, width, encoding, draw(st.integers(0, 1)), step, np.frombuffer(data, np.uint8))


camera_infos = st.builds(
    CameraInfo,
    header=headers,
    height=st.integers(0, 2**32 - 1),
    width=st.integers(0, 2**32 - 1),
    distortion_model=st.sampled_from(["plumb_bob", "rational_polynomial", ""]),
    d=st.lists(floats, max_size=8),
    k=st.lists(floats, min_size=9, max_size=9),
    r=st.lists(floats, min_size=9, max_size=9),
    p=st.lists(floats, min_size=12, max_size=12),
    binning_x=st.integers(0, 4),
    binning_y=st.integers(0, 4),
    roi=st.builds(
        RegionOfInterest,
        st.integers(0, 2**32 - 1),
        st.integers(0, 2**32 - 1),
        st.integers(0, 2**32 - 1),
        st.integers(0, 2**32 - 1),
        st.booleans(),
    ),
)
twists = st.builds(
    TwistStamped, headers, st.lists(floats, min_size=3, max_size=3), st.lists(floats, min_size=3, max_size=3)
)


@st.composite
def joint_states(draw):
    names = draw(st.lists(st.text(max_size=8), max_size=7))
    n = len(names)
    arrays = [draw(st.sampled_from([[], None])) or draw(st.lists(floats, min_size=n, max_size=n)) for _ in range(3)]
    return JointState(draw(headers), names, *arrays)


uint32s = st.integers(0, 2**32 - 1)
float64_multi_arrays = st.builds(
    Float64MultiArray,
    st.lists(floats, max_size=9),
    st.lists(st.tuples(st.text(max_size=8), uint32s, uint32s), max_size=3),
    uint32s,
)

CODECS = {
    "sensor_msgs/msg/Image": (images(), encode_image, decode_image, rb_image),
    "sensor_msgs/msg/CameraInfo": (camera_infos, encode_camera_info, decode_camera_info, rb_camera_info),
    "geometry_msgs/msg/TwistStamped": (twists, encode_twist_stamped, decode_twist_stamped, rb_twist),
    "sensor_msgs/msg/JointState": (joint_states(), encode_joint_state, decode_joint_state, rb_joint_state),
    "std_msgs/msg/Float64MultiArray": (float64_multi_arrays, encode_float64_multi_array, decode_float64_multi_array,
                                       rb_float64_multi_array),
}


def same_fields(a, b) -> bool:
    """Field-wise equality of two of our messages (numpy arrays compared by value)."""
    for name in a.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            if not np.array_equal(x, y):
                return False
        elif x != y:
            return False
    return True


@pytest.mark.parametrize("typename", sorted(CODECS))
def test_encoders_are_byte_identical_to_rosbags_and_round_trip(typename: str) -> None:
    strategy, encode, decode, to_rosbags = CODECS[typename]

    @settings(max_examples=300, deadline=None)
    @given(strategy)
    def check(msg) -> None:
        reference = bytes(TS.serialize_cdr(to_rosbags(msg), typename))
        assert encode(msg) == reference
        decoded = decode(reference)
        assert same_fields(decoded, msg)
        # rosbags reads our bytes back to the same message too
        assert bytes(TS.serialize_cdr(TS.deserialize_cdr(encode(msg), typename), typename)) == reference

    check()


def test_image_decode_is_a_view_of_the_payload() -> None:
    pixels = np.arange(48 * 64, dtype=np.uint16).reshape(48, 64)
    payload = encode_image(image_from_array(pixels, "mono16", Header(Time(1, 2), "cam")))
    image = decode_image(payload)
    payload_array = np.frombuffer(payload, np.uint8)
    assert np.shares_memory(image.data, payload_array)
    assert np.shares_memory(image.array, payload_array)
    np.testing.assert_array_equal(image.array, pixels)
    assert image.array.shape == (48, 64) and not image.array.flags.writeable


@pytest.mark.parametrize(
    ("encoding", "dtype", "shape"),
    [
        ("mono8", np.uint8, (5, 7)),
        ("rgb8", np.uint8, (5, 7, 3)),
        ("bgr8", np.uint8, (5, 7, 3)),
        ("rgba8", np.uint8, (5, 7, 4)),
        ("bgra8", np.uint8, (5, 7, 4)),
        ("mono16", np.uint16, (5, 7)),
        ("16UC1", np.uint16, (5, 7)),
        ("32FC1", np.float32, (5, 7)),
    ],
)
def test_array_round_trip_per_encoding(encoding: str, dtype: type, shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(0)
    array = (rng.random(shape) * 200).astype(dtype)
    msg = image_from_array(array, encoding, frame_id="cam")
    assert np.shares_memory(msg.data, array), "wrapping a contiguous array must not copy it"
    back = decode_image(encode_image(msg))
    assert back.array.shape == shape and back.array.dtype == np.dtype(dtype).newbyteorder("<")
    np.testing.assert_array_equal(back.array, array)
    assert back.header.frame_id == "cam"


def test_big_endian_and_padded_rows_are_viewed_correctly() -> None:
    values = np.arange(12, dtype=">f4").reshape(3, 4)
    padded = np.zeros((3, 20), np.uint8)  # 16 bytes of pixels + 4 bytes padding per row
    padded[:, :16] = values.view(np.uint8).reshape(3, 16)
    msg = Image(Header(Time(0, 0), "c"), 3, 4, "32FC1", 1, 20, padded.reshape(-1))
    np.testing.assert_array_equal(decode_image(encode_image(msg)).array, values)
    big = image_from_array(values, "32FC1")
    assert big.is_bigendian == 1
    np.testing.assert_array_equal(big.array, values)


def test_image_from_array_rejects_wrong_dtype_and_shape() -> None:
    with pytest.raises(InconsistentMessage, match="dtype uint8"):
        image_from_array(np.zeros((2, 2), np.float64), "mono8")
    with pytest.raises(InconsistentMessage, match=r"\(H, W, 3\)"):
        image_from_array(np.zeros((2, 2)), "rgb8")
    with pytest.raises(UnsupportedEncoding, match="nv21"):
        image_from_array(np.zeros((2, 2), np.uint8), "nv21")


def _image_payload(height: int, width: int, encoding: str, step: int, data: bytes, big: int = 0) -> bytes:
    raw = T["sensor_msgs/msg/Image"](
        header=rb_header(Header(Time(0, 0), "c")),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=big,
        step=step,
        data=np.frombuffer(data, np.uint8),
    )
    return bytes(TS.serialize_cdr(raw, "sensor_msgs/msg/Image"))


@pytest.mark.parametrize(
    ("payload", "error", "message"),
    [
        (_image_payload(2, 3, "mono8", 3, bytes(5)), InconsistentMessage, "expected height × step"),
        (_image_payload(2, 3, "rgb8", 8, bytes(16)), InconsistentMessage, "shorter than a row"),
        (_image_payload(2, 3, "mono16", 7, bytes(14)), InconsistentMessage, "misaligned"),
        (_image_payload(2, 3, "nv21", 6, bytes(12)), UnsupportedEncoding, "nv21"),
        (_image_payload(2, 3, "mono8", 3, bytes(6), big=2), InconsistentMessage, "is_bigendian"),
        (_image_payload(2, 3, "mono8", 3, bytes(6))[:-1], TruncatedMessage, "data"),
        (b"\x00\x00\x00\x00" + _image_payload(1, 1, "mono8", 1, b"x")[4:], UnsupportedEncoding, "CDR_LE"),
        (b"\x00\x01", TruncatedMessage, "encapsulation"),
    ],
)
def test_bad_images_raise_typed_errors_naming_the_problem(payload: bytes, error: type, message: str) -> None:
    with pytest.raises(error, match=message):
        decode_image(payload)


def test_image_size_limits_are_checked_before_the_data() -> None:
    forged = _image_payload(100_000, 100_000, "mono8", 100_000, bytes(10))  # claims 10 GB, carries 10 bytes
    with pytest.raises(MessageTooLarge, match="height × step = 100000 × 100000"):
        decode_image(forged)
    payload = _image_payload(100, 100, "mono8", 100, bytes(10_000))
    with pytest.raises(MessageTooLarge, match="payload is 10048 bytes; the maximum is 100"):
        decode_image(payload, max_bytes=100)
    assert decode_image(payload, max_bytes=len(payload)).array.shape == (100, 100)


def test_camera_info_intrinsics_round_trip() -> None:
    intrinsics = Intrinsics(fx=525.0, fy=520.0, cx=319.5, cy=239.5, width=640, height=480, skew=0.5)
    info = CameraInfo.from_intrinsics(intrinsics, Header(Time(3, 4), "camera"))
    back = decode_camera_info(encode_camera_info(info)).to_intrinsics()
    assert back == intrinsics
    np.testing.assert_array_equal(info.p.reshape(3, 4)[:, :3], intrinsics.K)


def test_camera_info_that_the_pinhole_model_cannot_represent_is_refused() -> None:
    header = Header(Time(0, 0), "c")
    k = Intrinsics.centred(500.0, 64, 48).K.reshape(-1)
    with pytest.raises(InconsistentMessage, match="monocular"):
        CameraInfo(header, 48, 64, k=k, p=[500, 0, 31.5, -25, 0, 500, 23.5, 0, 0, 0, 1, 0]).rectified_intrinsics()
    with pytest.raises(InconsistentMessage, match="binning"):
        CameraInfo(header, 48, 64, k=k, binning_x=2).to_intrinsics()
    with pytest.raises(InconsistentMessage, match="roi"):
        CameraInfo(header, 48, 64, k=k, roi=RegionOfInterest(0, 0, 10, 10)).to_intrinsics()
    with pytest.raises(InconsistentMessage, match="k has 8 values"):
        CameraInfo(header, 48, 64, k=k[:8])


def test_camera_info_intrinsics_of_raw_and_rectified_images() -> None:
    """As in ROS: `k` is the raw image's camera, the first 3×3 of `p` the rectified image's (`k` when `p` is unset),
    whatever the distortion coefficients."""
    header = Header(Time(0, 0), "c")
    k = Intrinsics(500.0, 502.0, 31.0, 24.0, 64, 48).K
    p = np.hstack([Intrinsics(420.0, 421.0, 32.5, 22.0, 64, 48).K, np.zeros((3, 1))])
    info = CameraInfo(header, 48, 64, d=[-0.3, 0.1, 0.001, -0.002, 0.0], k=k.reshape(-1), p=p.reshape(-1))
    assert info.distorted
    assert info.to_intrinsics() == Intrinsics(500.0, 502.0, 31.0, 24.0, 64, 48)
    assert info.rectified_intrinsics() == Intrinsics(420.0, 421.0, 32.5, 22.0, 64, 48)
    unset = CameraInfo(header, 48, 64, d=[-0.3, 0.1, 0, 0, 0], k=k.reshape(-1), p=np.zeros(12))
    assert unset.rectified_intrinsics() == unset.to_intrinsics()


def test_time_conversions() -> None:
    assert Time.from_ns(1_700_000_000_123_456_789) == Time(1_700_000_000, 123_456_789)
    assert Time.from_ns(-1) == Time(-1, 999_999_999)
    assert Time(5, 6).to_ns() == 5_000_000_006
    with pytest.raises(InconsistentMessage, match="nanosec"):
        Time(0, 1_000_000_000)


def test_twist_rejects_non_finite_values_and_joint_state_checks_lengths() -> None:
    header = Header(Time(0, 0), "camera")
    with pytest.raises(InconsistentMessage, match="non-finite"):
        TwistStamped(header, [0, float("nan"), 0], [0, 0, 0])
    payload = bytearray(encode_twist_stamped(TwistStamped(header, [1, 2, 3], [4, 5, 6])))
    payload[-8:] = np.array([np.inf]).tobytes()
    with pytest.raises(InconsistentMessage, match="non-finite"):
        decode_twist_stamped(bytes(payload))
    with pytest.raises(InconsistentMessage, match="expected 0 or one per joint"):
        JointState(header, ["a", "b"], position=[1.0])
    np.testing.assert_array_equal(TwistStamped(header, [1, 2, 3], [4, 5, 6]).vector, [1, 2, 3, 4, 5, 6])


# --- against rclpy (ROS 2 Kilted wheels: rmw_fastrtps typesupport on Fast-CDR) ----------------------------------------

RCLPY_MESSAGES_PER_TYPE = 2000


@pytest.mark.parametrize("typename", sorted(ros.RANDOM))
def test_random_rclpy_messages_decode_to_the_same_fields_and_ours_deserialize_in_rclpy(typename: str) -> None:
    """N/N: every random rclpy message decodes to its own fields, and our encoding reads back in rclpy equal to it."""
    encode, decode = ros.CODECS[typename]
    rng = np.random.default_rng(18)
    n = RCLPY_MESSAGES_PER_TYPE
    not_decoded, not_read_back = [], []
    for _ in range(n):
        msg = ros.RANDOM[typename](rng)
        ours = decode(ros.serialize(msg))
        if ros.fields(ours) != ros.fields(msg):
            not_decoded.append(msg)
        elif ros.deserialize(encode(ours), typename) != msg:
            not_read_back.append(msg)
    print(f"{typename}: {n - len(not_decoded)}/{n} decoded, {n - len(not_decoded) - len(not_read_back)}/{n} read back")
    assert not not_decoded and not not_read_back, (not_decoded[:2], not_read_back[:2])


def _joint_state_publisher() -> object:
    """What joint_state_publisher sends for a 6-joint arm: names and positions, velocity and effort empty."""
    m = ros.ROS_CLASSES["sensor_msgs/msg/JointState"]()
    m.header.stamp.sec, m.header.stamp.nanosec = 1_733_000_000, 123_456_789
    m.name = [f"joint_{i}" for i in range(1, 7)]
    m.position = [0.0, -1.57, 1.2, -0.3, 1.57, 0.1]
    return m


def _camera_info(model: str, d: list[float]) -> object:
    """A camera driver's CameraInfo (640×480, usb_cam / realsense style) with the given distortion model."""
    m = ros.ROS_CLASSES["sensor_msgs/msg/CameraInfo"]()
    m.header.stamp.sec, m.header.frame_id = 1_733_000_000, "camera_color_optical_frame"
    m.height, m.width, m.distortion_model, m.d = 480, 640, model, d
    m.k = [615.3, 0.0, 320.8, 0.0, 615.9, 241.2, 0.0, 0.0, 1.0]
    m.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    m.p = [615.3, 0.0, 320.8, 0.0, 0.0, 615.9, 241.2, 0.0, 0.0, 0.0, 1.0, 0.0]
    return m


def _image(encoding: str, height: int, width: int, frame_id: str = "camera_optical_frame") -> object:
    m = ros.ROS_CLASSES["sensor_msgs/msg/Image"]()
    m.header.frame_id, m.encoding, m.height, m.width = frame_id, encoding, height, width
    m.step = width * ENCODINGS[encoding].bytes_per_pixel
    m.data = np.random.default_rng(height).integers(0, 256, height * m.step, dtype=np.uint8).tobytes()
    return m


def _empty(typename: str) -> object:
    return ros.ROS_CLASSES[typename]()


REAL_SHAPES = {
    "joint_state_publisher (6 names, positions only)": ("sensor_msgs/msg/JointState", _joint_state_publisher),
    "JointState, all arrays empty": ("sensor_msgs/msg/JointState", lambda: _empty("sensor_msgs/msg/JointState")),
    "CameraInfo plumb_bob": ("sensor_msgs/msg/CameraInfo",
                             lambda: _camera_info("plumb_bob", [0.12, -0.25, 0.001, -0.002, 0.1])),
    "CameraInfo rational_polynomial": ("sensor_msgs/msg/CameraInfo", lambda: _camera_info(
        "rational_polynomial", [0.3, -2.1, 0.0, 0.001, 1.5, 0.2, -1.9, 1.4])),
    "CameraInfo equidistant": ("sensor_msgs/msg/CameraInfo",
                               lambda: _camera_info("equidistant", [-0.01, 0.05, -0.06, 0.02])),
    "CameraInfo default (empty d)": ("sensor_msgs/msg/CameraInfo", lambda: _empty("sensor_msgs/msg/CameraInfo")),
    "Image rgb8 640×480": ("sensor_msgs/msg/Image", lambda: _image("rgb8", 480, 640)),
    "Image mono16 odd width": ("sensor_msgs/msg/Image", lambda: _image("mono16", 3, 7, "d")),
    "Image mono8 0×0": ("sensor_msgs/msg/Image", lambda: _image("mono8", 0, 0)),
    "TwistStamped zero": ("geometry_msgs/msg/TwistStamped", lambda: _empty("geometry_msgs/msg/TwistStamped")),
}


@pytest.mark.parametrize("shape", sorted(REAL_SHAPES))
def test_common_real_shapes_from_rclpy_decode_and_read_back(shape: str) -> None:
    typename, make = REAL_SHAPES[shape]
    encode, decode = ros.CODECS[typename]
    msg = make()
    payload = ros.serialize(msg)
    ours = decode(payload)
    assert ros.fields(ours) == ros.fields(msg)
    assert ros.deserialize(encode(ours), typename) == msg
    assert len(encode(ours)) <= len(payload)  # rclpy's buffer may be longer (its size estimate), never shorter


def test_joint_state_publisher_payload_has_trailing_bytes_that_fast_cdr_ignores() -> None:
    """rclpy sizes the buffer by rmw_fastrtps's estimate, which reserves 8-byte alignment for each empty float64
    sequence: joint_state_publisher's usual message carries 8 bytes after its last field (and ros2 bag play /
    rmw_zenoh's publish_serialized_message forward them as they are)."""
    msg = _joint_state_publisher()
    payload = ros.serialize(msg)
    ours = encode_joint_state(decode_joint_state(payload))
    assert len(payload) - len(ours) == 8
    for extra in (1, 7, 8, 100):  # more bytes still read as the same message, by rclpy and by us
        assert ros.deserialize(payload + bytes([0xA5]) * extra, "sensor_msgs/msg/JointState") == msg
        assert ros.fields(decode_joint_state(payload + bytes([0xA5]) * extra)) == ros.fields(msg)


def _ignored_positions(payload: bytes, typename: str, msg: object) -> list[int]:
    """Byte positions (after the 4-byte header) that rclpy ignores: flipping one leaves its decode equal to `msg`."""
    ignored = []
    for i in range(4, len(payload)):
        flipped = bytearray(payload)
        flipped[i] ^= 0xFF
        try:
            same = ros.deserialize(bytes(flipped), typename) == msg
        except Exception:  # rclpy raises its own error types for malformed buffers
            same = False
        if same:
            ignored.append(i)
    return ignored


@pytest.mark.parametrize("shape", ["CameraInfo plumb_bob", "Image mono16 odd width", "JointState, all arrays empty",
                                   "joint_state_publisher (6 names, positions only)", "TwistStamped zero"])
def test_padding_of_any_value_is_ignored_like_rclpy_does(shape: str) -> None:
    """The bytes rclpy ignores (alignment padding, trailing bytes; found by flipping each byte) set to random values
    leave our decode unchanged; our own encoder writes them as zeros, so it matches rclpy's bytes with them masked."""
    typename, make = REAL_SHAPES[shape]
    encode, decode = ros.CODECS[typename]
    msg = make()
    ours = bytearray(encode(decode(ros.serialize(msg))))
    ignored = _ignored_positions(bytes(ours), typename, msg)
    assert ignored, "every message here has alignment padding"
    rng = np.random.default_rng(7)
    for _ in range(20):
        noisy = bytearray(ours)
        for i in ignored:
            noisy[i] = int(rng.integers(1, 256))
        assert ros.deserialize(bytes(noisy), typename) == msg
        assert ros.fields(decode(bytes(noisy))) == ros.fields(msg)
    assert all(ours[i] == 0 for i in ignored)
    masked_rclpy = bytearray(ros.serialize(msg)[: len(ours)])
    for i in ignored:
        masked_rclpy[i] = 0
    assert bytes(masked_rclpy) == bytes(ours)


def test_strings_and_bools_read_as_rclpy_reads_them() -> None:
    """Fast-CDR's typesupport reads a string of length 0 as "", keeps every byte of one without a NUL, replaces
    invalid UTF-8, and takes any non-zero bool byte as true; we read the same values."""
    twist = ros.ROS_CLASSES["geometry_msgs/msg/TwistStamped"]()
    twist.header.frame_id = "ab"
    payload = bytearray(ros.serialize(twist))  # frame_id: length at bytes 12..15, then "ab\0" at 16..18
    variants = {
        "length 0": payload[:12] + bytes(4) + payload[16:],
        "no NUL": payload[:18] + b"c" + payload[19:],
        "bad UTF-8": payload[:16] + b"\xff" + payload[17:],
    }
    for what, buf in variants.items():
        expected = ros.deserialize(bytes(buf), "geometry_msgs/msg/TwistStamped")
        assert ros.fields(decode_twist_stamped(bytes(buf))) == ros.fields(expected), what
    info = bytearray(ros.serialize(_camera_info("plumb_bob", [0.0] * 5)))
    for byte in (1, 2, 255):
        info[-1] = byte  # roi.do_rectify, the last field
        assert ros.deserialize(bytes(info), "sensor_msgs/msg/CameraInfo").roi.do_rectify
        assert decode_camera_info(bytes(info)).roi.do_rectify


def test_reader_refuses_what_rclpy_refuses() -> None:
    """Truncated buffers and a big-endian or non-CDR encapsulation fail in rclpy too; ours raise typed errors."""
    payload = ros.serialize(_joint_state_publisher())
    for bad, error in ((payload[:-40], TruncatedMessage), (b"\x00\x00\x00\x00" + payload[4:], UnsupportedEncoding),
                       (b"\x01\x01\x00\x00" + payload[4:], UnsupportedEncoding)):
        with pytest.raises(Exception):  # noqa: B017 — rclpy raises its own RMWError
            ros.deserialize(bad, "sensor_msgs/msg/JointState")
        with pytest.raises(error):
            decode_joint_state(bad)
    options = b"\x00\x01\x01\x02" + payload[4:]  # options bytes are ignored by both
    assert ros.fields(decode_joint_state(options)) == ros.fields(_joint_state_publisher())
