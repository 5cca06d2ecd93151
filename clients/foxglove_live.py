"""`ddvs monitor --foxglove`: a live Foxglove view of one servo, served with the Foxglove WebSocket protocol
(foxglove-sdk) from its Zenoh keys, to clients that offer either of its names, `foxglove.sdk.v1` (the Foxglove app)
or `foxglove.websocket.v1` (viewers on `@foxglove/ws-protocol`, such as Lichtblick): `clients.foxglove_relay`.

Channels: the channels of a run (`clients.channels.run_channels`: frames, camera info, twist, joint states, the
reference and the registration's residual image as ROS 2 CDR with `ros2msg` schemas; status, state, ground truth
and configuration as JSON with JSON schemas) and the ground-truth camera pose as `foxglove.FrameTransform`
`world → camera` on `/<prefix>/<robot>/arm/camera_pose` (from `arm/ground_truth`, when a simulator publishes it).
Payloads are forwarded as they arrive, logged at their arrival time; a channel nobody watches costs nothing (its
samples are not copied).

The service computes the residual (`servo/residual`) only while its key has a subscriber: this bridge subscribes
it on Zenoh only while a Foxglove client subscribes its channel.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from typing import TYPE_CHECKING, Any

import foxglove
import numpy as np
from foxglove.messages import FrameTransform, Quaternion, Timestamp, Vector3
from foxglove.websocket import ChannelView, Client, ServerListener

from clients.channels import ChannelSpec, pose_topic, run_channels
from clients.foxglove_relay import SubprotocolRelay
from ddvs_service.lie import so3_log

if TYPE_CHECKING:
    import zenoh

    from ddvs_service.protocol import Keys

log = logging.getLogger(__name__)
RESIDUAL = "servo_residual"


def pose_transform(camera_pose: list[float], stamp_ns: int) -> FrameTransform:
    """`world → camera` transform of a ground-truth pose `T_world_cam` (16 numbers, row-major; metres)."""
    T = np.asarray(camera_pose, dtype=np.float64).reshape(4, 4)
    r = so3_log(T[:3, :3])
    angle = float(np.linalg.norm(r))
    axis = r / angle if angle > 0.0 else np.zeros(3)
    s = np.sin(angle / 2.0)
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return FrameTransform(timestamp=Timestamp(sec=sec, nsec=nsec), parent_frame_id="world", child_frame_id="camera",
                          translation=Vector3(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                          rotation=Quaternion(x=float(axis[0] * s), y=float(axis[1] * s), z=float(axis[2] * s),
                                              w=float(np.cos(angle / 2.0))))


class FoxgloveBridge(ServerListener):
    """Serves `keys`' servo on `host:port` until `close()`; `port=0` picks a free port (`self.port`)."""

    def __init__(self, session: zenoh.Session, keys: Keys, host: str = "127.0.0.1", port: int = 8765) -> None:
        self._session = session
        self._keys = keys
        self.context = foxglove.Context()
        self.channels: dict[str, foxglove.Channel] = {spec.key_name: self._channel(spec)
                                                      for spec in run_channels(keys)}
        self.pose_channel = foxglove.channels.FrameTransformChannel(pose_topic(keys), context=self.context)
        self._subscribers = [session.declare_subscriber(keys.key(name), self._forward(name))
                             for name in self.channels if name != RESIDUAL]
        self._residual_topic = self.channels[RESIDUAL].topic()
        self._residual_watchers = 0
        self._residual_subscriber: Any = None
        self._lock = threading.Lock()
        self.server = foxglove.start_server(name=f"ddvs {keys.base}", host="127.0.0.1", port=0, context=self.context,
                                            server_listener=self)
        try:
            self.relay = SubprotocolRelay(host, port, self.server.port)  # the public socket, either protocol name
        except OSError:  # host:port taken or not ours
            self.server.stop()
            raise
        self.port = self.relay.port

    def _channel(self, spec: ChannelSpec) -> foxglove.Channel:
        schema = foxglove.Schema(name=spec.schema_name, encoding=spec.schema_encoding, data=spec.schema.encode())
        return foxglove.Channel(spec.topic, schema=schema, message_encoding=spec.message_encoding,
                                context=self.context)

    def _forward(self, key_name: str):
        channel = self.channels[key_name]

        def on_sample(sample: zenoh.Sample) -> None:
            now = time.time_ns()
            if key_name == "arm_ground_truth":
                self._log_pose(sample.payload.to_bytes(), now)
            if channel.has_sinks():
                channel.log(sample.payload.to_bytes(), log_time=now)

        return on_sample

    def _log_pose(self, payload: bytes, now: int) -> None:
        if not self.pose_channel.has_sinks():
            return
        try:
            truth = json.loads(payload)
            self.pose_channel.log(pose_transform(truth["camera_pose"], truth["stamp_ns"]), log_time=now)
        except (ValueError, KeyError, TypeError) as exc:
            log.warning("ground truth not shown: %s", exc)

    # --- foxglove.websocket.ServerListener: the residual key is subscribed only while a client watches ---------------
    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        if channel.topic != self._residual_topic:
            return
        with self._lock:
            self._residual_watchers += 1
            if self._residual_subscriber is None:
                self._residual_subscriber = self._session.declare_subscriber(self._keys.key(RESIDUAL),
                                                                             self._forward(RESIDUAL))

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        if channel.topic != self._residual_topic:
            return
        with self._lock:
            self._residual_watchers = max(self._residual_watchers - 1, 0)
            if self._residual_watchers == 0 and self._residual_subscriber is not None:
                self._residual_subscriber.undeclare()
                self._residual_subscriber = None

    def close(self) -> None:
        self.relay.close()
        self.server.stop()
        with self._lock:
            residual, self._residual_subscriber = self._residual_subscriber, None
        for subscriber in [*self._subscribers, *([residual] if residual is not None else [])]:
            subscriber.undeclare()
        self._subscribers.clear()


def serve(session: zenoh.Session, keys: Keys, host: str, port: int, stop: threading.Event) -> None:
    """Serve the live view until `stop` is set."""
    bridge = FoxgloveBridge(session, keys, host, port)
    layout = "docs/foxglove/ddvs-layout-ros2.json" if keys.rmw else "docs/foxglove/ddvs-layout.json"
    print(f"ddvs monitor: Foxglove live view of {keys.base} on ws://{host}:{bridge.port} — in Foxglove: Open "
          f"connection → Foxglove WebSocket; layout: {layout} (robot0; docs/recording.md)", flush=True)
    try:
        stop.wait()
    finally:
        bridge.close()
