"""Minimal little-endian CDR (XCDR1, as ROS 2 uses it) writer and bounds-checked reader.

Layout rules (OMG CDR / XCDR1 as emitted by rosidl typesupport and `rosbags`):
- A payload starts with the 4-byte encapsulation header `00 01 00 00` (representation CDR_LE, options 0).
- Offsets for alignment count from the first byte *after* that header. A primitive of size n ∈ {1, 2, 4, 8} is
  preceded by padding up to the next multiple of n (the writer writes zeros).
- `string`: uint32 length including the terminating NUL, the UTF-8 bytes, the NUL.
- `sequence<T>`: uint32 element count, then the elements (each aligned as T). Fixed arrays `T[n]` have no count.

The reader accepts what ROS 2's own reader (Fast-CDR through rmw_fastrtps / rmw_zenoh typesupport) accepts, so that
every payload a ROS 2 node sends decodes (docs/protocol.md, "What the decoders accept"): padding bytes of any value
(rclpy leaves them uninitialised), any number of bytes after the last field (rclpy's `serialize_message` returns a
buffer sized by an estimate that is up to 8 bytes per empty sequence longer than the fields), options bytes 2–3 of
the header ignored, a bool byte other than 0 as true, a string of length 0 as "", a string whose last byte is not
NUL as all its bytes, invalid UTF-8 with U+FFFD replacements (as rclpy converts it).

The reader never allocates from a length field before checking it against both the configured maximum
(`MessageTooLarge`) and the bytes actually left (`TruncatedMessage`).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import NoReturn

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.protocol.errors import InconsistentMessage, MessageTooLarge, TruncatedMessage, UnsupportedEncoding

ENCAPSULATION_CDR_LE = b"\x00\x01\x00\x00"
HEADER_SIZE = 4
_PAD = bytes(8)
_U32 = struct.Struct("<I")
_I32 = struct.Struct("<i")
_F64 = struct.Struct("<d")


class CdrWriter:
    """Appends CDR fields; `finish()` joins them into one `bytes` (large blobs are copied exactly once)."""

    def __init__(self) -> None:
        self._chunks: list[bytes | memoryview] = [ENCAPSULATION_CDR_LE]
        self._pos = 0  # offset after the encapsulation header, for alignment

    def _align(self, n: int) -> None:
        pad = -self._pos % n
        if pad:
            self._chunks.append(_PAD[:pad])
            self._pos += pad

    def _raw(self, data: bytes | memoryview) -> None:
        self._chunks.append(data)
        self._pos += len(data)

    def uint8(self, value: int) -> None:
        self._raw(bytes((value,)))

    def boolean(self, value: bool) -> None:
        self._raw(b"\x01" if value else b"\x00")

    def uint32(self, value: int) -> None:
        self._align(4)
        self._raw(_U32.pack(value))

    def int32(self, value: int) -> None:
        self._align(4)
        self._raw(_I32.pack(value))

    def float64(self, value: float) -> None:
        self._align(8)
        self._raw(_F64.pack(value))

    def string(self, value: str) -> None:
        data = value.encode("utf-8")
        self.uint32(len(data) + 1)
        self._raw(data + b"\x00")

    def float64_array(self, values: ArrayLike, length: int | None = None) -> None:
        """Fixed array `float64[length]` (no count) or, with `length=None`, `sequence<float64>`."""
        a = np.ascontiguousarray(values, dtype="<f8").reshape(-1)
        if length is None:
            self.uint32(a.size)
        elif a.size != length:
            raise InconsistentMessage(f"float64[{length}] array given {a.size} values; expected exactly {length}")
        if a.size:
            self._align(8)
            self._raw(a.tobytes())

    def string_sequence(self, values: Sequence[str]) -> None:
        self.uint32(len(values))
        for s in values:
            self.string(s)

    def uint8_sequence(self, data: bytes | memoryview | NDArray[np.uint8]) -> None:
        """`sequence<uint8>`: count then the bytes, appended without an intermediate copy."""
        view = data if isinstance(data, bytes) else (data.data if isinstance(data, np.ndarray) else data).cast("B")
        self.uint32(len(view))
        self._raw(view)

    def finish(self) -> bytes:
        return b"".join(self._chunks)


class CdrReader:
    """Reads CDR fields from `buf` (bytes, bytearray or memoryview) without copying it.

    `max_bytes` bounds the whole payload and every length field; exceeding it raises `MessageTooLarge`.
    """

    def __init__(self, buf: bytes | bytearray | memoryview, max_bytes: int) -> None:
        try:
            view = memoryview(buf).cast("B")
        except TypeError as exc:
            raise InconsistentMessage(f"payload must be a bytes-like object, got {type(buf).__name__}") from exc
        if len(view) > max_bytes:
            raise MessageTooLarge(f"payload is {len(view)} bytes; the maximum is {max_bytes}")
        if len(view) < HEADER_SIZE:
            raise TruncatedMessage(f"payload is {len(view)} bytes; a CDR payload needs a 4-byte encapsulation header")
        header = bytes(view[:HEADER_SIZE])
        if header[:2] != ENCAPSULATION_CDR_LE[:2]:
            raise UnsupportedEncoding(
                f"CDR representation {header[:2].hex()}: only CDR_LE (encapsulation header 00 01 00 00) is supported"
            )
        self._view = view[HEADER_SIZE:]
        self._pos = 0
        self.max_bytes = max_bytes

    @property
    def remaining(self) -> int:
        return len(self._view) - self._pos

    def _align(self, n: int) -> None:
        self._pos += -self._pos % n

    def _take(self, n: int, what: str) -> memoryview:
        pos = self._pos
        if pos + n > len(self._view):
            self._truncated(n, pos, what)
        self._pos = pos + n
        return self._view[pos : pos + n]

    def _truncated(self, n: int, pos: int, what: str) -> NoReturn:
        raise TruncatedMessage(f"{what}: needs {n} bytes at offset {pos}, only {max(self.remaining, 0)} left")

    def _primitive(self, fmt: struct.Struct, what: str) -> int | float:
        """One primitive of `fmt.size` bytes after its alignment padding (`_align` and `_take` in one step: a frame
        header is a dozen of them)."""
        n = fmt.size
        pos = self._pos + (-self._pos % n)
        if pos + n > len(self._view):
            self._pos = pos
            self._truncated(n, pos, what)
        self._pos = pos + n
        value: int | float = fmt.unpack_from(self._view, pos)[0]
        return value

    def check_length(self, count: int, item_size: int, what: str) -> None:
        """Reject a count of items of (at least) `item_size` bytes before anything is allocated from it."""
        nbytes = count * item_size
        if nbytes > self.max_bytes:
            raise MessageTooLarge(f"{what}: length {count} ({nbytes} bytes) exceeds the maximum of {self.max_bytes}")
        if nbytes > self.remaining:
            raise TruncatedMessage(f"{what}: length {count} needs {nbytes} bytes, only {max(self.remaining, 0)} left")

    def uint8(self, what: str) -> int:
        return self._take(1, what)[0]

    def boolean(self, what: str) -> bool:
        """Any non-zero byte is true (rosidl's Fast-CDR typesupport reads a bool as a uint8 and tests it != 0)."""
        return self.uint8(what) != 0

    def uint32(self, what: str) -> int:
        return int(self._primitive(_U32, what))

    def int32(self, what: str) -> int:
        return int(self._primitive(_I32, what))

    def float64(self, what: str) -> float:
        return float(self._primitive(_F64, what))

    def string(self, what: str) -> str:
        """Length 0 reads as "", a missing NUL terminator keeps every byte, invalid UTF-8 becomes U+FFFD — what
        Fast-CDR and rclpy make of such strings."""
        n = self.uint32(f"{what} length")
        if n == 0:
            return ""
        self.check_length(n, 1, what)
        raw = self._take(n, what)
        return str(raw[: n - 1] if raw[n - 1] == 0 else raw, "utf-8", "replace")

    def float64_array(self, what: str, length: int | None = None) -> NDArray[np.float64]:
        """Fixed `float64[length]` or, with `length=None`, `sequence<float64>`; returns a writable copy."""
        n = self.uint32(f"{what} count") if length is None else length
        if n == 0:
            return np.zeros(0)
        self._align(8)
        self.check_length(n, 8, what)
        return np.frombuffer(self._take(8 * n, what), dtype="<f8").astype(np.float64)

    def string_sequence(self, what: str) -> list[str]:
        n = self.uint32(f"{what} count")
        self.check_length(n, 4, what)  # each element takes at least its length field
        return [self.string(f"{what}[{i}]") for i in range(n)]

    def uint8_sequence(self, what: str) -> memoryview:
        """`sequence<uint8>` as a memoryview into the payload (no copy)."""
        n = self.uint32(f"{what} count")
        self.check_length(n, 1, what)
        return self._take(n, what)
