"""Images carried inside JSON commands (`set_reference` with `source="upload"`): base64 PNG or `.npy`.

Decoding checks the decoded size declared in the PNG IHDR chunk or the `.npy` header (width × height × channels ×
bytes per sample, `image_size`) *before* decompressing, so a forged or hostile upload cannot make the service allocate
more than `max_bytes` bytes.
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

from ddvs_service.protocol.errors import InvalidMessage
from ddvs_service.protocol.image_size import ImageHeader, check_decoded_size, png_header
from ddvs_service.protocol.ros import IMAGE_MAX_BYTES

UploadFormat = Literal["png", "npy"]
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


def _decode_png(raw: bytes, max_bytes: int) -> NDArray:
    header = png_header(raw)
    width, height = header.width, header.height
    check_decoded_size(header, max_bytes, "uploaded PNG")
    import cv2  # deferred: importing OpenCV takes ~0.5 s

    image = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InvalidMessage(f"uploaded PNG ({width}×{height}) could not be decoded")
    return image


def _decode_npy(raw: bytes, max_bytes: int) -> NDArray:
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
    check_decoded_size(ImageHeader(shape[1], shape[0], shape[2] if len(shape) == 3 else 1, dtype.itemsize),
                       max_bytes, "uploaded .npy")
    expected = int(np.prod(shape)) * dtype.itemsize
    body = raw[f.tell() :]
    if len(body) != expected:
        raise InvalidMessage(f"uploaded .npy body has {len(body)} bytes; its header {shape} {dtype} needs {expected}")
    return np.frombuffer(body, dtype=dtype).reshape(shape, order="F" if fortran_order else "C").copy()


def decode_upload(text: str, fmt: UploadFormat, max_bytes: int = IMAGE_MAX_BYTES) -> NDArray:
    """The image array of base64 `text` in format `fmt`, at most `max_bytes` bytes decoded; raises `InvalidMessage`
    / `MessageTooLarge` (the size is checked before decoding)."""
    try:
        raw = base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError) as exc:
        raise InvalidMessage(f"uploaded image is not valid base64: {exc}") from exc
    return _decode_png(raw, max_bytes) if fmt == "png" else _decode_npy(raw, max_bytes)
