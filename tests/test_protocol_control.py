"""JSON control plane: valid and invalid commands, replies, status, committed schemas, reference uploads."""

from __future__ import annotations

import base64
import contextlib
import json
import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ddvs_service.protocol import (
    PROTOCOL_VERSION,
    Command,
    InvalidMessage,
    MessageTooLarge,
    Reply,
    Status,
    decode_upload,
    dump,
    encode_upload,
    parse_command,
    parse_message,
)
from ddvs_service.protocol.schemas import SCHEMA_DIR, SCHEMA_MODELS, schema_documents, schema_text


def command(**fields) -> bytes:
    return json.dumps({"protocol_version": PROTOCOL_VERSION, **fields}).encode()


@pytest.mark.parametrize(
    "fields",
    [
        {"op": "start"},
        {"op": "stop", "id": "c-17"},
        {"op": "reset"},
        {"op": "get_state"},
        {"op": "get_config"},
        {"op": "set_config", "config": {"gain": 0.5, "max_speed": {"linear": 0.1}}},
        {"op": "set_reference", "source": "next_frame"},
        {"op": "set_reference", "source": "next_frame", "roi": {"x": 10, "y": 20, "width": 320, "height": 240}},
        {"op": "set_reference", "source": "upload", "image": {"format": "npy", "data": ""}},
    ],
)
def test_valid_commands_round_trip(fields: dict) -> None:
    cmd = parse_command(command(**fields))
    assert cmd.op == fields["op"]
    assert parse_command(dump(cmd)) == cmd


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b"{not json", "not valid JSON"),
        (b"\xff\xfe", "not valid JSON"),
        (b"[1, 2]", "JSON list; expected an object"),
        (b'{"op": "start"}', "protocol_version is missing; expected 1"),
        (json.dumps({"protocol_version": 2, "op": "start"}).encode(), "protocol_version is 2; expected 1"),
        (json.dumps({"protocol_version": True, "op": "start"}).encode(), "protocol_version is True"),
        (command(op="launch"), "op is 'launch'; expected one of set_reference, start"),
        (command(), "op is missing"),
        (command(op="start", speed=3), "speed: Extra inputs are not permitted"),
        (command(op="set_reference"), "needs 'source'"),
        (command(op="set_reference", source="upload"), "'image' exactly when source is 'upload'"),
        (command(op="set_reference", source="camera"), "source: Input should be 'next_frame' or 'upload'"),
        (command(op="start", roi={"x": 0, "y": 0, "width": 1, "height": 1}), "belong to set_reference"),
        (command(op="set_config"), "'config' is required by set_config"),
        (command(op="set_config", config=[1]), "config: Input should be a valid dictionary"),
        (command(op="set_reference", source="next_frame", roi={"x": -1, "y": 0, "width": 5, "height": 5}), "roi.x"),
        (b'{"protocol_version": 1, "op": "set_config", "config": {"gain": NaN}}', "NaN is not valid JSON"),
        (b"[" * 100_000, "not valid JSON"),
    ],
)
def test_invalid_commands_say_why(payload: bytes, reason: str) -> None:
    with pytest.raises(InvalidMessage) as info:
        parse_command(payload)
    assert reason in str(info.value)


def test_oversize_commands_are_rejected_before_parsing() -> None:
    payload = command(op="set_config", config={"blob": "x" * 2000})
    with pytest.raises(InvalidMessage, match=f"message is {len(payload)} bytes; the maximum is 1000"):
        parse_command(payload, max_bytes=1000)


@settings(max_examples=1000, deadline=None)
@given(st.binary(max_size=300) | st.text(max_size=300).map(str.encode))
def test_arbitrary_bytes_parse_or_raise_invalid_message(payload: bytes) -> None:
    with contextlib.suppress(InvalidMessage):
        parse_command(payload)


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=10),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)


@settings(max_examples=1000, deadline=None)
@given(
    st.dictionaries(
        st.sampled_from(["op", "source", "image", "roi", "config", "id", "extra"]), json_values, max_size=5
    ),
    st.sampled_from(["start", "set_reference", "set_config", "bogus"]),
)
def test_structured_garbage_parses_or_raises_invalid_message(fields: dict, op: str) -> None:
    with contextlib.suppress(InvalidMessage):
        parse_command(command(**{"op": op, **fields}))


def test_reply_and_status_round_trip_and_validate() -> None:
    assert parse_message(Reply, dump(Reply.success({"state": "READY"}))).data == {"state": "READY"}
    failure = parse_message(Reply, dump(Reply.failure("no reference set")))
    assert not failure.ok and failure.error == "no reference set"
    with pytest.raises(ValueError, match="'error' exactly when ok is false"):
        Reply(ok=False)
    status = Status(
        robot="robot0",
        state="SERVOING",
        frame_stamp_ns=1_700_000_000_000_000_000,
        seq=3,
        error=[0.1, 0, 0, 0, 0, 0.2],
        error_norm=0.2236,
        iterations=4,
        residual_rms=3.5,
        inlier_ratio=0.97,
        twist=[0.01, 0, 0, 0, 0, 0.02],
        latency_ms={"decode": 0.1, "registration": 2.0, "control": 0.05, "publish": 0.02, "total": 2.3},
        counters={"frames": 4, "dropped": 1, "rejected": 0},
    )
    assert parse_message(Status, dump(status)) == status
    broken = json.loads(dump(status))
    broken["error"] = [0.0] * 5
    with pytest.raises(InvalidMessage, match="error: List should have at least 6 items"):
        parse_message(Status, json.dumps(broken).encode())
    broken = {**json.loads(dump(status)), "state": "FLYING"}
    with pytest.raises(InvalidMessage, match="state: Input should be 'IDLE'"):
        parse_message(Status, json.dumps(broken).encode())


@pytest.mark.parametrize("name", sorted(SCHEMA_MODELS))
def test_committed_schema_files_match_the_models(name: str) -> None:
    path = SCHEMA_DIR / f"{name}.json"
    assert path.read_text(encoding="utf-8") == schema_text(schema_documents()[name]), (
        f"{path} is stale: run `python -m ddvs_service.protocol.schemas`"
    )


def test_schemas_state_the_protocol_version_and_forbid_extra_fields() -> None:
    for name, schema in schema_documents().items():
        assert schema["properties"]["protocol_version"]["const"] == PROTOCOL_VERSION, name
        assert schema["additionalProperties"] is False, name


@pytest.mark.parametrize("fmt", ["png", "npy"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_uploads_round_trip_losslessly(fmt: str, dtype: type) -> None:
    image = (np.arange(40 * 30).reshape(30, 40) * 7 % 60000).astype(dtype)
    cmd = Command(op="set_reference", source="upload", image={"format": fmt, "data": encode_upload(image, fmt)})
    back = parse_command(dump(cmd)).image.to_array()
    assert back.dtype == dtype
    np.testing.assert_array_equal(back, image)


def test_upload_sizes_are_checked_before_decoding() -> None:
    png = base64.b64decode(encode_upload(np.zeros((8, 8), np.uint8), "png"))
    forged = png[:16] + struct.pack(">II", 100_000, 100_000) + png[24:]  # IHDR claims 10^10 pixels
    with pytest.raises(MessageTooLarge, match="100000×100000 pixels × 1 channels × 1 bytes"):
        decode_upload(base64.b64encode(forged).decode(), "png")
    npy = base64.b64decode(encode_upload(np.zeros((8, 8), np.uint8), "npy"))
    forged_npy = npy.replace(b"(8, 8)", b"(9, 9)")  # header claims 81 bytes, body holds 64
    with pytest.raises(InvalidMessage, match="body has 64 bytes"):
        decode_upload(base64.b64encode(forged_npy).decode(), "npy")
    with pytest.raises(MessageTooLarge):
        decode_upload(encode_upload(np.zeros((64, 64), np.uint8), "npy"), "npy", max_bytes=100)
    with pytest.raises(InvalidMessage, match="not valid base64"):
        decode_upload("@@@", "png")
    with pytest.raises(InvalidMessage, match="dtype"):
        decode_upload(encode_upload(np.zeros((4, 4), np.int64), "npy"), "npy")


def _png_of_zeros(width: int, height: int, depth: int, colour: int, channels: int) -> bytes:
    """A valid PNG of zeros built chunk by chunk, compressed row by row: the payload stays small however many pixels
    it declares (a decode bomb)."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    row = bytes(1 + width * channels * depth // 8)  # filter byte 0, then the zero samples
    packer = zlib.compressobj(9)
    idat = b"".join(packer.compress(row) for _ in range(height)) + packer.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def test_a_png_decode_bomb_is_refused_from_its_header() -> None:
    """A 4096×4096 16-bit RGBA PNG is a ~130 KB payload and 128 MiB of pixels: the decoded size (width × height ×
    channels × bytes per sample), not the pixel count, is bounded, before OpenCV allocates anything."""
    bomb = _png_of_zeros(4096, 4096, depth=16, colour=6, channels=4)
    assert len(bomb) < 1 << 20
    text = base64.b64encode(bomb).decode()
    with pytest.raises(MessageTooLarge, match="4096×4096 pixels × 4 channels × 2 bytes = 134217728 bytes decoded"):
        decode_upload(text, "png", max_bytes=64 << 20)
    small = _png_of_zeros(64, 32, depth=16, colour=6, channels=4)  # the same kind of image, within the bound
    assert decode_upload(base64.b64encode(small).decode(), "png", max_bytes=64 * 32 * 8).shape == (32, 64, 4)
    with pytest.raises(MessageTooLarge):
        decode_upload(base64.b64encode(small).decode(), "png", max_bytes=64 * 32 * 8 - 1)
