"""`sensor_msgs/msg/CompressedImage` frames: PNG (lossless) or JPEG encoding of a `sensor_msgs/msg/Image` (`format`
is "png" or "jpeg", as `image_transport`'s compressed plugin and Foxglove expect; the CDR codec is the protocol's,
`ddvs_service.protocol.compressed`)."""

from __future__ import annotations

import numpy as np

from ddvs_service.protocol import CompressedImage, Image, encode_compressed_image

FORMATS = ("png", "jpeg")


def compress_image(image: Image, fmt: str, jpeg_quality: int = 90) -> bytes:
    """The CompressedImage payload of `image` (grey or colour, 8 or 16 bit; JPEG: 8 bit only)."""
    import cv2

    if fmt not in FORMATS:
        raise ValueError(f"compressed image format {fmt!r}: expected one of {FORMATS}")
    pixels = image.array
    if image.encoding in ("rgb8", "rgba8"):
        pixels = cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR if image.encoding == "rgb8" else cv2.COLOR_RGBA2BGRA)
    if fmt == "jpeg" and pixels.dtype != np.uint8:
        raise ValueError(f"JPEG needs 8-bit pixels; {image.encoding} frames can be recorded as png or raw")
    params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if fmt == "jpeg" else [cv2.IMWRITE_PNG_COMPRESSION, 1]
    ok, data = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", np.ascontiguousarray(pixels), params)
    if not ok:
        raise ValueError(f"cannot encode a {image.encoding} {image.width}×{image.height} frame as {fmt}")
    return encode_compressed_image(CompressedImage(image.header, fmt, data.tobytes()))
