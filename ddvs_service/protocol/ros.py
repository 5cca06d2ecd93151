"""ROS 2 data-plane messages and their CDR codecs, byte-identical to the ROS 2 (Humble … Kilted) definitions.

Types: `builtin_interfaces/Time`, `std_msgs/Header`, `sensor_msgs/Image`, `sensor_msgs/CameraInfo` (with
`RegionOfInterest`), `geometry_msgs/TwistStamped`, `sensor_msgs/JointState`, `std_msgs/Float64MultiArray` (what
ros2_control's forward command controllers take) and the `std_srvs/srv/Trigger` request and response. Field order and
alignment follow the `.msg` definitions exactly (see `cdr.py` for the layout rules); `tests/test_protocol_ros.py`
checks every encoder against `rosbags` and against rclpy (the ROS 2 Kilted wheels) both ways.

Decoders take the payload as bytes/memoryview (`sample.payload.to_bytes()`), raise only `ProtocolError`
subclasses, and check every size against `max_bytes` before allocating. `decode_image` returns pixel data as a
numpy view into the payload (no copy); `Image.array` reshapes it, still without copying.

Units and frames: `Time` is seconds + nanoseconds since the Unix epoch; a twist is `[v (m/s); ω (rad/s)]` expressed
in `header.frame_id` (the camera frame, OpenCV axes, for `…/servo/twist`); joint positions in rad, velocities in
rad/s, efforts in N·m.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.protocol.cdr import CdrReader, CdrWriter
from ddvs_service.protocol.errors import InconsistentMessage, MessageTooLarge, UnsupportedEncoding

IMAGE_MAX_BYTES = 64 << 20
"""Default bound on an image payload (64 MiB: 4096×4096 RGBA8 fits)."""
MESSAGE_MAX_BYTES = 1 << 20
"""Default bound on the other (small) messages."""

_INT32 = (-(2**31), 2**31 - 1)
_UINT32_MAX = 2**32 - 1
_NS_PER_S = 1_000_000_000


def _check_range(what: str, value: int, lo: int, hi: int) -> None:
    if not (isinstance(value, int | np.integer) and lo <= value <= hi):
        raise InconsistentMessage(f"{what} = {value!r}; expected an integer in [{lo}, {hi}]")


@dataclass(frozen=True)
class Time:
    """`builtin_interfaces/Time`: `sec` (int32) + `nanosec` (uint32, < 1e9) since the Unix epoch."""

    sec: int
    nanosec: int

    def __post_init__(self) -> None:
        _check_range("Time.sec", self.sec, *_INT32)
        _check_range("Time.nanosec", self.nanosec, 0, _NS_PER_S - 1)

    @classmethod
    def from_ns(cls, ns: int) -> Time:
        """From integer nanoseconds since the epoch (negative values floor towards −∞, as ROS does)."""
        sec, nanosec = divmod(int(ns), _NS_PER_S)
        return cls(sec, nanosec)

    @classmethod
    def now(cls) -> Time:
        return cls.from_ns(time.time_ns())

    def to_ns(self) -> int:
        return self.sec * _NS_PER_S + self.nanosec


@dataclass(frozen=True)
class Header:
    """`std_msgs/Header`: acquisition time of the data and the coordinate frame it is expressed in."""

    stamp: Time
    frame_id: str


class PixelFormat(NamedTuple):
    """Memory layout of one `sensor_msgs/Image` encoding: element type (little-endian form) and channel count."""

    dtype: np.dtype
    channels: int

    @property
    def bytes_per_pixel(self) -> int:
        return self.dtype.itemsize * self.channels


ENCODINGS: dict[str, PixelFormat] = {
    "mono8": PixelFormat(np.dtype("u1"), 1),
    "8UC1": PixelFormat(np.dtype("u1"), 1),
    "rgb8": PixelFormat(np.dtype("u1"), 3),
    "bgr8": PixelFormat(np.dtype("u1"), 3),
    "rgba8": PixelFormat(np.dtype("u1"), 4),
    "bgra8": PixelFormat(np.dtype("u1"), 4),
    "mono16": PixelFormat(np.dtype("<u2"), 1),
    "16UC1": PixelFormat(np.dtype("<u2"), 1),
    "32FC1": PixelFormat(np.dtype("<f4"), 1),
    "rgb16": PixelFormat(np.dtype("<u2"), 3),
    "bgr16": PixelFormat(np.dtype("<u2"), 3),
    "rgba16": PixelFormat(np.dtype("<u2"), 4),
    "bgra16": PixelFormat(np.dtype("<u2"), 4),
    # 4:2:2 YUV, two bytes a pixel: `yuv422` and `uyvy` are U Y0 V Y1, `yuv422_yuy2` and `yuyv` are Y0 U Y1 V
    "yuv422": PixelFormat(np.dtype("u1"), 2),
    "uyvy": PixelFormat(np.dtype("u1"), 2),
    "yuv422_yuy2": PixelFormat(np.dtype("u1"), 2),
    "yuyv": PixelFormat(np.dtype("u1"), 2),
    **{f"bayer_{pattern}{bits}": PixelFormat(np.dtype("u1" if bits == 8 else "<u2"), 1)
       for pattern in ("rggb", "bggr", "gbrg", "grbg") for bits in (8, 16)},
}
"""Supported `sensor_msgs/image_encodings` names (`ddvs_service.grey` turns each into grey levels)."""


def pixel_format(encoding: str) -> PixelFormat:
    try:
        return ENCODINGS[encoding]
    except KeyError:
        raise UnsupportedEncoding(
            f"image encoding {encoding!r} is not supported; expected one of {', '.join(ENCODINGS)}"
        ) from None


@dataclass(eq=False)
class Image:
    """`sensor_msgs/Image`. `data` is a flat uint8 array of `height*step` bytes (often a view of a payload).

    Rows are `step` bytes apart; pixels are packed in row-major order, `is_bigendian` (0/1) gives the byte order of
    multi-byte elements. Construction validates the layout and raises `ProtocolError` subclasses.
    """

    header: Header
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: NDArray[np.uint8]

    def __post_init__(self) -> None:
        if not isinstance(self.data, np.ndarray):
            self.data = np.frombuffer(self.data, dtype=np.uint8)
        if not self.data.flags.c_contiguous:
            self.data = np.ascontiguousarray(self.data)
        if self.data.dtype != np.uint8 or self.data.ndim != 1:
            raise InconsistentMessage(
                f"Image.data must be a flat uint8 array, got dtype {self.data.dtype} with shape {self.data.shape}"
            )
        fmt = pixel_format(self.encoding)
        _check_range("Image.height", self.height, 0, _UINT32_MAX)
        _check_range("Image.width", self.width, 0, _UINT32_MAX)
        _check_range("Image.step", self.step, 0, _UINT32_MAX)
        _check_range("Image.is_bigendian", int(self.is_bigendian), 0, 1)
        if self.step < self.width * fmt.bytes_per_pixel:
            raise InconsistentMessage(
                f"Image.step = {self.step} bytes is shorter than a row: width {self.width} × "
                f"{fmt.bytes_per_pixel} bytes per pixel ({self.encoding}) = {self.width * fmt.bytes_per_pixel}"
            )
        if self.step % fmt.dtype.itemsize:
            raise InconsistentMessage(
                f"Image.step = {self.step} is not a multiple of the {fmt.dtype.itemsize}-byte element of "
                f"{self.encoding}: rows would be misaligned"
            )
        if self.height * self.step != self.data.size:
            raise InconsistentMessage(
                f"Image data has {self.data.size} bytes; expected height × step = {self.height} × {self.step} = "
                f"{self.height * self.step}"
            )

    @property
    def array(self) -> NDArray:
        """The pixels as a numpy view of `data` (no copy): shape (H, W) for one channel, (H, W, C) otherwise.

        Channel order is the encoding's (rgb8 → R, G, B). Read-only when `data` views an immutable payload.
        """
        fmt = ENCODINGS[self.encoding]
        dtype = fmt.dtype.newbyteorder(">" if self.is_bigendian else "<")
        size = fmt.dtype.itemsize
        shape: tuple[int, ...]
        strides: tuple[int, ...]
        if fmt.channels == 1:
            shape, strides = (self.height, self.width), (self.step, size)
        else:
            shape, strides = (self.height, self.width, fmt.channels), (self.step, fmt.bytes_per_pixel, size)
        return np.ndarray(shape, dtype=dtype, buffer=self.data, offset=0, strides=strides)


@dataclass(frozen=True)
class RegionOfInterest:
    """`sensor_msgs/RegionOfInterest` in pixels; all zeros (or height/width 0) means the full image."""

    x_offset: int = 0
    y_offset: int = 0
    height: int = 0
    width: int = 0
    do_rectify: bool = False

    def __post_init__(self) -> None:
        for name in ("x_offset", "y_offset", "height", "width"):
            _check_range(f"RegionOfInterest.{name}", getattr(self, name), 0, _UINT32_MAX)


def _float_array(what: str, values: ArrayLike, length: int | None = None) -> NDArray[np.float64]:
    a = np.array(values, dtype=np.float64).reshape(-1)
    if length is not None and a.size != length:
        raise InconsistentMessage(f"{what} has {a.size} values; expected {length}")
    return a


@dataclass(eq=False)
class CameraInfo:
    """`sensor_msgs/CameraInfo`: calibration of the camera that took the images (pixels, OpenCV conventions).

    `k` (3×3), `r` (3×3) and `p` (3×4) are row-major flat arrays; `d` the distortion coefficients of
    `distortion_model` ("plumb_bob": k1, k2, t1, t2, k3; "rational_polynomial": k1, k2, t1, t2, k3, k4, k5, k6;
    "equidistant": k1, k2, k3, k4). As in ROS, `k` and `d` describe the raw (distorted) image and the first 3×3 of
    `p` the rectified one, so one camera info serves both `image_raw` and `image_rect`. Pixel centres at integer
    coordinates, as in the project.
    """

    header: Header
    height: int
    width: int
    distortion_model: str = "plumb_bob"
    d: NDArray[np.float64] = field(default_factory=lambda: np.zeros(5))
    k: NDArray[np.float64] = field(default_factory=lambda: np.eye(3).reshape(-1))
    r: NDArray[np.float64] = field(default_factory=lambda: np.eye(3).reshape(-1))
    p: NDArray[np.float64] = field(default_factory=lambda: np.eye(3, 4).reshape(-1))
    binning_x: int = 0
    binning_y: int = 0
    roi: RegionOfInterest = field(default_factory=RegionOfInterest)

    def __post_init__(self) -> None:
        _check_range("CameraInfo.height", self.height, 0, _UINT32_MAX)
        _check_range("CameraInfo.width", self.width, 0, _UINT32_MAX)
        _check_range("CameraInfo.binning_x", self.binning_x, 0, _UINT32_MAX)
        _check_range("CameraInfo.binning_y", self.binning_y, 0, _UINT32_MAX)
        self.d = _float_array("CameraInfo.d", self.d)
        self.k = _float_array("CameraInfo.k", self.k, 9)
        self.r = _float_array("CameraInfo.r", self.r, 9)
        self.p = _float_array("CameraInfo.p", self.p, 12)

    @classmethod
    def from_intrinsics(cls, intrinsics: Intrinsics, header: Header) -> CameraInfo:
        """Undistorted pinhole camera: plumb_bob with zero coefficients, R = I, P = [K | 0]."""
        K = intrinsics.K
        return cls(
            header=header,
            height=intrinsics.height,
            width=intrinsics.width,
            k=K.reshape(-1),
            p=np.hstack([K, np.zeros((3, 1))]).reshape(-1),
        )

    @property
    def distorted(self) -> bool:
        """True when `d` has a non-zero coefficient (the raw image differs from a pinhole image)."""
        return bool(np.any(self.d != 0.0))

    def to_intrinsics(self) -> Intrinsics:
        """The pinhole `Intrinsics` of the raw image, from `k` (distortion aside). Raises `InconsistentMessage` for
        what the engine cannot model: binning > 1, a region of interest smaller than the image, a malformed K."""
        return self._pinhole("k", self.k.reshape(3, 3))

    def rectified_intrinsics(self) -> Intrinsics:
        """The pinhole `Intrinsics` of the rectified image (`image_rect`): the first 3×3 of `p`, or `k` when `p` is
        all zeros (a driver without calibration leaves it so). Same checks as `to_intrinsics`; a monocular P has
        no translation column (P[:, 3] = 0)."""
        P = self.p.reshape(3, 4)
        if not np.any(P):
            return self.to_intrinsics()
        if np.any(P[:, 3] != 0.0):
            raise InconsistentMessage(f"CameraInfo.p = {self.p.tolist()}: expected a monocular projection matrix "
                                      "(last column 0); a stereo pair's right camera is not supported")
        return self._pinhole("p", P[:, :3])

    def _pinhole(self, what: str, K: NDArray[np.float64]) -> Intrinsics:
        if self.binning_x > 1 or self.binning_y > 1:
            raise InconsistentMessage(f"CameraInfo binning {self.binning_x}×{self.binning_y}: expected 0 or 1")
        roi = self.roi
        if (roi.width, roi.height) != (0, 0) and (roi.x_offset, roi.y_offset, roi.width, roi.height) != (
            0,
            0,
            self.width,
            self.height,
        ):
            raise InconsistentMessage(f"CameraInfo.roi = {roi}: expected the full image (or all zeros)")
        k = [float(v) for v in K.reshape(-1)]
        if k[3] != 0.0 or k[6:] != [0.0, 0.0, 1.0]:
            raise InconsistentMessage(f"CameraInfo.{what} = {k}: expected an upper-triangular 3×3 block with "
                                      "[2,2] = 1")
        try:
            return Intrinsics(fx=k[0], fy=k[4], cx=k[2], cy=k[5], width=self.width, height=self.height, skew=k[1])
        except ValueError as exc:
            raise InconsistentMessage(f"CameraInfo.{what} does not describe a pinhole camera: {exc}") from exc


@dataclass(eq=False)
class TwistStamped:
    """`geometry_msgs/TwistStamped`: `linear` v (m/s) and `angular` ω (rad/s), 3 finite floats each, expressed in
    `header.frame_id`. Non-finite values are rejected: a NaN velocity must never reach a robot."""

    header: Header
    linear: NDArray[np.float64]
    angular: NDArray[np.float64]

    def __post_init__(self) -> None:
        self.linear = _float_array("TwistStamped.linear", self.linear, 3)
        self.angular = _float_array("TwistStamped.angular", self.angular, 3)
        if not (np.isfinite(self.linear).all() and np.isfinite(self.angular).all()):
            raise InconsistentMessage(
                f"TwistStamped has non-finite values (linear {self.linear.tolist()}, angular {self.angular.tolist()})"
            )

    @property
    def vector(self) -> NDArray[np.float64]:
        """The 6-vector `[v; ω]`."""
        return np.concatenate([self.linear, self.angular])


@dataclass(eq=False)
class JointState:
    """`sensor_msgs/JointState`: per named joint, position (rad), velocity (rad/s), effort (N·m).

    Each of position/velocity/effort is empty or as long as `name` (the ROS contract, enforced here).
    """

    header: Header
    name: list[str]
    position: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    velocity: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    effort: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        self.name = list(self.name)
        for attr in ("position", "velocity", "effort"):
            values = _float_array(f"JointState.{attr}", getattr(self, attr))
            if values.size not in (0, len(self.name)):
                raise InconsistentMessage(
                    f"JointState.{attr} has {values.size} values; expected 0 or one per joint ({len(self.name)})"
                )
            setattr(self, attr, values)


# --- codecs --------------------------------------------------------------------------------------------------------


def write_header(w: CdrWriter, header: Header) -> None:
    """A `std_msgs/Header` into `w` (the leading field of every stamped message)."""
    w.int32(header.stamp.sec)
    w.uint32(header.stamp.nanosec)
    w.string(header.frame_id)


def read_header(r: CdrReader) -> Header:
    """A `std_msgs/Header` from `r`."""
    sec = r.int32("header.stamp.sec")
    nanosec = r.uint32("header.stamp.nanosec")
    return Header(Time(sec, nanosec), r.string("header.frame_id"))


def encode_image(msg: Image) -> bytes:
    """CDR payload of a `sensor_msgs/Image` (the pixel bytes are copied once, into the result)."""
    w = CdrWriter()
    write_header(w, msg.header)
    w.uint32(msg.height)
    w.uint32(msg.width)
    w.string(msg.encoding)
    w.uint8(int(msg.is_bigendian))
    w.uint32(msg.step)
    w.uint8_sequence(msg.data)
    return w.finish()


def decode_image(buf: bytes | bytearray | memoryview, max_bytes: int = IMAGE_MAX_BYTES) -> Image:
    """Decode a `sensor_msgs/Image` payload; `data` is a view into `buf` (keep `buf` alive, it is not copied)."""
    r = CdrReader(buf, max_bytes)
    header = read_header(r)
    height = r.uint32("height")
    width = r.uint32("width")
    encoding = r.string("encoding")
    is_bigendian = r.uint8("is_bigendian")
    step = r.uint32("step")
    pixel_format(encoding)
    if height * step > max_bytes:
        raise MessageTooLarge(f"image height × step = {height} × {step} bytes exceeds the maximum of {max_bytes}")
    data = r.uint8_sequence("data")
    return Image(header, height, width, encoding, is_bigendian, step, np.frombuffer(data, dtype=np.uint8))


def image_from_array(array: NDArray, encoding: str, header: Header | None = None, frame_id: str = "camera") -> Image:
    """Wrap a numpy image as an `Image` without copying when `array` is C-contiguous.

    `array` is (H, W) or (H, W, C) with the element type of `encoding` (uint8 for mono8/rgb8/bgr8/…, uint16 for
    mono16/16UC1, float32 for 32FC1); either byte order. `header=None` stamps it now with `frame_id`.
    """
    fmt = pixel_format(encoding)
    a = np.asarray(array)
    if a.ndim == 3 and fmt.channels == 1 and a.shape[2] == 1:
        a = a[:, :, 0]
    expected_ndim = 2 if fmt.channels == 1 else 3
    if a.ndim != expected_ndim or (fmt.channels > 1 and a.shape[2] != fmt.channels):
        want = "(H, W)" if fmt.channels == 1 else f"(H, W, {fmt.channels})"
        raise InconsistentMessage(f"{encoding} image must have shape {want}, got {a.shape}")
    if a.dtype.kind != fmt.dtype.kind or a.dtype.itemsize != fmt.dtype.itemsize:
        raise InconsistentMessage(f"{encoding} image must have dtype {fmt.dtype.name}, got {a.dtype}")
    is_bigendian = int(a.dtype.byteorder == ">" or (a.dtype.byteorder == "=" and not np.little_endian))
    a = np.ascontiguousarray(a)
    height, width = a.shape[:2]
    header = header if header is not None else Header(Time.now(), frame_id)
    data = a.reshape(-1).view(np.uint8)
    return Image(header, height, width, encoding, is_bigendian, width * fmt.bytes_per_pixel, data)


def encode_camera_info(msg: CameraInfo) -> bytes:
    """CDR payload of a `sensor_msgs/CameraInfo`."""
    w = CdrWriter()
    write_header(w, msg.header)
    w.uint32(msg.height)
    w.uint32(msg.width)
    w.string(msg.distortion_model)
    w.float64_array(msg.d)
    w.float64_array(msg.k, 9)
    w.float64_array(msg.r, 9)
    w.float64_array(msg.p, 12)
    w.uint32(msg.binning_x)
    w.uint32(msg.binning_y)
    w.uint32(msg.roi.x_offset)
    w.uint32(msg.roi.y_offset)
    w.uint32(msg.roi.height)
    w.uint32(msg.roi.width)
    w.boolean(msg.roi.do_rectify)
    return w.finish()


def decode_camera_info(buf: bytes | bytearray | memoryview, max_bytes: int = MESSAGE_MAX_BYTES) -> CameraInfo:
    r = CdrReader(buf, max_bytes)
    header = read_header(r)
    height = r.uint32("height")
    width = r.uint32("width")
    model = r.string("distortion_model")
    d = r.float64_array("d")
    k = r.float64_array("k", 9)
    rr = r.float64_array("r", 9)
    p = r.float64_array("p", 12)
    binning_x = r.uint32("binning_x")
    binning_y = r.uint32("binning_y")
    roi = RegionOfInterest(
        x_offset=r.uint32("roi.x_offset"),
        y_offset=r.uint32("roi.y_offset"),
        height=r.uint32("roi.height"),
        width=r.uint32("roi.width"),
        do_rectify=r.boolean("roi.do_rectify"),
    )
    return CameraInfo(header, height, width, model, d, k, rr, p, binning_x, binning_y, roi)


def encode_twist_stamped(msg: TwistStamped) -> bytes:
    """CDR payload of a `geometry_msgs/TwistStamped`."""
    w = CdrWriter()
    write_header(w, msg.header)
    w.float64_array(np.concatenate((msg.linear, msg.angular)), length=6)  # linear then angular, one aligned block
    return w.finish()


def decode_twist_stamped(buf: bytes | bytearray | memoryview, max_bytes: int = MESSAGE_MAX_BYTES) -> TwistStamped:
    r = CdrReader(buf, max_bytes)
    header = read_header(r)
    linear = [r.float64(f"twist.linear.{c}") for c in "xyz"]
    angular = [r.float64(f"twist.angular.{c}") for c in "xyz"]
    return TwistStamped(header, np.array(linear), np.array(angular))


def encode_joint_state(msg: JointState) -> bytes:
    """CDR payload of a `sensor_msgs/JointState`."""
    w = CdrWriter()
    write_header(w, msg.header)
    w.string_sequence(msg.name)
    w.float64_array(msg.position)
    w.float64_array(msg.velocity)
    w.float64_array(msg.effort)
    return w.finish()


def decode_joint_state(buf: bytes | bytearray | memoryview, max_bytes: int = MESSAGE_MAX_BYTES) -> JointState:
    r = CdrReader(buf, max_bytes)
    header = read_header(r)
    name = r.string_sequence("name")
    position = r.float64_array("position")
    velocity = r.float64_array("velocity")
    effort = r.float64_array("effort")
    return JointState(header, name, position, velocity, effort)


@dataclass(eq=False)
class Float64MultiArray:
    """`std_msgs/Float64MultiArray`: `data` with an optional layout (`dims` of (label, size, stride), `data_offset`).

    ros2_control's `forward_command_controller` (e.g. `forward_velocity_controller/commands`) reads `data` as one
    value per configured joint, in the controller's joint order, and ignores the layout."""

    data: NDArray[np.float64]
    dims: list[tuple[str, int, int]] = field(default_factory=list)
    data_offset: int = 0

    def __post_init__(self) -> None:
        self.data = _float_array("Float64MultiArray.data", self.data)
        self.dims = [(str(label), int(size), int(stride)) for label, size, stride in self.dims]
        for label, size, stride in self.dims:
            _check_range(f"Float64MultiArray dimension {label!r} size", size, 0, _UINT32_MAX)
            _check_range(f"Float64MultiArray dimension {label!r} stride", stride, 0, _UINT32_MAX)
        _check_range("Float64MultiArray.data_offset", self.data_offset, 0, _UINT32_MAX)


def encode_float64_multi_array(msg: Float64MultiArray) -> bytes:
    """CDR payload of a `std_msgs/Float64MultiArray`."""
    w = CdrWriter()
    w.uint32(len(msg.dims))
    for label, size, stride in msg.dims:
        w.string(label)
        w.uint32(size)
        w.uint32(stride)
    w.uint32(msg.data_offset)
    w.float64_array(msg.data)
    return w.finish()


def decode_float64_multi_array(buf: bytes | bytearray | memoryview,
                               max_bytes: int = MESSAGE_MAX_BYTES) -> Float64MultiArray:
    r = CdrReader(buf, max_bytes)
    n = r.uint32("layout.dim count")
    r.check_length(n, 12, "layout.dim")  # each dimension takes at least a string length, size and stride
    dims = [(r.string(f"layout.dim[{i}].label"), r.uint32(f"layout.dim[{i}].size"), r.uint32(f"layout.dim[{i}].stride"))
            for i in range(n)]
    offset = r.uint32("layout.data_offset")
    return Float64MultiArray(r.float64_array("data"), dims, offset)


def encode_trigger_request() -> bytes:
    """`std_srvs/srv/Trigger` request: no fields (rosidl adds one uint8 so that the structure is not empty)."""
    w = CdrWriter()
    w.uint8(0)
    return w.finish()


def decode_trigger_request(buf: bytes | bytearray | memoryview) -> None:
    """Check that `buf` is a `std_srvs/srv/Trigger` request (CDR_LE header and its one placeholder byte)."""
    CdrReader(buf, MESSAGE_MAX_BYTES).uint8("structure_needs_at_least_one_member")


def encode_trigger_response(success: bool, message: str) -> bytes:
    """`std_srvs/srv/Trigger` response: `success`, then a human-readable `message`."""
    w = CdrWriter()
    w.boolean(success)
    w.string(message)
    return w.finish()


def decode_trigger_response(buf: bytes | bytearray | memoryview) -> tuple[bool, str]:
    r = CdrReader(buf, MESSAGE_MAX_BYTES)
    return r.boolean("success"), r.string("message")
