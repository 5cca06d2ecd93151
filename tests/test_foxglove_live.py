"""`ddvs monitor --foxglove`: a `websockets` client speaking the Foxglove WebSocket protocol on loopback, offering
either name of the protocol (`foxglove.sdk.v1`, `foxglove.websocket.v1`), subscribes every channel of the live view
and receives each with the right schema, from real Zenoh publishers (plain keys, or ROS 2 mode's rmw_zenoh keys);
every topic the layout of that mode names carries data, and the layouts shipped in docs/foxglove are the builder's
output."""

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
import pytest
import websockets
from conftest import free_port
from run_messages import run_payloads

from clients.channels import pose_topic, run_channels, topic_name
from clients.foxglove_layout import LAYOUTS, layout_json, layout_topics
from ddvs_service.protocol import (
    GroundTruth,
    Header,
    Keys,
    SessionConfig,
    StateSnapshot,
    Time,
    TwistStamped,
    decode_image,
    decode_twist_stamped,
    dump,
    encode_image,
    image_from_array,
)
from ddvs_service.protocol.endpoints import Endpoints
from ddvs_service.protocol.msgdefs import message_definition
from ddvs_service.protocol.ros_settings import RosSettings

ROOT = Path(__file__).resolve().parents[1]
MODES = {"plain": Keys("ddvs", "foxtest"), "ros2": Keys("ddvs", "foxtest", RosSettings(domain_id=7))}
MESSAGE_DATA = 0x01
OFFERS = {"sdk": ["foxglove.sdk.v1"], "ws-protocol": ["foxglove.websocket.v1"]}
"""Subprotocols a client offers: an SDK client (the Foxglove app) the new name, a viewer on `@foxglove/ws-protocol`
(Lichtblick) the old one only (foxglove-sdk 0.30 alone accepts only `foxglove.sdk.v1`)."""


def _publish(port: int, keys: Keys, stop: threading.Event, watched: threading.Event,
             residual_early: list[bool]) -> None:
    """Every key of a run at 20 Hz (ground truth a turn about z, 0.3 rad), until `stop`, on the endpoints the nodes
    declare in the mode of `keys` (in ROS 2 mode with rmw_zenoh's graph tokens and attachments); the residual, as the
    service does, only while its key has a subscriber (`residual_early` records one before `watched` was set)."""
    from ddvs_service.lie import pose, so3_exp
    from ddvs_service.protocol import open_session

    with open_session(SessionConfig(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        ends = Endpoints(session, keys, "ddvs_servo")
        names = (*run_payloads(0), "servo_reference", "servo_state", "servo_config")
        pubs = {name: ends.publisher(name) for name in names}
        residual = ends.publisher("servo_residual")
        seq = 0
        while not stop.is_set():
            if residual.matching_status.matching:
                residual_early.append(not watched.is_set())
                residual.put(encode_image(image_from_array(np.full((4, 5), -3.5, np.float32), "32FC1")))
            payloads = run_payloads(seq)
            payloads["servo_reference"] = payloads["camera_image"]
            payloads["servo_state"] = dump(StateSnapshot(robot=keys.robot, state="SERVOING", has_reference=True))
            payloads["servo_config"] = json.dumps({"robot": keys.robot}).encode()
            T = pose(so3_exp([0, 0, 0.3]), [0.1, 0.2, 0.7])
            payloads["arm_ground_truth"] = dump(GroundTruth(stamp_ns=seq, camera_pose=T.reshape(-1).tolist()))
            payloads["servo_twist"] = _twist(seq)
            for name, payload in payloads.items():
                pubs[name].put(payload)
            seq += 1
            stop.wait(0.05)
        ends.close()


def _twist(seq: int) -> bytes:
    from ddvs_service.protocol import encode_twist_stamped

    return encode_twist_stamped(TwistStamped(Header(Time.from_ns(seq), "camera"), [0.01, 0, 0], [0, 0, seq]))


async def _watch(url: str, seconds: float,
                 offer: list[str]) -> tuple[dict, dict[int, dict], dict[int, list[bytes]]]:
    """Connect offering the subprotocols `offer`, subscribe every advertised channel, collect message data for
    `seconds`; the server must have chosen the first offered name."""
    channels: dict[int, dict] = {}
    received: dict[int, list[bytes]] = {}
    async with websockets.connect(url, subprotocols=offer, max_size=None) as ws:
        assert ws.subprotocol == offer[0], ws.subprotocol
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


@pytest.mark.parametrize(("client", "mode"), [("sdk", "plain"), ("ws-protocol", "plain"), ("sdk", "ros2")])
def test_a_websocket_client_receives_every_channel_with_its_schema(client: str, mode: str):
    """A client offering either subprotocol name gets every channel; in both modes every topic the layout of that
    mode names carries data."""
    keys = MODES[mode]
    zenoh_port, ws_port = free_port(), free_port()
    stop, watched, residual_early = threading.Event(), threading.Event(), []
    publisher = threading.Thread(target=_publish, args=(zenoh_port, keys, stop, watched, residual_early),
                                 daemon=True)
    publisher.start()
    ros = ["--ros-domain-id", str(keys.ros.domain_id)] if keys.rmw else []
    cmd = [sys.executable, "-m", "ddvs.cli", "monitor", "--foxglove", "--port", str(ws_port), "--robot", keys.robot,
           "--connect", f"tcp/127.0.0.1:{zenoh_port}", *ros]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        line = proc.stdout.readline()
        assert f"ws://127.0.0.1:{ws_port}" in line, line + proc.stdout.read()
        time.sleep(1.0)  # the bridge is up and subscribed to everything but the residual
        watched.set()
        info, channels, received = asyncio.run(_watch(f"ws://127.0.0.1:{ws_port}", 4.0, OFFERS[client]))
    finally:
        proc.terminate()
        assert proc.wait(20) == 0
        stop.set()
        publisher.join(5)
    assert info["op"] == "serverInfo"
    expected = {spec.topic: spec for spec in run_channels(keys)}
    by_topic = {c["topic"]: c for c in channels.values()}
    assert set(by_topic) == {*expected, pose_topic(keys)}
    for topic, spec in expected.items():
        channel = by_topic[topic]
        assert (channel["encoding"], channel["schemaName"], channel["schemaEncoding"]) == (
            spec.message_encoding, spec.schema_name, spec.schema_encoding), topic
        if spec.is_ros:
            assert channel["schema"] == message_definition(spec.schema_name)
        assert received.get(channel["id"]), f"nothing received on {topic}"
    pose = by_topic[pose_topic(keys)]
    assert (pose["encoding"], pose["schemaName"]) == ("protobuf", "foxglove.FrameTransform")
    assert received.get(pose["id"]), "no camera pose received"
    assert residual_early and not any(residual_early)  # the residual key was subscribed only once a client watched
    residual = decode_image(received[by_topic[topic_name(keys, "servo_residual")]["id"]][0])
    assert residual.encoding == "32FC1" and np.all(residual.array == -3.5)
    twists = [decode_twist_stamped(p) for p in received[by_topic[topic_name(keys, "servo_twist")]["id"]]]
    assert all(t.angular[2] == t.header.stamp.nanosec for t in twists)  # the payloads as published
    state = json.loads(received[by_topic[topic_name(keys, "servo_state")]["id"]][-1])
    assert state["state"] == "SERVOING"
    image = received[by_topic[topic_name(keys, "camera_image")]["id"]][0]
    assert len(image) > 48 * 64 and np.frombuffer(image[-48 * 64:], np.uint8).max() > 0
    live = {topic for topic, channel in by_topic.items() if received.get(channel["id"])}
    named = layout_topics(json.loads(layout_json(keys)))
    assert named <= live, f"the {mode} layout names topics the live view does not publish: {named - live}"



@pytest.mark.parametrize("path", sorted(LAYOUTS))
def test_the_shipped_layouts_are_the_builders_for_their_mode(path: str):
    """Each shipped layout is the builder's output for its mode and robot `robot0`; its topics are those of that
    mode's live view (that these carry data: the test above, with the test's robot)."""
    keys = LAYOUTS[path]
    shipped = (ROOT / path).read_text(encoding="utf-8")
    assert shipped == layout_json(keys)
    live = {spec.topic for spec in run_channels(keys)} | {pose_topic(keys)}
    named = layout_topics(json.loads(shipped))
    assert named <= live, named - live
    assert {topic_name(keys, name) for name in ("camera_image", "servo_twist", "servo_status")} <= named
