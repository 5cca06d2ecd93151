"""Frames as real cameras deliver them: every supported encoding and rclpy-serialised CompressedImage messages
decode to the grey levels of the scene (N/N), unsupported ones are refused with the supported list, a decode bomb is
refused from its header, and raw frames through plumb_bob / rational_polynomial / fisheye distortion are rectified
back to the pinhole image (`ddvs_service.rectification`), which is formed by `sim.lens` with the real renderer."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CompressedImage as RosCompressedImage
from sensor_msgs.msg import Image as RosImage

from ddvs_service.camera import Intrinsics
from ddvs_service.grey import decode_compressed, grey_image
from ddvs_service.lie import pose
from ddvs_service.protocol import (
    ENCODINGS,
    IMAGE_MAX_BYTES,
    CompressedImage,
    Header,
    MessageTooLarge,
    Time,
    UnsupportedEncoding,
    decode_compressed_image,
    decode_image,
    encode_compressed_image,
)
from ddvs_service.protocol.image_size import jpeg_header, png_header
from ddvs_service.rectification import camera_geometry

H, W = 120, 160


def _scene() -> np.ndarray:
    """A smooth colour picture (BGR uint8) whose three channels differ: a wrong channel order or Bayer pattern shows."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    b = 128 + 100 * np.sin(x / 9.0)
    g = 128 + 90 * np.cos(y / 7.0)
    r = 128 + 110 * np.sin((x + y) / 11.0)
    return np.clip(np.stack([b, g, r], axis=2), 0, 255).astype(np.uint8)


def _mosaic(bgr: np.ndarray, pattern: str) -> np.ndarray:
    """The Bayer mosaic of `bgr`: `pattern` names the colours of the 2×2 cell, row by row (rggb: R G / G B)."""
    channel = {"r": 2, "g": 1, "b": 0}
    out = np.empty(bgr.shape[:2], bgr.dtype)
    for k, colour in enumerate(pattern):
        dy, dx = divmod(k, 2)
        out[dy::2, dx::2] = bgr[dy::2, dx::2, channel[colour]]
    return out


def _yuv422(grey: np.ndarray, luma_first: bool) -> np.ndarray:
    """4:2:2 pixel pairs with luma `grey` and neutral chroma: Y U Y V (yuyv) or U Y V Y (uyvy), (H, W, 2) bytes."""
    out = np.full((*grey.shape, 2), 128, np.uint8)
    out[..., 0 if luma_first else 1] = grey
    return out


def _encoded(encoding: str, bgr: np.ndarray) -> np.ndarray:
    """`bgr` in the memory layout of `encoding` (the array a driver would put in Image.data)."""
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    wide = bgr.astype(np.uint16) * 257
    if encoding in ("mono8", "8UC1"):
        return grey
    if encoding in ("mono16", "16UC1"):
        return grey.astype(np.uint16) * 257
    if encoding == "32FC1":
        return grey.astype(np.float32)
    if encoding.startswith("bayer_"):
        pattern, bits = encoding[6:10], encoding[10:]
        return _mosaic(bgr if bits == "8" else wide, pattern)
    if encoding in ("yuv422", "uyvy", "yuv422_yuy2", "yuyv"):
        return _yuv422(grey, luma_first=encoding in ("yuv422_yuy2", "yuyv"))
    source = bgr if encoding.endswith("8") else wide
    rgb_first = encoding.startswith("rgb")
    pixels = source[..., ::-1] if rgb_first else source
    if "a" in encoding[3:4]:  # rgba / bgra
        alpha = np.full((*pixels.shape[:2], 1), 255 if source.dtype == np.uint8 else 65535, source.dtype)
        pixels = np.concatenate([pixels, alpha], axis=2)
    return np.ascontiguousarray(pixels)


def _rclpy_image(encoding: str, pixels: np.ndarray, big_endian: bool = False) -> bytes:
    msg = RosImage()
    msg.header.stamp.sec, msg.header.frame_id = 7, "camera_optical_frame"
    msg.height, msg.width, msg.encoding = pixels.shape[0], pixels.shape[1], encoding
    msg.is_bigendian = int(big_endian)
    data = pixels.astype(pixels.dtype.newbyteorder(">")) if big_endian else pixels
    msg.step = data.strides[0]
    msg.data = np.ascontiguousarray(data).tobytes()
    return bytes(serialize_message(msg))


def test_every_supported_encoding_decodes_to_the_grey_of_the_scene() -> None:
    """N/N encodings, serialised by rclpy, decode to the BT.601 grey of the scene: exactly (±1 grey level) for mono,
    colour and 4:2:2 frames, within the demosaicing error for Bayer mosaics — which a wrong pattern exceeds."""
    bgr = _scene()
    truth = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(np.float32)
    inner = (slice(4, -4), slice(4, -4))  # demosaicing borders aside
    decoded = []
    for encoding in ENCODINGS:
        grey = grey_image(decode_image(_rclpy_image(encoding, _encoded(encoding, bgr))))
        assert grey.shape == (H, W), encoding
        error = float(np.abs(grey.astype(np.float32) - truth)[inner].mean())
        assert error < (6.0 if encoding.startswith("bayer") else 1.0), (encoding, error)
        decoded.append(encoding)
    print(f"{len(decoded)}/{len(ENCODINGS)} encodings decode to the scene's grey: {', '.join(decoded)}")
    assert len(decoded) == len(ENCODINGS) == 25
    wrong = grey_image(decode_image(_rclpy_image("bayer_bggr8", _mosaic(bgr, "rggb"))))
    assert np.abs(wrong.astype(np.float32) - truth)[inner].mean() > 10.0  # the pattern matters
    big = grey_image(decode_image(_rclpy_image("mono16", _encoded("mono16", bgr), big_endian=True)))
    np.testing.assert_allclose(big, truth, atol=0.01)


def test_unsupported_encodings_and_odd_mosaics_are_refused_naming_what_is_supported() -> None:
    with pytest.raises(UnsupportedEncoding, match=r"'nv21' is not supported; expected one of mono8.*bayer_grbg16"):
        decode_image(_rclpy_image("nv21", np.zeros((4, 4), np.uint8)))
    with pytest.raises(ValueError, match="bayer_rggb8 frame is 5×4; expected an even width and height"):
        grey_image(decode_image(_rclpy_image("bayer_rggb8", np.zeros((4, 5), np.uint8))))


def _rclpy_compressed(fmt: str, data: bytes) -> bytes:
    msg = RosCompressedImage()
    msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id = 3, 4, "camera_optical_frame"
    msg.format = fmt
    msg.data = data
    return bytes(serialize_message(msg))


def test_rclpy_compressed_images_decode_jpeg_and_png_as_image_transport_names_them() -> None:
    """N/N CompressedImage messages serialised by rclpy: JPEG q80 (grey and colour), PNG 8 and 16 bit, in the short
    and in image_transport's long `format`; ours read back in rclpy."""
    bgr = _scene()
    truth = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(np.float32)
    cases = {
        "jpeg": (cv2.imencode(".jpg", truth.astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 80])[1], 3.0),
        "bgr8; jpeg compressed bgr8": (cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 80])[1], 3.0),
        "png": (cv2.imencode(".png", truth.astype(np.uint8))[1], 0.0),
        "bgr8; png compressed bgr8": (cv2.imencode(".png", bgr)[1], 1.0),
        "mono16; png compressed mono16": (cv2.imencode(".png", truth.astype(np.uint16) * 257)[1], 0.01),
    }
    ok = 0
    for fmt, (data, tolerance) in cases.items():
        payload = _rclpy_compressed(fmt, data.tobytes())
        msg = decode_compressed_image(payload)
        assert (msg.header, msg.format, msg.data) == (Header(Time(3, 4), "camera_optical_frame"), fmt, data.tobytes())
        back = deserialize_message(encode_compressed_image(msg), RosCompressedImage)
        assert (back.format, bytes(back.data), back.header.frame_id) == (fmt, data.tobytes(), "camera_optical_frame")
        grey = decode_compressed(msg, IMAGE_MAX_BYTES)
        assert grey.shape == (H, W)
        assert float(np.abs(grey.astype(np.float32) - truth).mean()) <= tolerance, fmt
        ok += 1
    print(f"{ok}/{len(cases)} rclpy CompressedImage messages decoded")
    assert ok == len(cases)
    with pytest.raises(UnsupportedEncoding, match=r"'tiff'.*expected jpeg or png"):
        decode_compressed(CompressedImage(Header(Time(0, 0), ""), "tiff", b"II*\x00"), IMAGE_MAX_BYTES)


def test_a_png_decode_bomb_is_refused_from_its_header_before_decoding() -> None:
    """A 4096×4096 16-bit RGBA PNG of a few hundred KB: its header declares 128 MiB of pixels, over the limit, and
    it is refused before OpenCV allocates them. A JPEG's size is read from its start-of-frame segment."""
    row = b"\x00" + bytes(4096 * 8)
    idat = zlib.compress(row * 4096, 9)

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 4096, 4096, 16, 6, 0, 0, 0))
           + chunk(b"IDAT", idat) + chunk(b"IEND", b""))
    assert len(png) < 1 << 20
    header = png_header(png)
    assert (header.width, header.height, header.channels, header.bytes_per_sample) == (4096, 4096, 4, 2)
    with pytest.raises(MessageTooLarge, match="4096×4096 pixels × 4 channels × 2 bytes = 134217728 bytes decoded"):
        decode_compressed(CompressedImage(Header(Time(0, 0), ""), "png", png), IMAGE_MAX_BYTES)
    jpeg = cv2.imencode(".jpg", np.zeros((48, 64, 3), np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 80])[1].tobytes()
    header = jpeg_header(jpeg)
    assert (header.width, header.height, header.channels, header.bytes_per_sample) == (64, 48, 3, 1)


# --- rectification of raw frames -----------------------------------------------------------------------------------

INTR = Intrinsics(300.0, 300.0, 159.5, 119.5, 320, 240)
LENSES = {
    "plumb_bob": (-0.3, 0.1, 0.0, 0.0, 0.0),
    "rational_polynomial": (-0.25, 0.08, 0.001, -0.001, 0.0, 0.02, 0.0, 0.0),
    "equidistant": (0.05, -0.02, 0.0, 0.0),
}


def _texture() -> np.ndarray:
    noise = cv2.GaussianBlur(np.random.default_rng(31).random((512, 512)).astype(np.float32), (0, 0), 3.0)
    return (40.0 + 175.0 * (noise - noise.min()) / (noise.max() - noise.min())).astype(np.float32)


@pytest.mark.parametrize("model", sorted(LENSES))
def test_raw_frames_through_a_distorting_lens_are_rectified_back_to_the_pinhole_image(model: str) -> None:
    """The raw image of a textured plane through each distortion model, rectified with the maps of its CameraInfo,
    equals the pinhole image of the same view (interpolation aside) where the unrectified one is far off."""
    from sim.freeflyer import render_view
    from sim.lens import DistortedLens
    from sim.surfaces import Plane

    plane = Plane(pose(np.eye(3), [0.0, 0.0, 0.0]), (2.0, 2.0))
    T = pose(np.eye(3), [0.0, 0.0, -0.5])
    texture = _texture()

    def render(intrinsics: Intrinsics) -> np.ndarray:
        return render_view(plane, texture, intrinsics, T)[0]

    lens = DistortedLens(INTR, model, LENSES[model])
    raw = lens.raw(render)
    geometry = camera_geometry(lens.camera_info(Header(Time(0, 0), "camera")), rectified=False)
    assert geometry.intrinsics == INTR and geometry.rectifier is not None
    rectified = geometry.frame(raw)
    pinhole = render(INTR)
    inner = (slice(40, -40), slice(50, -50))
    error = float(np.abs(rectified - pinhole)[inner].mean())
    unrectified = float(np.abs(raw - pinhole)[inner].mean())
    print(f"{model}: rectified vs pinhole {error:.2f} grey levels, raw vs pinhole {unrectified:.2f}")
    assert error < 1.0 and unrectified > 5.0 * error
    as_rect = camera_geometry(lens.camera_info(Header(Time(0, 0), "camera")), rectified=True)
    assert as_rect.rectifier is None and as_rect.intrinsics == INTR


def test_camera_info_of_an_unknown_distortion_model_is_refused() -> None:
    from sim.lens import DistortedLens

    info = DistortedLens(INTR, "plumb_bob", LENSES["plumb_bob"]).camera_info(Header(Time(0, 0), "camera"))
    info.distortion_model = "kannala_brandt"
    with pytest.raises(UnsupportedEncoding, match="'kannala_brandt' is not supported; expected one of plumb_bob"):
        camera_geometry(info, rectified=False)
    info.distortion_model, info.d = "equidistant", np.zeros(5) + 0.1
    with pytest.raises(ValueError, match=r"CameraInfo\.d has 5 coefficients; equidistant has 4"):
        camera_geometry(info, rectified=False)
