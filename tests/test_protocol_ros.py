"""ROS 2 CDR codecs: byte identity with rosbags, round trips, zero-copy image decoding, layout validation."""

from __future__ import annotations

import numpy as np
import pytest
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


CODECS = {
    "sensor_msgs/msg/Image": (images(), encode_image, decode_image, rb_image),
    "sensor_msgs/msg/CameraInfo": (camera_infos, encode_camera_info, decode_camera_info, rb_camera_info),
    "geometry_msgs/msg/TwistStamped": (twists, encode_twist_stamped, decode_twist_stamped, rb_twist),
    "sensor_msgs/msg/JointState": (joint_states(), encode_joint_state, decode_joint_state, rb_joint_state),
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
    with pytest.raises(UnsupportedEncoding, match="yuv422"):
        image_from_array(np.zeros((2, 2), np.uint8), "yuv422")


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
        (_image_payload(2, 3, "yuv422", 6, bytes(12)), UnsupportedEncoding, "yuv422"),
        (_image_payload(2, 3, "mono8", 3, bytes(6), big=2), InconsistentMessage, "is_bigendian"),
        (_image_payload(2, 3, "mono8", 3, bytes(6))[:-1], TruncatedMessage, "data"),
        (_image_payload(2, 3, "mono8", 3, bytes(6)) + bytes(8), InconsistentMessage, "unexpected bytes"),
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
    with pytest.raises(InconsistentMessage, match="distorted"):
        CameraInfo(header, 48, 64, d=[0.1, 0, 0, 0, 0], k=k).to_intrinsics()
    with pytest.raises(InconsistentMessage, match="binning"):
        CameraInfo(header, 48, 64, k=k, binning_x=2).to_intrinsics()
    with pytest.raises(InconsistentMessage, match="roi"):
        CameraInfo(header, 48, 64, k=k, roi=RegionOfInterest(0, 0, 10, 10)).to_intrinsics()
    with pytest.raises(InconsistentMessage, match="k has 8 values"):
        CameraInfo(header, 48, 64, k=k[:8])


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
