"""ddvs as a ROS 2 citizen over rmw_zenoh (docs/ros2.md), checked against real third-party parts: rmw_zenoh's own
token examples (docs/design.md), rclpy (the Kilted wheels) for every payload, and zenoh-ros2-sdk as the ROS-side
peer on loopback — its graph queries, publishers, subscribers and service client.

The live test runs `ddvs serve --ros-domain-id` in a subprocess; the SDK (this process) publishes rclpy-serialised
Image + CameraInfo of a free-flying camera on `/image_raw` and `/camera_info`, sets the reference and starts the servo
with `std_srvs/srv/Trigger` calls, and moves the camera by each TwistStamped it receives (decoded by rclpy) until the
camera is back at the reference pose.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh
from conftest import free_port
from geometry_msgs.msg import TwistStamped as RosTwistStamped
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CameraInfo as RosCameraInfo
from sensor_msgs.msg import CompressedImage as RosCompressedImage
from sensor_msgs.msg import Image as RosImage
from sensor_msgs.msg import JointState as RosJointState
from std_msgs.msg import Float64MultiArray as RosFloat64MultiArray
from std_srvs.srv import Trigger

from ddvs_service.camera import Intrinsics
from ddvs_service.lie import pose, pose_inv, so3_exp, so3_log
from ddvs_service.protocol import Keys, SessionConfig, open_session
from ddvs_service.protocol.guard import CommandGuard, CommandLimits
from ddvs_service.protocol.rmw import TYPE_HASHES, RmwAttachment
from ddvs_service.protocol.ros import (
    Float64MultiArray,
    decode_trigger_request,
    decode_trigger_response,
    encode_float64_multi_array,
    encode_trigger_request,
    encode_trigger_response,
)
from ddvs_service.protocol.ros_graph import (
    SENSOR_DATA_QOS,
    GraphEntity,
    GraphNode,
    RosQos,
    discover,
    parse_token,
)
from ddvs_service.protocol.ros_settings import RosSettings

DESIGN_ZID = "aac3178e146ba6f1fc6e6a4085e77f21"
CHATTER = ("std_msgs::msg::dds_::String_", "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
ADD_TWO_INTS = ("example_interfaces::srv::dds_::AddTwoInts_",
                "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a")


# --- formats against rmw_zenoh's own examples and rclpy ----------------------------------------------------------


def test_tokens_and_qos_are_rmw_zenohs_own_examples() -> None:
    """The examples of rmw_zenoh's docs/design.md ("Graph Cache"), built and parsed back."""
    listener = GraphNode(2, "/", "listener")
    examples = {
        f"@ros2_lv/2/{DESIGN_ZID}/0/0/NN/%/%/listener": GraphEntity(DESIGN_ZID, 0, 0, "NN", listener),
        f"@ros2_lv/2/{DESIGN_ZID}/0/10/MS/%/%/listener/%chatter/{CHATTER[0]}/{CHATTER[1]}/::,10:,:,:,,":
            GraphEntity(DESIGN_ZID, 0, 10, "MS", listener, "/chatter", *CHATTER, RosQos(depth=10).encode()),
        f"@ros2_lv/2/{DESIGN_ZID}/0/10/MP/%/%/talker/%chatter/{CHATTER[0]}/{CHATTER[1]}/::,7:,:,:,,":
            GraphEntity(DESIGN_ZID, 0, 10, "MP", GraphNode(2, "/", "talker"), "/chatter", *CHATTER,
                        RosQos(depth=7).encode()),
        f"@ros2_lv/2/{DESIGN_ZID}/0/10/SS/%/%/add_two_ints_server/%add_two_ints/{ADD_TWO_INTS[0]}/"
        f"{ADD_TWO_INTS[1]}/::,10:,:,:,,":
            GraphEntity(DESIGN_ZID, 0, 10, "SS", GraphNode(2, "/", "add_two_ints_server"), "/add_two_ints",
                        *ADD_TWO_INTS, RosQos(depth=10).encode()),
    }
    for token, entity in examples.items():
        assert entity.token() == token
        assert parse_token(token) == entity
    assert RosQos().encode() == "::,:,:,:,,"  # rmw_zenoh's defaults: reliable, volatile, keep last 42
    assert SENSOR_DATA_QOS.encode() == "2::,5:,:,:,,"
    assert RosQos(durability="transient_local", history="keep_all").encode() == ":1:2,:,:,:,,"
    qos = SENSOR_DATA_QOS.encode()
    namespaced = GraphEntity("ab", 3, 4, "MP", GraphNode(0, "/cell/arm0", "n"), "/cell/arm0/image_raw", "t", "h", qos)
    assert namespaced.token() == f"@ros2_lv/0/ab/3/4/MP/%/%cell%arm0/n/%cell%arm0%image_raw/t/h/{qos}"
    assert parse_token(namespaced.token()) == namespaced
    other = GraphEntity("ab", 3, 5, "MP", namespaced.node, "/cell/arm0/image_raw", "t", "h", qos)
    assert len(namespaced.gid()) == 16 and namespaced.gid() != other.gid()  # XXH3-128 of the whole token
    for bad in ("@ros2_lv/0/ab/0/0/XX/%/%/n", "@ros2_lv/0/ab/0/1/MP/%/%/n", "other/0/ab/0/0/NN/%/%/n",
                "@ros2_lv/0/ab/0/1/MP/%/%/n/%t/T/H/1:2"):
        with pytest.raises(ValueError):
            parse_token(bad)


def test_trigger_request_and_response_read_back_in_rclpy() -> None:
    assert deserialize_message(encode_trigger_request(), Trigger.Request) == Trigger.Request()
    decode_trigger_request(serialize_message(Trigger.Request()))  # rclpy's 8-byte buffer (3 trailing bytes)
    for success, message in ((True, "start: done, state SERVOING"), (False, "stop: not allowed in IDLE"), (True, "")):
        response = Trigger.Response(success=success, message=message)
        assert deserialize_message(encode_trigger_response(success, message), Trigger.Response) == response
        assert decode_trigger_response(serialize_message(response)) == (success, message)


def test_guard_takes_ros2_control_commands_in_joint_order() -> None:
    keys = Keys("ddvs", "arm0", RosSettings(domain_id=3))
    guard = CommandGuard(keys, 0.1, CommandLimits(joint_velocity={"a": 1.0, "b": 2.0}), clock=lambda: 5)
    payload = encode_float64_multi_array(Float64MultiArray([0.5, -1.5]))
    msg = guard.velocity_array(keys.arm_velocity_commands, payload, ["a", "b"])
    assert msg is not None and msg.name == ["a", "b"] and msg.velocity.tolist() == [0.5, -1.5]
    assert msg.header.stamp.to_ns() == 5
    assert guard.velocity_array(keys.arm_velocity_commands, payload, ["a", "b", "c"]) is None  # one per joint
    too_fast = encode_float64_multi_array(Float64MultiArray([0.5, 2.5]))
    assert guard.velocity_array(keys.arm_velocity_commands, too_fast, ["a", "b"]) is None
    assert guard.velocity_array(keys.arm_joint_states, payload, ["a", "b"]) is None  # not this topic's key
    assert guard.velocity_array(keys.arm_velocity_commands, b"\x00\x01\x00\x00\x05", ["a", "b"]) is None
    assert dict(guard.rejections) == {"no_velocity": 1, "out_of_range": 1, "foreign_key": 1, "malformed": 1}


# --- live, with zenoh-ros2-sdk as the ROS side ------------------------------------------------------------------

DOMAIN = 42
INTR = Intrinsics.centred(260.0, 200, 150)
DT = 0.1  # s: the camera moves by twist × DT between frames
T_REF = pose(so3_exp([np.pi, 0.0, 0.0]), [0.0, 0.0, 0.5])  # 0.5 m above the plane z = 0, looking down


@pytest.fixture(scope="module")
def ros_side() -> Iterator[int]:
    """zenoh-ros2-sdk's shared session, listening on a loopback port for ddvs to connect to; message definitions
    from the ROS wheels' share/ directory (the SDK would otherwise fetch them from the network). One per module: the
    SDK's message registry outlives its session and would not register the types again in a second one."""
    from zenoh_ros2_sdk import ZenohSession, get_registry

    get_registry(str(Path(sys.prefix) / "share"))
    port = free_port()
    os.environ["ZENOH_CONFIG_OVERRIDE"] = f'listen/endpoints=["tcp/127.0.0.1:{port}"];connect/endpoints=[]'
    try:
        ZenohSession.get_instance("127.0.0.1", port)
        yield port
    finally:
        del os.environ["ZENOH_CONFIG_OVERRIDE"]
        if ZenohSession._instance is not None:
            ZenohSession._instance.close()


def _texture() -> np.ndarray:
    """Smoothed seeded noise, 40–215 grey levels: textured everywhere, no period (no ambiguous match)."""
    import cv2

    noise = cv2.GaussianBlur(np.random.default_rng(18).random((512, 512)).astype(np.float32), (0, 0), 3.0)
    return (40.0 + 175.0 * (noise - noise.min()) / (noise.max() - noise.min())).astype(np.float32)


def _rclpy_frame(image: np.ndarray, stamp_ns: int) -> tuple[bytes, bytes]:
    """Image (mono8) and CameraInfo as a ROS camera driver sends them, serialised by rclpy."""
    img = RosImage()
    img.header.stamp.sec, img.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    img.header.frame_id = "camera_optical_frame"
    img.height, img.width, img.encoding, img.step = INTR.height, INTR.width, "mono8", INTR.width
    img.data = np.clip(np.rint(image), 0, 255).astype(np.uint8).tobytes()
    info = RosCameraInfo()
    info.header = img.header
    info.height, info.width, info.distortion_model = INTR.height, INTR.width, "plumb_bob"
    info.d, info.k = [0.0] * 5, INTR.K.reshape(-1).tolist()
    info.r = np.eye(3).reshape(-1).tolist()
    info.p = np.hstack([INTR.K, np.zeros((3, 1))]).reshape(-1).tolist()
    return bytes(serialize_message(img)), bytes(serialize_message(info))


class RosPeer:
    """The ROS side: SDK publishers of /image_raw and /camera_info (putting rclpy's bytes with the SDK's rmw
    attachment), the SDK subscriber of the twist topic, raw twist payloads for rclpy, Trigger calls."""

    def __init__(self, port: int) -> None:
        from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber, ZenohSession

        common = {"router_port": port, "domain_id": DOMAIN, "node_name": "camera_driver"}
        self.image = ROS2Publisher("/image_raw", "sensor_msgs/msg/Image", qos=SENSOR_DATA_QOS.encode(),
                                   type_hash=TYPE_HASHES["sensor_msgs/msg/Image"], **common)
        self.info = ROS2Publisher("/camera_info", "sensor_msgs/msg/CameraInfo", qos=SENSOR_DATA_QOS.encode(),
                                  type_hash=TYPE_HASHES["sensor_msgs/msg/CameraInfo"], **common)
        self.sdk_twists: list[object] = []
        self.twist_sub = ROS2Subscriber("/servo_node/delta_twist_cmds", "geometry_msgs/msg/TwistStamped",
                                        callback=self.sdk_twists.append,
                                        type_hash=TYPE_HASHES["geometry_msgs/msg/TwistStamped"],
                                        router_port=port, domain_id=DOMAIN, node_name="servo_node")
        self.session = ZenohSession.get_instance().session
        self._lock = threading.Condition()
        self.raw_twists: list[tuple[bytes, bytes | None]] = []
        self._raw = self.session.declare_subscriber(self.twist_sub.keyexpr, self._on_twist)
        self.port = port
        self._seq = 0

    def _on_twist(self, sample: zenoh.Sample) -> None:
        with self._lock:
            attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
            self.raw_twists.append((sample.payload.to_bytes(), attachment))
            self._lock.notify_all()

    def publish(self, image: np.ndarray, stamp_ns: int) -> None:
        from zenoh_ros2_sdk.attachment import Attachment

        img, info = _rclpy_frame(image, stamp_ns)
        for publisher, payload in ((self.info, info), (self.image, img)):
            self._seq += 1
            publisher.pub.put(payload, attachment=Attachment(self._seq, time.time_ns(),
                                                              publisher.publisher_gid).to_bytes())

    def twist_for(self, stamp_ns: int, timeout: float = 20.0) -> RosTwistStamped:
        """The first twist (decoded by rclpy) stamped `stamp_ns`."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while True:
                for payload, attachment in self.raw_twists:
                    msg = deserialize_message(payload, RosTwistStamped)
                    stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                    if stamp == stamp_ns:
                        assert attachment is not None and RmwAttachment.decode(attachment).gid
                        return msg
                remaining = deadline - time.monotonic()
                assert remaining > 0, f"no twist for the frame stamped {stamp_ns} within {timeout} s"
                self._lock.wait(remaining)

    def call(self, service: str) -> tuple[bool, str]:
        from zenoh_ros2_sdk import ROS2ServiceClient

        client = ROS2ServiceClient(f"/ddvs_servo/{service}", "std_srvs/srv/Trigger", request_definition="",
                                   response_definition="bool success\nstring message",
                                   type_hash=TYPE_HASHES["std_srvs/srv/Trigger"], router_port=self.port,
                                   domain_id=DOMAIN, timeout=20.0)
        try:
            response = client.call()
        finally:
            client.close()
        assert response is not None, f"no answer from /ddvs_servo/{service}"
        return bool(response.success), str(response.message)

    def close(self) -> None:
        self._raw.undeclare()
        for endpoint in (self.twist_sub, self.image, self.info):
            endpoint.close()


def _serve(tmp_path: Path, port: int, transport: str = "raw") -> subprocess.Popen:
    config = tmp_path / "serve.json"
    config.write_text(json.dumps({"state_dir": str(tmp_path / "state"), "registration": {"template_size": [120, 90]},
                                  "camera": {"transport": transport},
                                  "control": {"gains": 2.0, "max_linear": 0.5, "max_angular": 1.0}}))
    env = {k: v for k, v in os.environ.items() if not k.startswith(("DDVS_", "ZENOH_"))}
    return subprocess.Popen([sys.executable, "-X", "faulthandler", "-m", "ddvs.cli", "serve", "--config", str(config),
                             "--fresh", "--ros-domain-id", str(DOMAIN), "--listen", "tcp/127.0.0.1:0",
                             "--connect", f"tcp/127.0.0.1:{port}"],
                            stderr=subprocess.PIPE, text=True, env=env)


def _wait_for_graph(port: int, timeout: float = 60.0) -> list[tuple[str, list[str]]]:
    from zenoh_ros2_sdk import get_service_names_and_types

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        services = get_service_names_and_types(domain_id=DOMAIN, router_port=port)
        if len([s for s, _ in services if s.startswith("/ddvs_servo/")]) == 4:
            return services
        time.sleep(0.3)
    raise AssertionError(f"ddvs_servo's services did not appear in the graph within {timeout} s")


def test_serve_in_ros2_mode_servoes_a_camera_driven_by_a_ros_peer(ros_side: int, tmp_path: Path) -> None:
    from zenoh_ros2_sdk import get_topic_info, get_topic_names_and_types

    from sim.freeflyer import FreeFlyer
    from sim.surfaces import Plane

    port = ros_side
    service = _serve(tmp_path, port)
    peer = RosPeer(port)
    try:
        services = _wait_for_graph(port)
        assert ("/ddvs_servo/start", ["std_srvs/srv/Trigger"]) in services
        topics = dict(get_topic_names_and_types(domain_id=DOMAIN, router_port=port))
        assert topics["/image_raw"] == ["sensor_msgs/msg/Image"]
        assert topics["/servo_node/delta_twist_cmds"] == ["geometry_msgs/msg/TwistStamped"]
        assert topics["/ddvs/reference"] == ["sensor_msgs/msg/Image"]
        info = get_topic_info("/servo_node/delta_twist_cmds", domain_id=DOMAIN, router_port=port, verbose=True)
        assert [(p.node_name, p.node_namespace, p.qos) for p in info.publishers] == [("ddvs_servo", "/",
                                                                                     "::,1:,:,:,,")]
        tokens = [str(r.ok.key_expr) for r in peer.session.liveliness().get(f"@ros2_lv/{DOMAIN}/**", timeout=2.0)
                  if r.ok is not None]
        ours = [parse_token(t) for t in tokens if "/ddvs_servo" in t]
        assert {e.kind for e in ours} == {"NN", "MS", "MP", "SS"} and len({e.zid for e in ours}) == 1
        assert {e.topic for e in ours if e.kind == "MS"} == {"/image_raw", "/camera_info"}

        plane = Plane(pose(np.eye(3), [0.0, 0.0, 0.0]), (0.6, 0.6))
        flyer = FreeFlyer(plane, INTR, T_REF, T_REF, DT, texture=_texture())
        assert peer.call("set_reference") == (True, "the next camera frame becomes the reference")
        for _ in range(20):  # a camera streams; the reference is the first frame the service has intrinsics for
            stamp = time.time_ns()  # (the first camera info may reach it after the first image, or not at all:
            peer.publish(flyer.observe().image, stamp)  # Zenoh drops a put made before the subscriber is known)
            peer.twist_for(stamp)  # every frame is answered (a zero twist until the servo starts)
            ok, message = peer.call("start")
            if ok:
                break
        assert ok and "SERVOING" in message, message
        flyer.T_world_cam = T_REF @ pose(so3_exp([0.01, -0.015, 0.025]), [0.01, -0.008, 0.005])
        errors = []
        for _ in range(150):
            stamp = time.time_ns()
            peer.publish(flyer.observe().image, stamp)
            twist = peer.twist_for(stamp)
            assert twist.header.frame_id == "camera_optical_frame"
            t, w = twist.twist.linear, twist.twist.angular
            flyer.move([t.x, t.y, t.z, w.x, w.y, w.z])
            E = pose_inv(T_REF) @ flyer.T_world_cam  # metres + radians: 1e-3 is 1 mm or 0.06°
            errors.append(float(np.linalg.norm(E[:3, 3]) + np.linalg.norm(so3_log(E[:3, :3]))))
            if np.linalg.norm([t.x, t.y, t.z, w.x, w.y, w.z]) == 0.0 and errors[-1] < 1e-3:
                break  # CONVERGED: the service commands zero
        print(f"converged in {len(errors)} frames: pose error {errors[0]:.4f} → {errors[-1]:.2e} (m + rad); "
              f"{len(peer.sdk_twists)} twists received by the SDK, {len(peer.raw_twists)} decoded by rclpy")
        assert errors[-1] < 1e-3, f"pose error {errors[-1]:.2e} after {len(errors)} frames (from {errors[0]:.3f})"
        assert len(peer.sdk_twists) >= len(errors)  # the SDK's own subscriber got every twist too
        ok, message = peer.call("stop")
        assert ok and "STOPPED" in message
    finally:
        peer.close()
        if service.poll() is None:
            service.send_signal(signal.SIGTERM)
        code = service.wait(timeout=30)
        stderr = service.stderr.read() if service.stderr else ""
        print(stderr[-6000:])  # shown when the test fails
    assert code == 0


def test_bridge_in_ros2_mode_reads_joint_states_and_commands_ros2_control(ros_side: int,
                                                                         caplog: pytest.LogCaptureFixture) -> None:
    """The bridge reads rclpy's JointState on /joint_states and a TwistStamped on the twist topic, and publishes
    Float64MultiArray velocities in its configured joint order on /forward_velocity_controller/commands. It logs
    the ROS publishers of its inputs, and warns about one of another type hash (whose samples cannot arrive)."""
    from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber
    from zenoh_ros2_sdk.attachment import Attachment

    from clients.bridge import load_bridge
    from clients.bridge_node import BridgeNode

    port = ros_side
    bridge = load_bridge(Path(__file__).resolve().parents[1] / "configs" / "arm" / "ur5_bridge.json")
    names = list(bridge.joint_names)
    common = {"router_port": port, "domain_id": DOMAIN}
    joints = ROS2Publisher("/joint_states", "sensor_msgs/msg/JointState", node_name="joint_state_broadcaster",
                           type_hash=TYPE_HASHES["sensor_msgs/msg/JointState"], **common)
    twist = ROS2Publisher("/servo_node/delta_twist_cmds", "geometry_msgs/msg/TwistStamped", node_name="servo",
                          type_hash=TYPE_HASHES["geometry_msgs/msg/TwistStamped"], **common)
    other_hash = ROS2Publisher("/joint_states", "sensor_msgs/msg/JointState", node_name="other_distro",
                               type_hash="RIHS01_" + "0" * 64, **common)
    caplog.set_level("INFO", logger="ddvs.endpoints")
    received: list[object] = []
    commands = ROS2Subscriber("/forward_velocity_controller/commands", "std_msgs/msg/Float64MultiArray",
                              callback=received.append, node_name="forward_velocity_controller",
                              type_hash=TYPE_HASHES["std_msgs/msg/Float64MultiArray"], **common)
    raw: list[bytes] = []
    peer_session = joints.session_mgr.session
    raw_sub = peer_session.declare_subscriber(commands.keyexpr, lambda s: raw.append(s.payload.to_bytes()))
    bridge_port = free_port()  # `ddvs ros` below meets both peers (on a ROS machine: through rmw_zenohd)
    bridge_zenoh = SessionConfig(connect=[f"tcp/127.0.0.1:{port}"], listen=[f"tcp/127.0.0.1:{bridge_port}"])
    with open_session(bridge_zenoh) as session:
        node = BridgeNode(bridge, session, Keys("ddvs", "arm0", RosSettings(domain_id=DOMAIN)), rate=50.0)
        stop = threading.Event()
        thread = threading.Thread(target=node.run, args=(stop,), daemon=True)
        thread.start()
        try:
            time.sleep(1.0)  # discovery
            publishers = {(e.topic, e.dds_type, e.node.name) for e in discover(session, DOMAIN) if e.kind == "MP"}
            assert ("/joint_states", "sensor_msgs::msg::dds_::JointState_", "joint_state_broadcaster") in publishers
            assert ("/forward_velocity_controller/commands", "std_msgs::msg::dds_::Float64MultiArray_",
                    "ddvs_bridge") in publishers
            env = {k: v for k, v in os.environ.items() if not k.startswith(("DDVS_", "ZENOH_"))}
            graph = subprocess.run([sys.executable, "-m", "ddvs.cli", "ros", "--ros-domain-id", str(DOMAIN), "-v",
                                    "--connect", f"tcp/127.0.0.1:{port},tcp/127.0.0.1:{bridge_port}"],
                                   capture_output=True, text=True,
                                   timeout=120, env=env, check=True).stdout.splitlines()
            for line in ("  /ddvs_bridge", "  /joint_state_broadcaster",
                         "  /joint_states [sensor_msgs/msg/JointState] publishers 2, subscriptions 1",  # 2 hashes
                         "  /forward_velocity_controller/commands [std_msgs/msg/Float64MultiArray] publishers 1, "
                         "subscriptions 1",
                         "    MS /ddvs_bridge qos ::,1:,:,:,, " + TYPE_HASHES["sensor_msgs/msg/JointState"]):
                assert line in graph, graph
            q = [0.0, -1.2, 1.4, -1.8, -1.57, 0.3]
            for seq in range(1, 40):
                now = time.time_ns()
                js = RosJointState(name=[*reversed(names), "gripper"], position=[*reversed(q), 0.01])
                js.header.stamp.sec, js.header.stamp.nanosec = divmod(now, 1_000_000_000)
                tw = RosTwistStamped()
                tw.header.stamp = js.header.stamp
                tw.header.frame_id = "camera_optical_frame"
                tw.twist.linear.x, tw.twist.angular.z = 0.02, 0.05
                for publisher, msg in ((joints, js), (twist, tw)):
                    publisher.pub.put(bytes(serialize_message(msg)),
                                      attachment=Attachment(seq, now, publisher.publisher_gid).to_bytes())
                time.sleep(0.02)
            time.sleep(0.3)
        finally:
            stop.set()
            thread.join(5)
            node.close()
    deadline = time.monotonic() + 5.0  # the SDK's subscriber hands samples to its callback on a thread of its own
    while len(received) < len(raw) and time.monotonic() < deadline:
        time.sleep(0.05)
    raw_sub.undeclare()
    for endpoint in (joints, twist, commands, other_hash):
        endpoint.close()
    seen = {(r.levelname, r.__dict__["fields"]["topic"], r.__dict__["fields"]["node"])
            for r in caplog.records if r.name == "ddvs.endpoints"}
    assert {("INFO", "/joint_states", "/joint_state_broadcaster"), ("INFO", "/servo_node/delta_twist_cmds", "/servo"),
            ("WARNING", "/joint_states", "/other_distro")} <= seen, seen
    decoded = [deserialize_message(p, RosFloat64MultiArray) for p in raw]
    moving = [np.array(m.data) for m in decoded if np.any(np.array(m.data))]
    assert moving and all(v.size == len(names) for v in moving), [m.data for m in decoded[:3]]
    assert len(received) == len(raw) and node.guard.accepted > 0
    expected = bridge.joint_velocities([0.02, 0, 0, 0, 0, 0.05], q)  # q in the configured order: reordered by name
    np.testing.assert_allclose(moving[-1], expected, rtol=1e-9, atol=1e-12)


@pytest.mark.slow
def test_full_servo_run_with_every_node_in_ros2_mode_converges(tmp_path: Path) -> None:
    """`ddvs sim arm`, `ddvs serve` and `ddvs bridge`, all with `--ros-domain-id`: images and camera info on
    /image_raw and /camera_info, the twist on /servo_node/delta_twist_cmds, joint states on /joint_states, velocity
    commands as Float64MultiArray on /forward_velocity_controller/commands (realtime clock: those carry no stamp);
    the arm servoes from the paper's displacement to CONVERGED."""
    from orchestration.arm_run import ArmRunSettings, run_arm

    settings = ArmRunSettings(out_dir=tmp_path / "run", template=(70, 70), clock="realtime", fps=30.0,
                              time_limit=420.0, robot="ros_arm", ros_domain_id=DOMAIN + 1)
    result = run_arm(settings)
    print({"converged": result.converged, "reason": result.reason, "images": result.images,
           "wall_s": round(result.wall_s, 1)})
    assert result.converged, f"{result.reason}; logs in {settings.out_dir / 'logs'}"


def test_ros_options_from_the_command_line_and_their_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    import argparse

    from ddvs_service.protocol.ros_cli import add_ros_arguments, ros_settings_from_args

    parser = argparse.ArgumentParser()
    add_ros_arguments(parser)
    monkeypatch.delenv("DDVS_ROS_DOMAIN_ID", raising=False)
    base = RosSettings(namespace="/cell", topics={"camera_info": "/cam/info"})
    args = parser.parse_args(["--ros-domain-id", "5", "--ros-topic", "camera_image:=/cam/image_raw"])
    assert ros_settings_from_args(args, base) == RosSettings(
        domain_id=5, namespace="/cell", topics={"camera_info": "/cam/info", "camera_image": "/cam/image_raw"})
    assert not ros_settings_from_args(parser.parse_args([])).enabled
    monkeypatch.setenv("DDVS_ROS_DOMAIN_ID", "7")
    assert ros_settings_from_args(parser.parse_args([])).domain_id == 7
    for argv, message in ((["--ros-domain-id", "300"], "less than or equal to 232"),
                          (["--ros-topic", "camera"], "expected ROW:=NAME"),
                          (["--ros-topic", "servo_status:=/status"], "expected one of camera_image"),
                          (["--ros-topic", "camera_image:=/9cam"], "not a fully qualified ROS name"),
                          (["--ros-namespace", "cell"], "namespace 'cell'")):
        with pytest.raises(SystemExit, match=message):
            ros_settings_from_args(parser.parse_args(argv))


def test_serve_in_ros2_mode_reads_image_transports_compressed_topic(ros_side: int, tmp_path: Path) -> None:
    """`camera.transport` compressed in ROS 2 mode: the service subscribes to /image_raw/compressed with
    sensor_msgs/msg/CompressedImage's type hash; a ROS peer's rclpy-serialised JPEG q80 frames (image_transport's
    long `format`) with their camera info are answered, the reference carries the peer's header, and the servo
    moves the camera towards the reference."""
    import cv2
    from zenoh_ros2_sdk import ROS2Publisher, get_topic_names_and_types
    from zenoh_ros2_sdk.attachment import Attachment

    from ddvs_service.protocol import decode_image
    from sim.freeflyer import FreeFlyer
    from sim.surfaces import Plane

    port = ros_side
    service = _serve(tmp_path, port, "compressed")
    peer = RosPeer(port)
    compressed = ROS2Publisher("/image_raw/compressed", "sensor_msgs/msg/CompressedImage",
                               qos=SENSOR_DATA_QOS.encode(), type_hash=TYPE_HASHES["sensor_msgs/msg/CompressedImage"],
                               router_port=port, domain_id=DOMAIN, node_name="camera_driver")
    references: list[bytes] = []
    reference_sub = peer.session.declare_subscriber(
        f"{DOMAIN}/ddvs/reference/sensor_msgs::msg::dds_::Image_/{TYPE_HASHES['sensor_msgs/msg/Image']}",
        lambda sample: references.append(sample.payload.to_bytes()))
    sequence = 0

    def publish(image: np.ndarray, stamp_ns: int) -> RosTwistStamped:
        nonlocal sequence
        _, info = _rclpy_frame(image, stamp_ns)
        msg = RosCompressedImage()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        msg.header.frame_id = "camera_optical_frame"
        msg.format = "mono8; jpeg compressed mono8"
        pixels = np.clip(np.rint(image), 0, 255).astype(np.uint8)
        msg.data = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, 80])[1].tobytes()
        for publisher, payload in ((peer.info, info), (compressed, bytes(serialize_message(msg)))):
            sequence += 1
            publisher.pub.put(payload, attachment=Attachment(sequence, time.time_ns(),
                                                             publisher.publisher_gid).to_bytes())
        return peer.twist_for(stamp_ns)

    try:
        _wait_for_graph(port)
        topics = dict(get_topic_names_and_types(domain_id=DOMAIN, router_port=port))
        assert topics["/image_raw/compressed"] == ["sensor_msgs/msg/CompressedImage"]
        plane = Plane(pose(np.eye(3), [0.0, 0.0, 0.0]), (0.6, 0.6))
        flyer = FreeFlyer(plane, INTR, T_REF, T_REF, DT, texture=_texture())
        assert peer.call("set_reference") == (True, "the next camera frame becomes the reference")
        for _ in range(20):  # as in the raw test: the reference is the first frame the service has intrinsics for
            stamp = time.time_ns()
            publish(flyer.observe().image, stamp)
            ok, message = peer.call("start")
            if ok:
                break
        assert ok and "SERVOING" in message, message
        deadline = time.monotonic() + 10.0
        while not references:
            assert time.monotonic() < deadline, "no reference on /ddvs/reference"
            time.sleep(0.05)
        reference = decode_image(references[-1])
        assert reference.header.frame_id == "camera_optical_frame" and reference.encoding == "mono8"
        flyer.T_world_cam = T_REF @ pose(so3_exp([0.0, 0.0, 0.02]), [0.01, -0.008, 0.0])
        errors = []
        for _ in range(15):
            twist = publish(flyer.observe().image, time.time_ns())
            assert twist.header.frame_id == "camera_optical_frame"
            t, w = twist.twist.linear, twist.twist.angular
            flyer.move([t.x, t.y, t.z, w.x, w.y, w.z])
            E = pose_inv(T_REF) @ flyer.T_world_cam
            errors.append(float(np.linalg.norm(E[:3, 3]) + np.linalg.norm(so3_log(E[:3, :3]))))
        print(f"compressed over ROS 2: pose error {errors[0]:.4f} → {errors[-1]:.4f} (m + rad) in 15 frames")
        assert errors[-1] < 0.3 * errors[0]
    finally:
        reference_sub.undeclare()
        compressed.close()
        peer.close()
        if service.poll() is None:
            service.send_signal(signal.SIGTERM)
        code = service.wait(timeout=30)
        stderr = service.stderr.read() if service.stderr else ""
        print(stderr[-6000:])
    assert code == 0
