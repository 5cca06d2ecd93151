"""Camera frames as the grey levels the engine registers: every supported `sensor_msgs/Image` encoding and the JPEG
and PNG files of a `sensor_msgs/CompressedImage`, converted with OpenCV.

Grey levels are in [0, 255] (the engine's convention, docs/ARCHITECTURE.md): 8-bit frames give uint8 (colour by
ITU-R BT.601 luma, `cv2.cvtColor`; 4:2:2 YUV by its Y samples; Bayer mosaics demosaiced to grey), 16-bit frames
float32 scaled by 255/65535, `32FC1` its own values. The decoded size of a compressed frame is read from the file's
header and bounded before anything is decoded (`protocol.image_size`), by the same byte limit as a raw frame's
payload.
"""

from __future__ import annotations

from functools import cache

import numpy as np
from numpy.typing import NDArray

from ddvs_service.protocol.compressed import CompressedImage, decode_compressed_image
from ddvs_service.protocol.errors import InconsistentMessage
from ddvs_service.protocol.image_size import check_decoded_size, jpeg_header, png_header
from ddvs_service.protocol.ros import ENCODINGS, Image, decode_image

_SCALE_16 = np.float32(255.0 / 65535.0)


@cache
def _conversions() -> dict[str, int | None]:
    """OpenCV colour conversion to grey of each encoding (None: already grey)."""
    import cv2

    bayer = {"rggb": cv2.COLOR_BayerRGGB2GRAY, "bggr": cv2.COLOR_BayerBGGR2GRAY,
             "gbrg": cv2.COLOR_BayerGBRG2GRAY, "grbg": cv2.COLOR_BayerGRBG2GRAY}
    table: dict[str, int | None] = {
        "mono8": None, "8UC1": None, "mono16": None, "16UC1": None, "32FC1": None,
        "rgb8": cv2.COLOR_RGB2GRAY, "bgr8": cv2.COLOR_BGR2GRAY, "rgba8": cv2.COLOR_RGBA2GRAY,
        "bgra8": cv2.COLOR_BGRA2GRAY, "rgb16": cv2.COLOR_RGB2GRAY, "bgr16": cv2.COLOR_BGR2GRAY,
        "rgba16": cv2.COLOR_RGBA2GRAY, "bgra16": cv2.COLOR_BGRA2GRAY,
        "yuv422": cv2.COLOR_YUV2GRAY_UYVY, "uyvy": cv2.COLOR_YUV2GRAY_UYVY,
        "yuv422_yuy2": cv2.COLOR_YUV2GRAY_YUY2, "yuyv": cv2.COLOR_YUV2GRAY_YUY2,
        **{f"bayer_{pattern}{bits}": code for pattern, code in bayer.items() for bits in (8, 16)},
    }  # fmt: skip
    assert set(table) == set(ENCODINGS), "every protocol encoding needs its grey conversion"
    return table


def grey_image(image: Image) -> NDArray:
    """Grey levels (H, W) of `image`: a view of its pixels for mono8/8UC1/32FC1, converted otherwise (module
    docstring). Raises `InconsistentMessage` for a 4:2:2 or Bayer frame of odd size."""
    import cv2

    code = _conversions()[image.encoding]
    pixels = image.array
    if not pixels.dtype.isnative:  # is_bigendian: OpenCV and the engine read native byte order
        pixels = pixels.astype(pixels.dtype.newbyteorder("="))
    if code is not None:
        if image.encoding.startswith(("yuv", "uyvy", "yuyv", "bayer")) and (image.width % 2 or image.height % 2):
            raise InconsistentMessage(f"{image.encoding} frame is {image.width}×{image.height}; expected an even "
                                      "width and height (2×2 Bayer cells, 4:2:2 pixel pairs)")
        pixels = cv2.cvtColor(np.ascontiguousarray(pixels), code)
    if pixels.dtype == np.uint16:
        return pixels.astype(np.float32) * _SCALE_16
    return pixels


def decode_compressed(msg: CompressedImage, max_bytes: int) -> NDArray:
    """Grey levels (H, W) of a JPEG or PNG frame: uint8, or float32 for a 16-bit PNG. The decoded size its header
    declares is checked against `max_bytes` before decoding (`MessageTooLarge`); a file OpenCV cannot decode raises
    `InconsistentMessage`, an unknown format `UnsupportedEncoding`."""
    import cv2

    codec = msg.codec
    header = png_header(msg.data) if codec == "png" else jpeg_header(msg.data)
    check_decoded_size(header, max_bytes, f"compressed {codec} frame")
    pixels = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH)
    if pixels is None or pixels.shape != (header.height, header.width):
        raise InconsistentMessage(f"compressed {codec} frame ({len(msg.data)} bytes) does not decode to the "
                                  f"{header.width}×{header.height} image its header declares")
    if pixels.dtype == np.uint16:
        return pixels.astype(np.float32) * _SCALE_16
    return np.asarray(pixels)


def checked_frame(payload: bytes | memoryview, compressed: bool,
                  max_bytes: int) -> tuple[Image | CompressedImage, tuple[int, int]]:
    """The message of one camera frame's CDR payload and its size `(width, height)` in pixels, checked without
    decoding any pixel: a `sensor_msgs/Image`, or a `sensor_msgs/CompressedImage` when `compressed` (its JPEG/PNG
    header read, the decoded size it declares bounded by `max_bytes`). Cheap enough for a subscriber's callback;
    `frame_pixels` then gives the grey levels. Raises `ProtocolError` subclasses naming what is wrong."""
    if compressed:
        msg = decode_compressed_image(payload, max_bytes)
        header = png_header(msg.data) if msg.codec == "png" else jpeg_header(msg.data)
        check_decoded_size(header, max_bytes, f"compressed {msg.codec} frame")
        return msg, (header.width, header.height)
    image = decode_image(payload, max_bytes)
    return image, (image.width, image.height)


def frame_pixels(msg: Image | CompressedImage, max_bytes: int) -> NDArray:
    """Grey levels (H, W) of a frame `checked_frame` returned (`grey_image`, `decode_compressed`)."""
    return grey_image(msg) if isinstance(msg, Image) else decode_compressed(msg, max_bytes)
