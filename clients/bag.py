"""rosbag2 bag directories of servo runs (metadata.yaml + MCAP storage): writer, crash-tolerant reader, recovery.

Layout of a bag `run/` (docs/recording.md):

    run/metadata.yaml    rosbag2 metadata (version 9, storage `mcap`); written at close and by `recover_bag`
    run/run_0.mcap       the ROS 2 channels: CDR messages, `ros2msg` schemas, profile `ros2` (rosbag2's storage file)
    run/run_json.mcap    the JSON channels: `json` messages, `jsonschema` schemas (status, state, ground truth, config)

The JSON channels have a file of their own because rosbag2 plays a bag only when all its topics share one
serialization format, and `rosbags` (0.11) refuses to open an MCAP file that holds a `jsonschema` schema; Foxglove
opens both files together. Each message is logged at its arrival time at the recorder (`log_time`, ns since the Unix
epoch) and published at its header stamp (`publish_time`; the arrival time for JSON messages).

Crash safety: the open chunk of each file is closed (compressed, written and handed to the operating system) at
least every `flush_period_s`, and whenever it exceeds `chunk_size`; a recorder killed at any moment loses at most
its open chunks. `iter_messages` reads a file up to its last complete record (a killed recorder's file has no
summary or footer); `recover_bag` rewrites such files complete and writes metadata.yaml (`ddvs record --recover`).
Nothing is fsynced: a power loss may lose what the operating system had not yet written.
"""

from __future__ import annotations

import json
import os
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from clients.channels import ChannelSpec
from ddvs_service.protocol.rmw import TYPE_HASHES

METADATA_FILE = "metadata.yaml"
META_RECORD = "ddvs"
MCAP_MAGIC = b"\x89MCAP0\r\n"
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


def storage_files(directory: Path) -> tuple[Path, Path]:
    """The bag's ROS 2 storage file and its JSON file."""
    return directory / f"{directory.name}_0.mcap", directory / f"{directory.name}_json.mcap"


class _McapFile:
    """One MCAP file being written: its channels registered up front, messages counted per topic."""

    def __init__(self, path: Path, profile: str, channels: list[ChannelSpec], compression: str, chunk_size: int,
                 meta: dict[str, Any]) -> None:
        self.path = path
        self._file: IO[bytes] = open(path, "xb")  # noqa: SIM115 (closed in close())
        self.writer = Writer(self._file, chunk_size=chunk_size, compression=COMPRESSIONS[compression])
        self.writer.start(profile=profile, library="ddvs")
        if meta:
            self.writer.add_metadata(META_RECORD, {k: json.dumps(v) for k, v in meta.items()})
        self.ids: dict[str, int] = {}
        self.specs: dict[str, ChannelSpec] = {}
        for spec in channels:
            schema_id = self.writer.register_schema(spec.schema_name, spec.schema_encoding, spec.schema.encode())
            self.ids[spec.topic] = self.writer.register_channel(spec.topic, spec.message_encoding, schema_id)
            self.specs[spec.topic] = spec
        self.counts = dict.fromkeys(self.ids, 0)
        self.start_ns: int | None = None
        self.end_ns: int | None = None

    def write(self, topic: str, payload: bytes, log_time_ns: int, publish_time_ns: int) -> None:
        self.writer.add_message(self.ids[topic], log_time_ns, payload, publish_time_ns, sequence=self.counts[topic])
        self.counts[topic] += 1
        self.start_ns = log_time_ns if self.start_ns is None else min(self.start_ns, log_time_ns)
        self.end_ns = log_time_ns if self.end_ns is None else max(self.end_ns, log_time_ns)

    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self.writer.finish()
        self._file.close()


class BagWriter:
    """Writes one bag directory (`directory` must not exist or be empty). `write(topic, payload, log_time_ns,
    publish_time_ns)` appends a message to the file of its channel; `flush_if_due()` closes the open chunks once
    `flush_period_s` has passed since the last flush (call it often); `close()` finishes both files and writes
    metadata.yaml. `meta` (JSON values) goes to a `ddvs` metadata record and to metadata.yaml's `custom_data`."""

    def __init__(self, directory: str | Path, channels: list[ChannelSpec], meta: dict[str, Any] | None = None,
                 compression: str = "zstd", flush_period_s: float = 0.5, chunk_size: int = 1 << 20) -> None:
        if compression not in COMPRESSIONS:
            raise ValueError(f"compression {compression!r}: expected one of {', '.join(COMPRESSIONS)}")
        if not 0 < flush_period_s <= 1.0:
            raise ValueError(f"flush_period_s = {flush_period_s}: expected a period in (0, 1] seconds")
        self.directory = Path(directory)
        if self.directory.exists() and any(self.directory.iterdir()):
            raise FileExistsError(f"bag directory {self.directory} is not empty; choose a new one")
        self.directory.mkdir(parents=True, exist_ok=True)
        self.meta = dict(meta or {})
        ros_path, json_path = storage_files(self.directory)
        self.ros = _McapFile(ros_path, "ros2", [c for c in channels if c.is_ros], compression, chunk_size, self.meta)
        self.json = _McapFile(json_path, "", [c for c in channels if not c.is_ros], compression, chunk_size, {})
        self._by_topic = {topic: f for f in (self.ros, self.json) for topic in f.ids}
        self.flush_period_s = flush_period_s
        self._last_flush = time.monotonic()

    @property
    def counts(self) -> dict[str, int]:
        """Messages written per topic."""
        return {**self.ros.counts, **self.json.counts}

    def write(self, topic: str, payload: bytes, log_time_ns: int, publish_time_ns: int) -> None:
        try:
            target = self._by_topic[topic]
        except KeyError:
            known = ", ".join(self._by_topic)
            raise KeyError(f"topic {topic!r} is not a channel of this bag; channels: {known}") from None
        target.write(topic, payload, log_time_ns, publish_time_ns)

    def flush_if_due(self) -> bool:
        """Close the open chunks when `flush_period_s` has passed since the last flush; True when it flushed."""
        now = time.monotonic()
        if now - self._last_flush < self.flush_period_s:
            return False
        self.flush()
        return True

    def flush(self) -> None:
        self.ros.flush()
        self.json.flush()
        self._last_flush = time.monotonic()

    def close(self) -> None:
        self.ros.close()
        self.json.close()
        write_metadata(self.directory, self.ros.path.name,
                       [(self.ros.specs[t], n) for t, n in self.ros.counts.items()],
                       self.ros.start_ns, self.ros.end_ns, self.meta)


# --- metadata.yaml ---------------------------------------------------------------------------------------------------


def metadata_yaml(file_name: str, topics: list[tuple[ChannelSpec, int]], start_ns: int | None, end_ns: int | None,
                  meta: dict[str, Any]) -> str:
    """rosbag2's metadata.yaml (version 9) of a one-file MCAP bag: per topic its type, `cdr` and message count."""
    count = sum(n for _, n in topics)
    start = start_ns if start_ns is not None and count else 0
    duration = (end_ns - start_ns) if start_ns is not None and end_ns is not None and count else 0
    lines = ["rosbag2_bagfile_information:", "  version: 9", "  storage_identifier: mcap",
             "  duration:", f"    nanoseconds: {duration}",
             "  starting_time:", f"    nanoseconds_since_epoch: {start}",
             f"  message_count: {count}", "  topics_with_message_count:"]
    for spec, n in topics:
        lines += ["    - topic_metadata:", f"        name: {spec.topic}", f"        type: {spec.schema_name}",
                  f"        serialization_format: {spec.message_encoding}", "        offered_qos_profiles: []",
                  f"        type_description_hash: \"{TYPE_HASHES.get(spec.schema_name, '')}\"",
                  f"      message_count: {n}"]
    lines += ["  compression_format: \"\"", "  compression_mode: \"\"",
              "  relative_file_paths:", f"    - {file_name}",
              "  files:", f"    - path: {file_name}",
              "      starting_time:", f"        nanoseconds_since_epoch: {start}",
              "      duration:", f"        nanoseconds: {duration}",
              f"      message_count: {count}"]
    if meta:
        lines.append("  custom_data:")
        lines += [f"    {key}: {json.dumps(json.dumps(value))}" for key, value in meta.items()]
    else:
        lines.append("  custom_data: {}")
    lines.append("  ros_distro: \"\"")
    return "\n".join(lines) + "\n"


def write_metadata(directory: Path, file_name: str, topics: list[tuple[ChannelSpec, int]], start_ns: int | None,
                   end_ns: int | None, meta: dict[str, Any]) -> None:
    """Write metadata.yaml atomically (temporary file + rename)."""
    path = directory / METADATA_FILE
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(metadata_yaml(file_name, topics, start_ns, end_ns, meta), encoding="utf-8")
    os.replace(tmp, path)


# --- reading ---------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BagMessage:
    """One message of a bag file with its channel's topic, encoding and schema name."""

    topic: str
    message_encoding: str
    schema_name: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes


@dataclass
class FileContents:
    """What `read_records` found in one MCAP file: schemas, channels, metadata records, and whether it is complete
    (ends with a footer) or was cut short (a killed recorder: everything up to the last complete record)."""

    schemas: dict[int, Schema]
    channels: dict[int, Channel]
    metadata: dict[str, dict[str, str]]
    complete: bool = False


def read_records(path: Path, contents: FileContents) -> Iterator[Message]:
    """The messages of an MCAP file in file order, up to its last complete record; fills `contents` as it goes.

    A chunk is used whole or not at all (its CRC is checked); a file cut inside a record ends the iteration there.
    """
    with open(path, "rb") as f:
        reader = StreamReader(f, emit_chunks=True, validate_crcs=True)
        try:
            for record in reader.records:
                inner = breakup_chunk(record, validate_crc=True) if isinstance(record, Chunk) else [record]
                for item in inner:
                    if isinstance(item, Schema):
                        contents.schemas[item.id] = item
                    elif isinstance(item, Channel):
                        contents.channels[item.id] = item
                    elif isinstance(item, Metadata):
                        contents.metadata[item.name] = dict(item.metadata)
                    elif isinstance(item, Message):
                        yield item
            contents.complete = True
        except (EndOfFile, McapError, ValueError, struct.error):
            return  # cut short: a killed writer's last, incomplete record


def iter_messages(path: Path) -> Iterator[BagMessage]:
    """`BagMessage`s of one MCAP file (complete or cut short), in file order."""
    contents = FileContents({}, {}, {})
    for message in read_records(path, contents):
        channel = contents.channels[message.channel_id]
        schema = contents.schemas.get(channel.schema_id)
        yield BagMessage(channel.topic, channel.message_encoding, schema.name if schema else "", message.log_time,
                         message.publish_time, message.data)


def is_bag(directory: str | Path) -> bool:
    """True when `directory` holds a ddvs bag (its ROS 2 storage file exists)."""
    directory = Path(directory)
    return storage_files(directory)[0].exists()


def bag_messages(directory: str | Path) -> Iterator[BagMessage]:
    """Every message of a bag: the ROS 2 file's, then the JSON file's (each in file order)."""
    directory = Path(directory)
    for path in storage_files(directory):
        if path.exists():
            yield from iter_messages(path)


def bag_counts(directory: str | Path) -> dict[str, int]:
    """Messages per topic of a bag (both files; a killed recorder's bag up to its last complete chunk)."""
    counts: dict[str, int] = {}
    for message in bag_messages(directory):
        counts[message.topic] = counts.get(message.topic, 0) + 1
    return counts


def bag_meta(directory: str | Path) -> dict[str, Any]:
    """The `ddvs` metadata record of the bag's ROS 2 file (JSON values decoded), {} without one."""
    contents = FileContents({}, {}, {})
    for _ in read_records(storage_files(Path(directory))[0], contents):
        if META_RECORD in contents.metadata:
            break
    return {k: json.loads(v) for k, v in contents.metadata.get(META_RECORD, {}).items()}


# --- recovery --------------------------------------------------------------------------------------------------------


def _rewrite(path: Path, profile: str, compression: str) -> tuple[dict[str, int], int | None, int | None,
                                                                   dict[str, ChannelSpec], dict[str, Any]]:
    """Rewrite `path` complete from its readable records (a temporary file, then rename)."""
    contents = FileContents({}, {}, {})
    messages = list(read_records(path, contents))
    tmp = path.with_name(path.name + ".recovering")
    tmp.unlink(missing_ok=True)
    specs: dict[str, ChannelSpec] = {}
    for channel in contents.channels.values():
        schema = contents.schemas.get(channel.schema_id)
        specs[channel.topic] = ChannelSpec("", channel.topic, channel.message_encoding, schema.name if schema else "",
                                           schema.encoding if schema else "",
                                           schema.data.decode() if schema else "")
    meta = {k: json.loads(v) for k, v in contents.metadata.get(META_RECORD, {}).items()}
    out = _McapFile(tmp, profile, list(specs.values()), compression, 1 << 20, meta)
    for message in messages:
        out.write(contents.channels[message.channel_id].topic, message.data, message.log_time, message.publish_time)
    out.close()
    os.replace(tmp, path)
    return out.counts, out.start_ns, out.end_ns, specs, meta


def recover_bag(directory: str | Path, compression: str = "zstd") -> dict[str, int]:
    """Make a killed recorder's bag whole: rewrite each storage file from its readable records (a killed recorder's
    complete chunks; a complete file comes out with the same messages) and write metadata.yaml. Returns the messages
    kept per topic (both files)."""
    directory = Path(directory)
    ros_path, json_path = storage_files(directory)
    if not ros_path.exists():
        raise FileNotFoundError(f"{directory} is not a ddvs bag: it has no {ros_path.name}")
    counts: dict[str, int] = {}
    for path, profile in ((ros_path, "ros2"), (json_path, "")):
        if not path.exists():
            continue
        file_counts, start, end, specs, meta = _rewrite(path, profile, compression)
        counts.update(file_counts)
        if path == ros_path:
            write_metadata(directory, path.name, [(specs[t], n) for t, n in file_counts.items()], start, end, meta)
    return counts
