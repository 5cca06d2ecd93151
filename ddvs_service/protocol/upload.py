"""Images carried inside JSON commands (`set_reference` with `source="upload"`): base64 PNG or `.npy`.

Decoding checks the declared size in the PNG IHDR chunk or the `.npy` header *before* decompressing, so a
forged or hostile upload cannot make the service allocate more than `max_pixels` pixels.
"""

from __future__ import annotations

import base64
import binascii
import io
import struct
from typing import Literal

import numpy as np
from numpy.lib import format as npy_format
from numpy.typing import NDArray

from ddvs_service.protocol.errors import InvalidMessage, MessageTooLarge

UploadFormat = Literal["png", "npy"]
MAX_PIXELS = 4096 * 4096
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_NPY_HEADER_READERS = {(1, 0): npy_format.read_array_header_1_0, (2, 0): npy_format.read_array_header_2_0}
_NPY_DTYPES = ("|u1", "<u2", ">u2", "<f4", ">f4", "<f8", ">f8")


def encode_upload(image: NDArray, fmt: UploadFormat = "png") -> str:
    """Base64 text of `image` ((H, W) or (H, W, C)) as PNG (uint8/uint16, lossless) or `.npy` (any listed dtype)."""
    if fmt == "png":
        import cv2  # deferred: importing OpenCV takes ~0.5 s

        ok, data = cv2.imencode(".png", np.ascontiguousarray(image))
        if not ok:
            raise ValueError(f"could not encode an image of shape {image.shape} and dtype {image.dtype} as PNG")
        raw = data.tobytes()
    else:
        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(image), allow_pickle=False)
        raw = buf.getvalue()
    return base64.b64encode(raw).decode("ascii")


def _check_pixels(height: int, width: int, max_pixels: int) -> None:
    if height * width > max_pixels:
        raise MessageTooLarge(f"uploaded image is {width}×{height} pixels; the maximum is {max_pixels} pixels")
    if height == 0 or width == 0:
        raise InvalidMessage(f"uploaded image is {width}×{height} pixels; expected a non-empty image")


def _decode_png(raw: bytes, max_pixels: int) -> NDArray:
    if len(raw) < 24 or raw[:8] != _PNG_SIGNATURE or raw[12:16] != b"IHDR":
        raise InvalidMessage("uploaded 'png' data does not start with a PNG signature and IHDR chunk")
    width, height = struct.unpack(">II", raw[16:24])
    _check_pixels(height, width, max_pixels)
    import cv2  # deferred: importing OpenCV takes ~0.5 s

    image = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InvalidMessage(f"uploaded PNG ({width}×{height}) could not be decoded")
    return image


def _decode_npy(raw: bytes, max_pixels: int) -> NDArray:
    f = io.BytesIO(raw)
    try:
        version = npy_format.read_magic(f)
        if version not in _NPY_HEADER_READERS:
            raise ValueError(f".npy format version {version}; expected 1.0 or 2.0")
        shape, fortran_order, dtype = _NPY_HEADER_READERS[version](f)
    except (ValueError, SyntaxError, TypeError, struct.error) as exc:
        raise InvalidMessage(f"uploaded 'npy' data has no valid .npy header: {exc}") from exc
    if dtype.str not in _NPY_DTYPES:
        raise InvalidMessage(f"uploaded .npy has dtype {dtype.str}; expected one of {', '.join(_NPY_DTYPES)}")
    if len(shape) not in (2, 3) or (len(shape) == 3 and shape[2] not in (1, 3, 4)):
        raise InvalidMessage(f"uploaded .npy has shape {shape}; expected (H, W) or (H, W, C) with C in 1, 3, 4")
    _check_pixels(shape[0], shape[1], max_pixels)
    expected = int(np.prod(shape)) * dtype.itemsize
    body = raw[f.tell() :]
    if len(body) != expected:
        raise InvalidMessage(f"uploaded .npy body has {len(body)} bytes; its header {shape} {dtype} needs {expected}")
    return np.frombuffer(body, dtype=dtype).reshape(shape, order="F" if fortran_order else "C").copy()


def decode_upload(text: str, fmt: UploadFormat, max_pixels: int = MAX_PIXELS) -> NDArray:
    """The image array of base64 `text` in format `fmt`; raises `InvalidMessage` / `MessageTooLarge`."""
    try:
        raw = base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError) as exc:
        raise InvalidMessage(f"uploaded image is not valid base64: {exc}") from exc
    return _decode_png(raw, max_pixels) if fmt == "png" else _decode_npy(raw, max_pixels)
