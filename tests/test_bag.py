"""Bags of `ddvs record` (rosbag2 directory, MCAP storage): message definitions against the ROS type store, a
recorded run read back by the `rosbags` rosbag2 reader and the `mcap` reader, a killed recorder's complete chunks,
and `ddvs record --recover`."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from bag_checks import check_bag
from conftest import free_port
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from run_messages import frame, run_payloads

from clients.bag import (
    BagWriter,
    FileContents,
    bag_messages,
    iter_messages,
    read_records,
    recover_bag,
    storage_files,
)
from clients.channels import json_schema, ros_channel, run_channels, topic_name
from clients.compressed_image import compress_image
from ddvs_service.protocol import (
    TOPICS,
    Header,
    Keys,
    SessionConfig,
    StateSnapshot,
    Status,
    Time,
    declare_publisher,
    dump,
    encode_image,
    image_from_array,
    open_session,
    parse_message,
)
from ddvs_service.protocol.msgdefs import MSG_TEXT, message_definition

ROOT = Path(__file__).resolve().parents[1]
JAZZY = get_typestore(Stores.ROS2_JAZZY)


@pytest.mark.parametrize("ros_type", sorted(MSG_TEXT))
def test_message_definitions_are_the_ros_types(ros_type):
    types = get_types_from_msg(message_definition(ros_type), ros_type)
    assert ros_type in types
    for name, fields in types.items():
        assert fields == JAZZY.fielddefs[name], name


ONCE = {
    "servo_reference": lambda: encode_image(image_from_array(frame(0), "mono8")),
    "servo_residual": lambda: encode_image(image_from_array(np.full((4, 5), -1.5, np.float32), "32FC1")),
    "servo_state": lambda: dump(StateSnapshot(robot="r", state="READY", has_reference=True, message="set")),
    "servo_config": lambda: json.dumps({"robot": "r", "control": {"law": "ddvs"}}).encode(),
}


def _start_recorder(out: Path, port: int, robot: str, *extra: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "ddvs.cli", "record", str(out), "--robot", robot,
           "--listen", f"tcp/127.0.0.1:{port}", "--meta", "stop_threshold=0.001", *extra]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 30
    while not storage_files(out)[0].exists():
        assert proc.poll() is None, proc.stdout.read().decode()
        assert time.monotonic() < deadline, "the recorder did not start"
        time.sleep(0.05)
    return proc


def _publish_run(port: int, keys: Keys, count: int, hz: float, stop_at: float | None = None) -> dict[str, list[bytes]]:
    """Publish `count` rounds of every key at `hz` (the ONCE keys first); returns what was sent per key."""
    sent: dict[str, list[bytes]] = {name: [] for name in (*ONCE, *run_payloads(0))}
    with open_session(SessionConfig(connect=[f"tcp/127.0.0.1:{port}"])) as session:
        pubs = {name: declare_publisher(session, keys, name) for name in sent}
        time.sleep(1.0)  # the recorder's subscriptions reach this session
        for name, make in ONCE.items():
            sent[name].append(make())
            pubs[name].put(sent[name][-1])
        for seq in range(count):
            for name, payload in run_payloads(seq).items():
                pubs[name].put(payload)
                sent[name].append(payload)
            time.sleep(1.0 / hz)
            if stop_at is not None and time.monotonic() >= stop_at:
                break
        for pub in pubs.values():
            pub.undeclare()
    return sent


def test_recorded_run_is_read_by_rosbags_and_the_mcap_reader(tmp_path):
    port, keys, out = free_port(), Keys("ddvs", "bagtest"), tmp_path / "run"
    proc = _start_recorder(out, port, keys.robot)
    try:
        sent = _publish_run(port, keys, count=60, hz=50)
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(20) == 0, proc.stdout.read().decode()
    finally:
        if proc.poll() is None:
            proc.kill()
    topic_of = {spec.key_name: spec.topic for spec in run_channels(keys)}

    # rosbags: the rosbag2 directory (metadata.yaml + storage file), every ROS message decoded with the bag's own
    # message definitions, byte-identical to what was published
    decoded: dict[str, list] = {}
    with AnyReader([out]) as reader:
        for connection, _, raw in reader.messages():
            decoded.setdefault(connection.topic, []).append((reader.deserialize(raw, connection.msgtype), raw))
        metadata_counts = {c.topic: c.msgcount for c in reader.connections}
    for name in ("camera_image", "camera_image_rect", "camera_image_compressed", "camera_image_rect_compressed",
                 "camera_info", "servo_twist", "arm_joint_states", "servo_reference", "servo_residual"):
        raws = [raw for _, raw in decoded[topic_of[name]]]
        _assert_in_order(raws, sent[name], name)
        assert metadata_counts[topic_of[name]] == len(raws)
    for image, _ in decoded[topic_of["camera_image"]]:
        np.testing.assert_array_equal(image.data.reshape(48, 64), frame(image.header.stamp.nanosec))
    twists = [msg.twist.linear.x for msg, _ in decoded[topic_of["servo_twist"]]]
    assert twists == sorted(twists)
    assert decoded[topic_of["camera_info"]][0][0].k[2] == 31.5

    # mcap reader: each file's summary lists every channel with its message count
    counts = {}
    for path in storage_files(out):
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
        assert summary is not None and summary.statistics is not None
        for channel_id, channel in summary.channels.items():
            counts[channel.topic] = summary.statistics.channel_message_counts.get(channel_id, 0)
            schema = summary.schemas[channel.schema_id]
            assert (channel.message_encoding, schema.encoding) in (("cdr", "ros2msg"), ("json", "jsonschema"))
            if channel.message_encoding == "json":
                key = next(k for k, t in topic_of.items() if t == channel.topic)
                assert schema.data.decode() == json_schema(key)
    by_topic: dict[str, list[bytes]] = {}
    for message in bag_messages(out):
        by_topic.setdefault(message.topic, []).append(message.data)
    assert counts == {topic: len(data) for topic, data in by_topic.items()}
    assert set(counts) == set(topic_of.values())  # every channel, each with messages
    for name in ("servo_status", "arm_ground_truth", "servo_state", "servo_config"):
        _assert_in_order(by_topic[topic_of[name]], sent[name], name)
    statuses = [parse_message(Status, data) for data in by_topic[topic_of["servo_status"]]]
    assert [s.seq for s in statuses] == sorted(s.seq for s in statuses)
    assert check_bag(out) == {topic: len(data) for topic, data in by_topic.items()}  # mcap_ros2 decodes them too


def _assert_in_order(recorded: list[bytes], sent: list[bytes], name: str) -> None:
    """`recorded` is `sent` in order, all of it on keys with BLOCK congestion control; on DROP keys less what the
    transport dropped on this loaded 2-core machine (at least half)."""
    it = iter(sent)
    assert all(any(r == s for s in it) for r in recorded), f"{name}: recorded messages not sent, or out of order"
    least = len(sent) if TOPICS[name].congestion == "BLOCK" else 0.5 * len(sent)
    assert len(recorded) >= least, f"{name}: {len(recorded)} of {len(sent)} recorded"


def test_killed_recorder_keeps_every_complete_chunk_and_recover_makes_the_bag_whole(tmp_path):
    port, keys, out = free_port(), Keys("ddvs", "killtest"), tmp_path / "run"
    proc = _start_recorder(out, port, keys.robot, "--flush-period", "0.5")
    try:
        kill_at = time.monotonic() + 1.0 + 2.5  # 1 s for the subscriptions, then 2.5 s of 100 Hz
        sent = _publish_run_killing(port, keys, proc, kill_at)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    status_topic = topic_name(keys, "servo_status")
    read = [m for m in bag_messages(out) if m.topic == status_topic]
    published = len(sent["servo_status"])
    # every message read back is one that was sent, in order; at most the last flush period (0.5 s, 50 messages at
    # 100 Hz) plus the writer's lag is lost
    assert [m.data for m in read] == sent["servo_status"][: len(read)]
    assert published - 80 <= len(read) <= published, (len(read), published)
    assert not (out / "metadata.yaml").exists()  # written at close only: the recorder died mid-run
    for path in storage_files(out):
        contents = FileContents({}, {}, {})
        assert sum(1 for _ in read_records(path, contents)) > 0 and not contents.complete  # no footer
    frames = [m for m in bag_messages(out) if m.topic == topic_name(keys, "camera_image")]
    assert [m.data for m in frames] == sent["camera_image"][: len(frames)] and len(frames) >= published - 80

    kept = subprocess.run([sys.executable, "-m", "ddvs.cli", "record", str(out), "--recover"], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert kept.returncode == 0, kept.stderr
    assert json.loads(kept.stdout)[status_topic] == len(read)
    with AnyReader([out]) as reader:
        n = {c.topic: c.msgcount for c in reader.connections}
        assert sum(1 for _ in reader.messages()) == sum(n.values())
    assert n[topic_name(keys, "camera_image")] == len(frames)


def _publish_run_killing(port: int, keys: Keys, proc: subprocess.Popen, kill_at: float) -> dict[str, list[bytes]]:
    """Publish at 100 Hz and `kill -9` the recorder at `kill_at` while publishing; what was sent before the kill."""
    sent: dict[str, list[bytes]] = {}
    with open_session(SessionConfig(connect=[f"tcp/127.0.0.1:{port}"])) as session:
        pubs = {name: declare_publisher(session, keys, name) for name in run_payloads(0)}
        time.sleep(1.0)
        seq = 0
        while time.monotonic() < kill_at:
            for name, payload in run_payloads(seq).items():
                pubs[name].put(payload)
                sent.setdefault(name, []).append(payload)
            seq += 1
            time.sleep(0.01)
        os.kill(proc.pid, signal.SIGKILL)
        for pub in pubs.values():
            pub.undeclare()
    return sent


def test_a_file_cut_anywhere_reads_back_whole_chunks(tmp_path):
    keys = Keys("ddvs", "cut")
    specs = {spec.key_name: spec for spec in run_channels(keys)}
    writer = BagWriter(tmp_path / "bag", list(specs.values()), {"note": "cut"}, compression="lz4")
    per_chunk, chunks = 5, 8
    for c in range(chunks):
        for i in range(per_chunk):
            seq = c * per_chunk + i
            writer.write(specs["servo_twist"].topic, run_payloads(seq)["servo_twist"], seq, seq)
        writer.flush()
    path = storage_files(tmp_path / "bag")[0]
    whole = path.read_bytes()  # a killed recorder's file: complete chunks, no summary, no footer
    writer.close()
    cut_file = tmp_path / "cut.mcap"
    longest_cut: dict[int, int] = {}
    for cut in range(len(whole) - 1, 0, -37):
        cut_file.write_bytes(whole[:cut])
        n = sum(1 for _ in iter_messages(cut_file))
        assert n % per_chunk == 0, (cut, n)
        longest_cut.setdefault(n, cut)
    assert set(longest_cut) == {per_chunk * c for c in range(chunks + 1)}  # every prefix of whole chunks only

    path.write_bytes(whole[: longest_cut[per_chunk * (chunks - 1)]])  # a bag cut inside its last chunk
    counts = recover_bag(tmp_path / "bag", "none")
    assert counts[specs["servo_twist"].topic] == per_chunk * (chunks - 1)
    with AnyReader([tmp_path / "bag"]) as reader:
        assert sum(1 for _ in reader.messages()) == per_chunk * (chunks - 1)


def test_compressed_frames_decode_with_rosbags(tmp_path):
    keys = Keys("ddvs", "png")
    image = image_from_array(frame(3), "mono8", Header(Time.from_ns(5), "camera"))
    spec = ros_channel(keys, "camera_image_compressed")
    writer = BagWriter(tmp_path / "bag", [spec])
    writer.write(spec.topic, compress_image(image, "png"), 10, 5)
    writer.write(spec.topic, compress_image(image, "jpeg"), 11, 5)
    writer.close()
    with AnyReader([tmp_path / "bag"]) as reader:
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()]
    assert [m.format for m in msgs] == ["png", "jpeg"] and msgs[0].header.stamp.nanosec == 5
    np.testing.assert_array_equal(cv2.imdecode(msgs[0].data, cv2.IMREAD_UNCHANGED), frame(3))
    assert np.abs(cv2.imdecode(msgs[1].data, cv2.IMREAD_UNCHANGED).astype(int) - frame(3)).mean() < 3
