"""Robustness of every CDR decoder: generated, truncated, bit-flipped and forged messages either decode to a valid
message or raise a `ProtocolError` — never another exception, never an allocation sized by a forged field."""

from __future__ import annotations

import struct
import tracemalloc
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_protocol_ros import CODECS

from ddvs_service.protocol import Header, Image, ProtocolError, Time, decode_image, encode_image

FORGED_VALUES = (0xFFFFFFFF, 0x7FFFFFFF, 0x10000000, 0x01000000)
ALLOCATION_SLACK = 256 << 10


@pytest.fixture
def traced() -> Iterator[Callable[[], int]]:
    """Start tracemalloc; the yielded function returns the most bytes allocated at once (above what was live at
    its previous call) since its previous call."""
    tracemalloc.start()
    baseline = 0

    def growth_since_last_call() -> int:
        nonlocal baseline
        current, peak = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        grown, baseline = peak - baseline, current
        return grown

    try:
        yield growth_since_last_call
    finally:
        tracemalloc.stop()


def decode_or_reject(decode, encode, payload: bytes) -> None:
    """The property: a valid message (which re-encodes and re-decodes) or a ProtocolError, nothing else."""
    try:
        msg = decode(payload)
    except ProtocolError:
        return
    decode(encode(msg))


def mutate(payload: bytes, data: st.DataObject) -> bytes:
    buf = bytearray(payload)
    kind = data.draw(st.sampled_from(["truncate", "flip", "word", "insert", "delete", "append"]), label="mutation")
    if kind == "truncate":
        return bytes(buf[: data.draw(st.integers(0, len(buf) - 1), label="cut")])
    if kind == "flip":
        for _ in range(data.draw(st.integers(1, 4), label="flips")):
            bit = data.draw(st.integers(0, 8 * len(buf) - 1), label="bit")
            buf[bit // 8] ^= 1 << (bit % 8)
    elif kind == "word":  # overwrite an aligned 32-bit word: the likely place of a length field
        offset = 4 + 4 * data.draw(st.integers(0, (len(buf) - 8) // 4), label="word")
        value = data.draw(st.sampled_from([*FORGED_VALUES, 0, 1, 2, 3]) | st.integers(0, 2**32 - 1), label="value")
        buf[offset : offset + 4] = struct.pack("<I", value)
    elif kind == "insert":
        at = data.draw(st.integers(0, len(buf)), label="at")
        buf[at:at] = data.draw(st.binary(min_size=1, max_size=8), label="inserted")
    elif kind == "delete":
        at = data.draw(st.integers(0, len(buf) - 1), label="at")
        del buf[at : at + data.draw(st.integers(1, 8), label="deleted")]
    else:
        buf += data.draw(st.binary(min_size=1, max_size=16), label="appended")
    return bytes(buf)


@pytest.mark.slow
@pytest.mark.parametrize("typename", sorted(CODECS))
def test_mutated_messages_decode_or_raise_protocol_error(typename: str) -> None:
    strategy, encode, decode, _ = CODECS[typename]

    @settings(
        max_examples=2000, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large]
    )
    @given(strategy, st.data())
    def check(msg, data: st.DataObject) -> None:
        decode_or_reject(decode, encode, mutate(encode(msg), data))

    check()


@pytest.mark.parametrize("typename", sorted(CODECS))
def test_random_bytes_decode_or_raise_protocol_error(typename: str) -> None:
    _, encode, decode, _ = CODECS[typename]

    @settings(max_examples=1000, deadline=None)
    @given(st.sampled_from([b"", b"\x00\x01\x00\x00", b"\x00\x00\x00\x00"]), st.binary(max_size=200))
    def check(prefix: bytes, body: bytes) -> None:
        decode_or_reject(decode, encode, prefix + body)

    check()


@pytest.mark.parametrize("typename", sorted(CODECS))
def test_every_forged_length_word_is_rejected_without_allocating(typename: str, traced: Callable[[], int]) -> None:
    """Exhaustive over the aligned words of a typical message: a huge value in any field allocates nothing big."""
    strategy, encode, decode, _ = CODECS[typename]

    @settings(max_examples=25, deadline=None)
    @given(strategy)
    def check(msg) -> None:
        payload = encode(msg)
        for offset in range(4, len(payload) - 3, 4):
            for value in FORGED_VALUES:
                forged = bytearray(payload)
                forged[offset : offset + 4] = struct.pack("<I", value)
                traced()
                decode_or_reject(decode, encode, bytes(forged))
                assert traced() < 8 * len(payload) + ALLOCATION_SLACK, f"offset {offset}, value {value:#x}"

    check()


def test_forged_image_sizes_never_allocate_the_claimed_size(traced: Callable[[], int]) -> None:
    pixels = np.zeros((4, 4), np.uint8)
    payload = bytearray(encode_image(Image(Header(Time(0, 0), "c"), 4, 4, "mono8", 0, 4, pixels.reshape(-1))))
    # encapsulation (4), sec, nanosec, frame_id (length 2, "c\0", 2 padding) → height at 20, width at 24; the data
    # count precedes the 16 pixel bytes and the step precedes it
    for offset in (20, 24, len(payload) - 24, len(payload) - 20):
        forged = bytearray(payload)
        forged[offset : offset + 4] = struct.pack("<I", 0xFFFFFFFF)
        traced()
        with pytest.raises(ProtocolError):
            decode_image(bytes(forged))
        assert traced() < ALLOCATION_SLACK
