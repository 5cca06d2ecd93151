"""`sensor_msgs/CompressedImage` and its CDR codec.

image_transport's `compressed` plugin publishes it on `<image topic>/compressed` with `format` "jpeg" or "png", or
in its longer form `"<encoding>; jpeg compressed <encoding>"` (e.g. "bgr8; jpeg compressed bgr8"); `data` is the
file as `cv2.imencode` writes it. Decoding the pixels, bounded by the size the file's header declares
(`image_size`), is `ddvs_service.grey`'s.
"""

from __future__ import annotations

from dataclasses import dataclass

from ddvs_service.protocol.cdr import CdrReader, CdrWriter
from ddvs_service.protocol.errors import UnsupportedEncoding
from ddvs_service.protocol.ros import IMAGE_MAX_BYTES, Header, read_header, write_header

FORMATS = ("jpeg", "png")


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
