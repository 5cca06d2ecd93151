"""The decoded size of an image, read from its header before anything is decompressed or allocated.

A compressed image is a decode bomb when its payload is small and its pixels are many: a 4096×4096 16-bit RGBA PNG
of zeros is a 130 KB payload and a 128 MiB array. Every decoder of a compressed image reads the header first
(`png_header`, `jpeg_header`), then calls `check_decoded_size` with its bound, and only then decodes.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from ddvs_service.protocol.errors import InvalidMessage, MessageTooLarge

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# PNG colour type → channels of the array OpenCV decodes it to with IMREAD_UNCHANGED (palette and grey+alpha may
# come out with 4 channels: BGRA)
_PNG_CHANNELS = {0: 1, 2: 3, 3: 4, 4: 4, 6: 4}


@dataclass(frozen=True)
class ImageHeader:
    """What a header declares: `width` × `height` pixels of `channels` samples of `bytes_per_sample` bytes."""

    width: int
    height: int
    channels: int
    bytes_per_sample: int

    @property
    def decoded_bytes(self) -> int:
        """Bytes of the decoded array."""
        return self.width * self.height * self.channels * self.bytes_per_sample


def png_header(raw: bytes) -> ImageHeader:
    """The IHDR chunk of a PNG file (width, height, bit depth, colour type); raises `InvalidMessage`."""
    if len(raw) < 26 or raw[:8] != PNG_SIGNATURE or raw[12:16] != b"IHDR":
        raise InvalidMessage("PNG data does not start with a PNG signature and IHDR chunk")
    width, height, depth, colour = struct.unpack(">IIBB", raw[16:26])
    if colour not in _PNG_CHANNELS or depth not in (1, 2, 4, 8, 16):
        raise InvalidMessage(f"PNG header declares bit depth {depth} and colour type {colour}; expected a depth of "
                             f"1, 2, 4, 8 or 16 bits and a colour type in {sorted(_PNG_CHANNELS)}")
    return ImageHeader(width, height, _PNG_CHANNELS[colour], 2 if depth == 16 else 1)


_JPEG_START_OF_FRAME = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def jpeg_header(raw: bytes) -> ImageHeader:
    """The start-of-frame segment of a JPEG file (precision, height, width, components), found by walking the
    marker segments from the start-of-image marker; raises `InvalidMessage`."""
    if raw[:2] != b"\xff\xd8":
        raise InvalidMessage("JPEG data does not start with a start-of-image marker")
    pos = 2
    while pos + 4 <= len(raw):
        if raw[pos] != 0xFF:
            raise InvalidMessage(f"JPEG data: a marker expected at byte {pos}")
        marker = raw[pos + 1]
        if marker == 0xFF:  # fill byte before a marker
            pos += 1
            continue
        (length,) = struct.unpack(">H", raw[pos + 2 : pos + 4])
        if marker in _JPEG_START_OF_FRAME and pos + 10 <= len(raw):
            precision, height, width, components = struct.unpack(">BHHB", raw[pos + 4 : pos + 10])
            return ImageHeader(width, height, components, 2 if precision > 8 else 1)
        pos += 2 + length
    raise InvalidMessage("JPEG data without a start-of-frame segment")


def check_decoded_size(header: ImageHeader, max_bytes: int, what: str) -> None:
    """Refuse an image whose decoded array would exceed `max_bytes` (`MessageTooLarge`) or that is empty
    (`InvalidMessage`); `what` names the image in the message."""
    size = f"{header.width}×{header.height} pixels × {header.channels} channels × {header.bytes_per_sample} bytes"
    if header.decoded_bytes > max_bytes:
        raise MessageTooLarge(f"{what} is {size} = {header.decoded_bytes} bytes decoded; "
                              f"the maximum is {max_bytes} bytes")
    if header.width == 0 or header.height == 0:
        raise InvalidMessage(f"{what} is {size}; expected a non-empty image")
