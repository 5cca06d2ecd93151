"""ROS 2 mode under the secure set-up (docs/security.md, "ROS 2 mode"): `ddvs security init --ros-domain-id` writes
rules for the rmw_zenoh keys, the service node's Trigger services and the ROS graph; the real `ddvs router` enforces
them over mutual TLS on loopback.

- Every role's ddvs node, declared as the programs do (`Endpoints` with their node names), does its work in ROS 2
  mode — camera frames to the service, twists to the bridge, ros2_control commands to the arm, the operator's
  Trigger call answered, the whole graph seen — and the audit counts no denial.
- The intruder roles of the plain-mode tests, in ROS 2 mode: only the service sends twists, only the bridge commands
  the arm, only the operator calls the Trigger services and only the service serves them, and no role can show a
  node of another role in the graph; each attempt is counted under its identity.
- The real `ddvs serve --ros-domain-id` under rules made without ROS 2 refuses to start and says which command makes
  them (it used to start deaf); under rules with it, it servoes: the Trigger services answer the operator and the
  camera's frames come back to the bridge as twists, with no denial in the audit.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest
import zenoh
from conftest import free_port
from test_security import Inbox
from test_security_audit import audit_lines, ddvs_router, newest_report, open_roles
from test_security_fleet import send_frame
from test_service_node import Service, scene, service_config, shifted

from ddvs_service.protocol import Header, Keys, SessionConfig, Time, decode_twist_stamped, encode_image
from ddvs_service.protocol.audit import audit_key
from ddvs_service.protocol.endpoints import Endpoints, read_trigger_request, reply_trigger
from ddvs_service.protocol.rmw import RmwAttachment, RmwPublisherIdentity, rmw_zenoh_key
from ddvs_service.protocol.ros import decode_trigger_response, encode_trigger_request, image_from_array
from ddvs_service.protocol.ros_graph import (
    ARM_SIM_NODE,
    BRIDGE_NODE,
    CAMERA_NODE,
    SERVO_NODE,
    TRIGGER,
    GraphEntity,
    GraphNode,
    discover,
)
from ddvs_service.protocol.ros_settings import RosSettings
from ddvs_service.service.config import ServiceConfig

DOMAIN = 17
KEYS = Keys("ddvs", "rc", RosSettings(domain_id=DOMAIN))
START = rmw_zenoh_key(DOMAIN, f"/{SERVO_NODE}/start", TRIGGER)
START_LIMIT_S = 120.0


def init(out: Path, endpoint: str, *extra: str) -> None:
    subprocess.run([sys.executable, "-m", "ddvs.cli", "security", "init", "--robot", KEYS.robot, "--router", endpoint,
                    *extra, str(out)], check=True, capture_output=True)


def call_trigger(session: zenoh.Session, key: str = START, timeout: float = 2.0) -> tuple[bool, str] | None:
    """A ROS Trigger call as rmw_zenoh's client makes it (request CDR + attachment); None when nothing answers."""
    attachment = RmwAttachment(1, time.time_ns(), RmwPublisherIdentity().gid).encode()
    for reply in session.get(key, payload=encode_trigger_request(), attachment=attachment, timeout=timeout):
        if reply.ok is not None:
            return decode_trigger_response(reply.ok.payload.to_bytes())
    return None


class TriggerServer:
    """A Trigger service as the service node declares it, answering `(True, "started")`, recording each call."""

    def __init__(self, ends: Endpoints) -> None:
        self.calls = 0
        ends.trigger_service("start", self._on_query)

    def _on_query(self, query: zenoh.Query) -> None:
        self.calls += 1
        reply_trigger(query, read_trigger_request(query), True, "started")


def frame(n: int) -> bytes:
    image = np.full((8, 8), n % 256, np.uint8)
    return encode_image(image_from_array(image, "mono8", Header(Time.from_ns(n), "cam")))


@pytest.mark.slow
def test_ros2_mode_works_for_every_role_and_the_intruder_roles_get_nothing(tmp_path: Path) -> None:
    endpoint = f"tls/localhost:{free_port()}"
    out = tmp_path / "secure"
    init(out, endpoint, "--ros-domain-id", str(DOMAIN))
    log = tmp_path / "router.log"
    with ExitStack() as stack, ddvs_router(out, endpoint, log):
        names = ("service", "camera", "arm", "bridge", "operator", "observer")
        roles = ("service", "plant", "plant", "bridge", "operator", "observer")
        sessions = dict(zip(names, open_roles(stack, out, *roles), strict=True))
        ends = {name: Endpoints(sessions[name], KEYS, node) for name, node in (
            ("service", SERVO_NODE), ("camera", CAMERA_NODE), ("arm", ARM_SIM_NODE), ("bridge", BRIDGE_NODE))}
        for endpoints in ends.values():
            stack.callback(endpoints.close)
        frames: list[bytes] = []
        twists: list[bytes] = []
        commands: list[bytes] = []

        def collect(into: list[bytes]) -> Callable[[zenoh.Sample], None]:
            return lambda sample: into.append(sample.payload.to_bytes())

        ends["service"].subscriber("camera_image", collect(frames))
        twist_out = ends["service"].publisher("servo_twist")
        server = TriggerServer(ends["service"])
        camera_out = ends["camera"].publisher("camera_image")
        ends["bridge"].subscriber("servo_twist", collect(twists))
        arm_out = ends["bridge"].publisher("arm_velocity_commands")
        ends["arm"].subscriber("arm_velocity_commands", collect(commands))
        watched = Inbox(sessions["observer"], KEYS.servo_twist)  # observers read the twists too
        reports = Inbox(sessions["observer"], audit_key(KEYS.base))
        time.sleep(0.5)

        # every role does its work in ROS 2 mode: no denial
        def delivered(send: Callable[[], None], into: list[bytes], timeout: float = 3.0) -> bool:
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline:
                send()
                time.sleep(0.05)
                if into:
                    return True
            return False

        assert delivered(lambda: camera_out.put(frame(1)), frames)
        assert delivered(lambda: twist_out.put(b"twist"), twists) and watched.wait_for(b"twist")
        assert delivered(lambda: arm_out.put(b"qd"), commands)
        assert call_trigger(sessions["operator"]) == (True, "started") and server.calls == 1
        nodes = {(e.node.name, e.kind) for e in discover(sessions["observer"], DOMAIN)}
        assert {(SERVO_NODE, "SS"), (SERVO_NODE, "MP"), (SERVO_NODE, "MS"), (CAMERA_NODE, "MP"),
                (BRIDGE_NODE, "MS"), (BRIDGE_NODE, "MP"), (ARM_SIM_NODE, "MS")} <= nodes, nodes
        quiet = newest_report(reports, lambda r: False, timeout=1.5)
        assert quiet["denied"] == {} and quiet["no_role"] == {}, quiet
        assert audit_lines(log) == []

        # the intruder roles, as in plain mode
        for name in ("bridge", "operator", "camera"):
            sessions[name].put(KEYS.servo_twist, f"forged by the {name}".encode())
        for name in ("service", "operator", "observer"):
            sessions[name].put(KEYS.arm_velocity_commands, b"forged qd")
        for name in ("camera", "bridge", "observer"):
            assert call_trigger(sessions[name], timeout=0.5) is None, f"the {name} called the Trigger service"
        rogue_calls: list[bytes] = []
        rogue = sessions["camera"].declare_queryable(START, lambda q: rogue_calls.append(b"call"), complete=True)
        stack.callback(rogue.undeclare)
        forged_node = GraphNode(DOMAIN, "/", SERVO_NODE)  # the observer posing as the service node in the graph
        forged = GraphEntity(str(sessions["observer"].info.zid()), 0, 9, "MP", forged_node, "/forged",
                             "std_msgs::msg::dds_::String_", "RIHS01_0", "::,1:,:,:,,")
        token = sessions["observer"].liveliness().declare_token(forged.token())
        stack.callback(token.undeclare)
        time.sleep(0.6)
        assert call_trigger(sessions["operator"]) == (True, "started") and server.calls == 2 and rogue_calls == []
        assert not [p for p in watched.payloads if p.startswith(b"forged")]
        assert [p for p in twists if p.startswith(b"forged")] == [b"forged by the bridge"]  # its own, locally
        assert b"forged qd" not in commands
        assert not any(e.topic == "/forged" for e in discover(sessions["operator"], DOMAIN))
        intruders = {f"{role}@{KEYS.base}" for role in ("bridge", "operator", "plant", "service", "observer")}
        report = newest_report(reports, lambda r: set(r["denied"]) == intruders)
        assert set(report["denied"]) == intruders, report
        denied = {(e["identity"].split("@")[0], e["action"]) for e in audit_lines(log) if e["msg"] == "access denied"}
        assert {("plant", "Put"), ("plant", "Declare Queryable"), ("observer", "Liveliness Token")} <= denied, denied


@pytest.mark.slow
def test_ddvs_serve_in_ros2_mode_refuses_rules_without_it_and_servoes_under_rules_with_it(tmp_path: Path) -> None:
    endpoint = f"tls/localhost:{free_port()}"
    plain, ros = tmp_path / "plain", tmp_path / "ros"
    init(plain, endpoint)

    def config(out: Path) -> ServiceConfig:
        return service_config(0, tmp_path / "state").model_copy(update={"robot": KEYS.robot, "zenoh": SessionConfig(
            mode="client", connect=[endpoint], zenoh_config=out / "service-mtls.json5")})

    deaf = Service(config(plain), tmp_path, "--ros-domain-id", str(DOMAIN), "--no-warmup")
    deaf.proc.wait(timeout=120)
    code, stderr = deaf.stop()
    assert code == 2, stderr[-4000:]
    assert "ROS 2 mode (domain 17, namespace '/') of robot 'ddvs/rc' is not covered" in stderr, stderr[-4000:]
    assert "ddvs security init --robot rc --prefix ddvs --ros-domain-id 17" in stderr

    init(ros, endpoint, "--ros-domain-id", str(DOMAIN))
    log = tmp_path / "router.log"
    with ExitStack() as stack:
        stack.enter_context(ddvs_router(ros, endpoint, log))
        operator, camera, bridge = open_roles(stack, ros, "operator", "plant", "bridge")
        camera_ends, bridge_ends = Endpoints(camera, KEYS, CAMERA_NODE), Endpoints(bridge, KEYS, BRIDGE_NODE)
        stack.callback(camera_ends.close)
        stack.callback(bridge_ends.close)
        frames = camera_ends.publisher("camera_image")
        twists: list[bytes] = []
        bridge_ends.subscriber("servo_twist", lambda sample: twists.append(sample.payload.to_bytes()))
        statuses = Inbox(operator, KEYS.servo_status)
        service = Service(config(ros), tmp_path, "--ros-domain-id", str(DOMAIN))
        stack.callback(service.stop)
        set_reference = rmw_zenoh_key(DOMAIN, f"/{SERVO_NODE}/set_reference", TRIGGER)
        deadline = time.monotonic() + START_LIMIT_S
        while (answer := call_trigger(operator, set_reference, timeout=1.0)) is None:
            assert service.proc.poll() is None, service.stop()[1][-4000:]
            assert time.monotonic() < deadline, "the service's Trigger services never answered the operator"
        assert answer == (True, "the next camera frame becomes the reference"), answer

        def send(image: np.ndarray, n: int) -> dict[str, object]:  # the twist goes to the bridge
            return send_frame(frames.put, statuses.payloads, twists, image, n)

        assert send(scene(), 1)["state"] == "READY"
        started = call_trigger(operator, rmw_zenoh_key(DOMAIN, f"/{SERVO_NODE}/start", TRIGGER), timeout=5.0)
        assert started is not None and started[0] and "SERVOING" in started[1], started
        states = [send(shifted(scene(), 3.0, -2.0, 1.0), n)["state"] for n in range(2, 5)]
        assert states == ["SERVOING"] * 3, states
        twist = decode_twist_stamped(twists[-1]).vector
        assert np.all(np.isfinite(twist)) and np.linalg.norm(twist) > 0.0, twist
        code, stderr = service.stop()
        assert code == 0, stderr[-4000:]
    assert [e for e in audit_lines(log) if e["msg"] == "access denied"] == []
