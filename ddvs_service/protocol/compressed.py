"""`sensor_msgs/CompressedImage`: its CDR codec, and the size of a JPEG or PNG read from its header alone.

image_transport's `compressed` plugin publishes it on `<image topic>/compressed` with `format` "jpeg" or "png", or
in its longer form `"<encoding>; jpeg compressed <encoding>"` (e.g. "bgr8; jpeg compressed bgr8"); `data` is the
file as `cv2.imencode` writes it. `compressed_geometry` reads the width, height and channels from the PNG IHDR
chunk or the JPEG start-of-frame segment, so a decoder can refuse an oversized image before allocating its pixels
(a 100 KB PNG can hold 4096×4096 16-bit RGBA). Decoding the pixels themselves is `ddvs_service.grey`'s.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import NamedTuple

from ddvs_service.protocol.cdr import CdrReader, CdrWriter
from ddvs_service.protocol.errors import InconsistentMessage, UnsupportedEncoding
from ddvs_service.protocol.ros import IMAGE_MAX_BYTES, Header, read_header, write_header

FORMATS = ("jpeg", "png")
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # colour type → samples per pixel (3: palette indices)
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


@dataclass(frozen=True)
class CompressedImage:
    """`sensor_msgs/CompressedImage`: `header`, `format` (see the module docstring) and the file bytes `data`."""

    header: Header
    format: str
    data: bytes

    @property
    def codec(self) -> str:
        """"jpeg" or "png", from `format` (image_transport's long form included); `UnsupportedEncoding` else."""
        text = self.format.lower()
        for codec in FORMATS:
            if text == codec or f"{codec} compressed" in text or (codec == "jpeg" and text in ("jpg", "jpeg")):
                return codec
        raise UnsupportedEncoding(f"CompressedImage.format {self.format!r} is not supported; expected jpeg or png "
                                  "(as image_transport's compressed plugin writes them)")


class Geometry(NamedTuple):
    """Size of a compressed image, read from its header: pixels, channels and bits per channel."""

    width: int
    height: int
    channels: int
    bits: int

    @property
    def decoded_bytes(self) -> int:
        """Bytes of the decoded pixels (what `cv2.imdecode` allocates at least)."""
        return self.width * self.height * self.channels * max(self.bits // 8, 1)


def encode_compressed_image(msg: CompressedImage) -> bytes:
    """CDR payload of a `sensor_msgs/CompressedImage` (header, format, data)."""
    w = CdrWriter()
    write_header(w, msg.header)
    w.string(msg.format)
    w.uint8_sequence(msg.data)
    return w.finish()


def decode_compressed_image(buf: bytes | bytearray | memoryview, max_bytes: int = IMAGE_MAX_BYTES) -> CompressedImage:
    """Decode a `sensor_msgs/CompressedImage` payload (the file bytes are copied out of `buf`)."""
    r = CdrReader(buf, max_bytes)
    header = read_header(r)
    fmt = r.string("format")
    return CompressedImage(header, fmt, bytes(r.uint8_sequence("data")))


def compressed_geometry(data: bytes, codec: str) -> Geometry:
    """Width, height, channels and bit depth of a JPEG or PNG file from its header; `InconsistentMessage` when the
    header is not there or does not parse."""
    if codec == "png":
        return _png_geometry(data)
    if codec == "jpeg":
        return _jpeg_geometry(data)
    raise UnsupportedEncoding(f"compressed codec {codec!r}: expected one of {', '.join(FORMATS)}")


def _png_geometry(data: bytes) -> Geometry:
    if len(data) < 26 or not data.startswith(_PNG_SIGNATURE) or data[12:16] != b"IHDR":
        raise InconsistentMessage("CompressedImage: not a PNG file (no signature and IHDR chunk in its first bytes)")
    width, height, bits, colour = struct.unpack(">IIBB", data[16:26])
    if colour not in _PNG_CHANNELS:
        raise InconsistentMessage(f"CompressedImage: PNG colour type {colour}; expected one of {sorted(_PNG_CHANNELS)}")
    return Geometry(width, height, 3 if colour == 3 else _PNG_CHANNELS[colour], bits)


def _jpeg_geometry(data: bytes) -> Geometry:
    if not data.startswith(b"\xff\xd8"):
        raise InconsistentMessage("CompressedImage: not a JPEG file (no start-of-image marker)")
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            raise InconsistentMessage(f"CompressedImage: JPEG marker expected at byte {pos}")
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        (length,) = struct.unpack(">H", data[pos + 2 : pos + 4])
        if marker in _JPEG_SOF:
            if pos + 10 > len(data):
                break
            bits, height, width, channels = struct.unpack(">BHHB", data[pos + 4 : pos + 10])
            return Geometry(width, height, channels, bits)
        pos += 2 + length
    raise InconsistentMessage("CompressedImage: JPEG file without a start-of-frame segment")
