"""Recordings of servo runs as streams of JSON records (docs/recording.md): `load_recording` reads a bag of
`ddvs record` (`clients/bag.py`) or the older JSON Lines directory, whose writer and reader are here.

JSON Lines format: a directory of append-only JSON Lines streams, plus optional frames as PNG files.

Crash safety: every record is one complete line written with a single `write` and flushed at once, so a killed
recorder leaves every complete record readable; a torn last line (no trailing newline, or not valid JSON) is
skipped by the reader. A frame is written to a temporary name and renamed into place before its index line is
appended, so every indexed frame file is complete. `meta.json` is written once, atomically (temporary + rename).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

from clients.bag import bag_messages, bag_meta, is_bag
from clients.channels import topic_name
from ddvs_service.protocol import Keys

FORMAT_NAME = "ddvs-recording"
FORMAT_VERSION = 1
STREAMS = ("status", "state", "twist", "joint_states", "ground_truth", "camera_info", "frames")
FRAMES_DIR = "frames"
META_FILE = "meta.json"
# stream name -> key name of `ddvs_service.protocol.TOPICS`
RECORDED_KEYS = {
    "status": "servo_status",
    "state": "servo_state",
    "twist": "servo_twist",
    "joint_states": "arm_joint_states",
    "ground_truth": "arm_ground_truth",
    "camera_info": "camera_info",
}


def decode_record(stream: str, payload: bytes, recv_ns: int) -> dict[str, Any]:
    """The JSON record of one payload of `stream` (raises `ValueError`, e.g. `ProtocolError`, on a bad payload)."""
    from ddvs_service.protocol import decode_camera_info, decode_joint_state, decode_twist_stamped

    if stream in ("status", "state", "ground_truth"):
        msg = json.loads(payload)
        if not isinstance(msg, dict):
            raise ValueError(f"{stream} payload is a JSON {type(msg).__name__}; expected an object")
        return {"recv_ns": recv_ns, "msg": msg}
    if stream == "twist":
        twist = decode_twist_stamped(payload)
        return {"recv_ns": recv_ns, "stamp_ns": twist.header.stamp.to_ns(), "frame_id": twist.header.frame_id,
                "twist": twist.vector.tolist()}
    if stream == "joint_states":
        joints = decode_joint_state(payload)
        return {"recv_ns": recv_ns, "stamp_ns": joints.header.stamp.to_ns(), "name": joints.name,
                "position": joints.position.tolist(), "velocity": joints.velocity.tolist()}
    if stream == "camera_info":
        info = decode_camera_info(payload)
        return {"recv_ns": recv_ns, "stamp_ns": info.header.stamp.to_ns(), "width": info.width,
                "height": info.height, "distortion_model": info.distortion_model, "d": info.d.tolist(),
                "k": info.k.tolist()}
    raise ValueError(f"no decoder for stream {stream!r}")


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class RecordingWriter:
    """Writes one recording directory. `write(stream, record)` appends a JSON object (a line) to `<stream>.jsonl`;
    `write_frame(image, record)` stores `frames/<seq>.png` and appends its index line to `frames.jsonl`."""

    def __init__(self, directory: str | Path, meta: dict[str, Any]) -> None:
        self.directory = Path(directory)
        if self.directory.exists() and any(self.directory.iterdir()):
            raise FileExistsError(f"recording directory {self.directory} is not empty; choose a new one")
        (self.directory / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
        header = {"format": FORMAT_NAME, "version": FORMAT_VERSION, **meta}
        _atomic_write(self.directory / META_FILE, json.dumps(header, indent=2).encode("utf-8"))
        self._files: dict[str, IO[str]] = {}
        self.counts = dict.fromkeys(STREAMS, 0)

    def write(self, stream: str, record: dict[str, Any]) -> None:
        if stream not in STREAMS:
            raise ValueError(f"unknown stream {stream!r}; expected one of {STREAMS}")
        f = self._files.get(stream)
        if f is None:
            f = self._files[stream] = open(self.directory / f"{stream}.jsonl", "a", encoding="utf-8")  # noqa: SIM115
        f.write(json.dumps(record, separators=(",", ":"), allow_nan=False) + "\n")
        f.flush()
        self.counts[stream] += 1

    def write_frame(self, image: NDArray, record: dict[str, Any]) -> None:
        """Store a grey or BGR uint8/uint16 frame losslessly as PNG; `record` (stamps) goes to `frames.jsonl` with
        the file name under `file`."""
        import cv2

        name = f"{FRAMES_DIR}/{self.counts['frames']:06d}.png"
        ok, data = cv2.imencode(".png", np.ascontiguousarray(image))
        if not ok:
            raise ValueError(f"cannot encode a frame of shape {image.shape}, dtype {image.dtype} as PNG")
        path = self.directory / name
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_bytes(data.tobytes())
        os.replace(tmp, path)
        self.write("frames", {**record, "file": name})

    def close(self) -> None:
        for f in self._files.values():
            f.close()
        self._files.clear()


def read_stream(path: str | Path) -> list[dict[str, Any]]:
    """Every complete record of a JSON Lines stream (missing file: none); a torn last line is skipped."""
    path = Path(path)
    if not path.exists():
        return []
    records = []
    text = path.read_text(encoding="utf-8")
    lines = text.split("\n")
    for i, line in enumerate(lines):
        if not line:
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            if i == len(lines) - 1:  # the torn record of a killed writer
                break
            raise ValueError(f"{path}: line {i + 1} is not valid JSON (only the last line may be torn)") from None
    return records


@dataclass
class Recording:
    """A loaded recording: `meta` (meta.json) and the records of each stream (lists of dicts, in arrival order)."""

    directory: Path
    meta: dict[str, Any]
    streams: dict[str, list[dict[str, Any]]] = field(default_factory=dict)

    def __getitem__(self, stream: str) -> list[dict[str, Any]]:
        return self.streams[stream]

    def frame(self, index: int) -> NDArray:
        """The image of the `index`-th record of the frames stream (as stored: grey or BGR)."""
        import cv2

        image = cv2.imread(str(self.directory / self.streams["frames"][index]["file"]), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise FileNotFoundError(f"frame {index} of {self.directory} is missing or unreadable")
        return image


def load_bag(directory: str | Path) -> Recording:
    """The records of a bag (complete or a killed recorder's), as `decode_record` makes them from each payload;
    the frames stream stays empty (read images with `clients.bag.bag_messages`)."""
    directory = Path(directory)
    meta = {"format": "rosbag2", **bag_meta(directory)}
    keys = Keys(meta.get("prefix", "ddvs"), meta.get("robot", "robot0"))
    stream_of = {topic_name(keys, key_name): stream for stream, key_name in RECORDED_KEYS.items()}
    streams: dict[str, list[dict[str, Any]]] = {name: [] for name in STREAMS}
    for message in bag_messages(directory):
        stream = stream_of.get(message.topic)
        if stream is not None:
            streams[stream].append(decode_record(stream, message.data, message.log_time_ns))
    return Recording(directory, meta, streams)


def load_recording(directory: str | Path) -> Recording:
    """Read a recording: a bag of `ddvs record` (`load_bag`) or a JSON Lines directory written by
    `RecordingWriter` (or a killed recorder)."""
    directory = Path(directory)
    if is_bag(directory):
        return load_bag(directory)
    meta_path = directory / META_FILE
    if not meta_path.exists():
        raise FileNotFoundError(f"{directory} is not a recording: it has no {META_FILE}")
    meta = json.loads(meta_path.read_text(encoding="utf-8"))
    if meta.get("format") != FORMAT_NAME or meta.get("version") != FORMAT_VERSION:
        raise ValueError(f"{meta_path}: format {meta.get('format')!r} version {meta.get('version')!r}; expected "
                         f"{FORMAT_NAME!r} version {FORMAT_VERSION}")
    streams = {name: read_stream(directory / f"{name}.jsonl") for name in STREAMS}
    return Recording(directory, meta, streams)
