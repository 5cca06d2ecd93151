"""`ddvs monitor --foxglove`: a `websockets` client speaking the Foxglove WebSocket protocol on loopback
subscribes every channel of the live view and receives each with the right schema, from a real Zenoh publisher;
the layout shipped in docs/foxglove is the builder's output and names the run's channels."""

from __future__ import annotations

import asyncio
import json
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import websockets
from conftest import free_port
from run_messages import run_payloads

from clients.channels import pose_topic, run_channels, topic_name
from clients.foxglove_layout import layout_json
from ddvs_service.protocol import (
    GroundTruth,
    Header,
    Keys,
    SessionConfig,
    StateSnapshot,
    Time,
    TwistStamped,
    declare_publisher,
    decode_image,
    decode_twist_stamped,
    dump,
    encode_image,
    image_from_array,
)
from ddvs_service.protocol.msgdefs import message_definition

ROOT = Path(__file__).resolve().parents[1]
KEYS = Keys("ddvs", "foxtest")
MESSAGE_DATA = 0x01
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
"""What Foxglove offers: foxglove-sdk 0.30 names the foxglove.websocket.v1 protocol `foxglove.sdk.v1` and accepts
only that name."""


def _publish(port: int, stop: threading.Event, watched: threading.Event, residual_early: list[bool]) -> None:
    """Every key of a run at 20 Hz (ground truth a turn about z, 0.3 rad), until `stop`; the residual, as the service
    does, only while its key has a subscriber (`residual_early` records one before `watched` was set)."""
    from ddvs_service.lie import pose, so3_exp
    from ddvs_service.protocol import open_session

    with open_session(SessionConfig(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        names = (*run_payloads(0), "servo_reference", "servo_state", "servo_config")
        pubs = {name: declare_publisher(session, KEYS, name) for name in names}
        residual = declare_publisher(session, KEYS, "servo_residual")
        seq = 0
        while not stop.is_set():
            if residual.matching_status.matching:
                residual_early.append(not watched.is_set())
                residual.put(encode_image(image_from_array(np.full((4, 5), -3.5, np.float32), "32FC1")))
            payloads = run_payloads(seq)
            payloads["servo_reference"] = payloads["camera_image"]
            payloads["servo_state"] = dump(StateSnapshot(robot=KEYS.robot, state="SERVOING", has_reference=True))
            payloads["servo_config"] = json.dumps({"robot": KEYS.robot}).encode()
            T = pose(so3_exp([0, 0, 0.3]), [0.1, 0.2, 0.7])
            payloads["arm_ground_truth"] = dump(GroundTruth(stamp_ns=seq, camera_pose=T.reshape(-1).tolist()))
            payloads["servo_twist"] = _twist(seq)
            for name, payload in payloads.items():
                pubs[name].put(payload)
            seq += 1
            stop.wait(0.05)


def _twist(seq: int) -> bytes:
    from ddvs_service.protocol import encode_twist_stamped

    return encode_twist_stamped(TwistStamped(Header(Time.from_ns(seq), "camera"), [0.01, 0, 0], [0, 0, seq]))


async def _watch(url: str, seconds: float) -> tuple[dict, dict[int, dict], dict[int, list[bytes]]]:
    """Connect, subscribe every advertised channel, collect message data for `seconds`."""
    channels: dict[int, dict] = {}
    received: dict[int, list[bytes]] = {}
    async with websockets.connect(url, subprotocols=SUBPROTOCOLS, max_size=None) as ws:
        info = json.loads(await ws.recv())
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            try:
                frame = await asyncio.wait_for(ws.recv(), timeout=0.2)
            except TimeoutError:
                continue
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "advertise":
                    new = {c["id"]: c for c in msg["channels"]}
                    channels.update(new)
                    await ws.send(json.dumps({"op": "subscribe",
                                              "subscriptions": [{"id": cid, "channelId": cid} for cid in new]}))
            elif frame[0] == MESSAGE_DATA:
                subscription, _log_time = struct.unpack_from("<IQ", frame, 1)
                received.setdefault(subscription, []).append(bytes(frame[13:]))
    return info, channels, received


def test_a_websocket_client_receives_every_channel_with_its_schema():
    zenoh_port, ws_port = free_port(), free_port()
    stop, watched, residual_early = threading.Event(), threading.Event(), []
    publisher = threading.Thread(target=_publish, args=(zenoh_port, stop, watched, residual_early), daemon=True)
    publisher.start()
    cmd = [sys.executable, "-m", "ddvs.cli", "monitor", "--foxglove", "--port", str(ws_port), "--robot", KEYS.robot,
           "--connect", f"tcp/127.0.0.1:{zenoh_port}"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        line = proc.stdout.readline()
        assert f"ws://127.0.0.1:{ws_port}" in line, line + proc.stdout.read()
        time.sleep(1.0)  # the bridge is up and subscribed to everything but the residual
        watched.set()
        info, channels, received = asyncio.run(_watch(f"ws://127.0.0.1:{ws_port}", 4.0))
    finally:
        proc.terminate()
        assert proc.wait(20) == 0
        stop.set()
        publisher.join(5)
    assert info["op"] == "serverInfo"
    expected = {spec.topic: spec for spec in run_channels(KEYS)}
    by_topic = {c["topic"]: c for c in channels.values()}
    assert set(by_topic) == {*expected, pose_topic(KEYS)}
    for topic, spec in expected.items():
        channel = by_topic[topic]
        assert (channel["encoding"], channel["schemaName"], channel["schemaEncoding"]) == (
            spec.message_encoding, spec.schema_name, spec.schema_encoding), topic
        if spec.is_ros:
            assert channel["schema"] == message_definition(spec.schema_name)
        assert received.get(channel["id"]), f"nothing received on {topic}"
    pose = by_topic[pose_topic(KEYS)]
    assert (pose["encoding"], pose["schemaName"]) == ("protobuf", "foxglove.FrameTransform")
    assert received.get(pose["id"]), "no camera pose received"
    assert residual_early and not any(residual_early)  # the residual key was subscribed only once a client watched
    residual = decode_image(received[by_topic[topic_name(KEYS, "servo_residual")]["id"]][0])
    assert residual.encoding == "32FC1" and np.all(residual.array == -3.5)
    twists = [decode_twist_stamped(p) for p in received[by_topic[topic_name(KEYS, "servo_twist")]["id"]]]
    assert all(t.angular[2] == t.header.stamp.nanosec for t in twists)  # the payloads as published
    state = json.loads(received[by_topic[topic_name(KEYS, "servo_state")]["id"]][-1])
    assert state["state"] == "SERVOING"
    image = received[by_topic[topic_name(KEYS, "camera_image")]["id"]][0]
    assert len(image) > 48 * 64 and np.frombuffer(image[-48 * 64:], np.uint8).max() > 0


def test_the_shipped_layout_is_the_builders_and_names_run_channels():
    shipped = (ROOT / "docs" / "foxglove" / "ddvs-layout.json").read_text(encoding="utf-8")
    assert shipped == layout_json(Keys())
    text = json.dumps(json.loads(shipped), ensure_ascii=False)
    topics = {spec.topic for spec in run_channels(Keys())}
    for key_name in ("camera_image", "camera_info", "servo_reference", "servo_residual", "servo_status", "servo_twist",
                     "servo_state"):
        assert topic_name(Keys(), key_name) in text and topic_name(Keys(), key_name) in topics, key_name
    assert pose_topic(Keys()) in text
