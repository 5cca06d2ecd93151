"""The real, unchanged `ddvs serve` and `ddvs sim arm` behind the secured hub: TLS clients of a router with mutual TLS
and the generated deny-by-default rules. The operator sets the reference and reads the state; an observer (and a plant
identity) can neither set the reference nor change the configuration, and the service's state shows that nothing
changed. Only the bridge's joint velocities move the simulated arm."""

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
import zenoh
from conftest import free_port
from test_security import KEYS, SCOPE, SCRIPT, Inbox, _zenoh_config

from ddvs_service.protocol import (
    Command,
    Header,
    JointState,
    Reply,
    Time,
    decode_joint_state,
    dump,
    encode_image,
    encode_joint_state,
    image_from_array,
)
from ddvs_service.protocol.security import (
    ROLES,
    TlsFiles,
    certificate_identities,
    client_config,
    render_json5,
    router_config,
)

REPO = Path(__file__).resolve().parents[1]
W, H = 320, 240


def texture() -> np.ndarray:
    rng = np.random.default_rng(7)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (H, W)).astype(np.float32), (0, 0), 3.0)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def command(session: zenoh.Session, timeout: float = 2.0, **kwargs: object) -> Reply | None:
    """The service's reply to one command, or None when no reply came (refused by the router)."""
    for reply in session.get(KEYS.servo_command, payload=dump(Command(**kwargs)), timeout=timeout):
        if reply.ok is not None:
            return Reply.model_validate_json(reply.ok.payload.to_bytes())
    return None


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("certs")
    subprocess.run(["bash", str(SCRIPT), str(directory), "--robot", KEYS.robot], check=True, capture_output=True)
    return directory


@pytest.mark.slow
def test_ddvs_serve_over_mtls_obeys_the_operator_only(certs: Path, tmp_path: Path) -> None:
    endpoint = f"tls/localhost:{free_port()}"
    router = zenoh.open(_zenoh_config(router_config(
        KEYS, certificate_identities(SCOPE), [endpoint], TlsFiles.for_role(certs, "router"),
        observers_read_frames=False)))
    sessions = [router]
    zenoh_file = tmp_path / "service.json5"
    zenoh_file.write_text(render_json5(client_config("service", [endpoint], TlsFiles.for_role(certs, "service")),
                                       "ddvs serve as the service role"))
    serve_file = tmp_path / "serve.json"
    serve_file.write_text(json.dumps({
        "robot": KEYS.robot,
        "zenoh": {"mode": "client", "connect": [endpoint], "zenoh_config": str(zenoh_file)},
        "state_dir": str(tmp_path / "state"),
        "intrinsics": {"fx": 420.0, "fy": 420.0, "cx": (W - 1) / 2, "cy": (H - 1) / 2, "width": W, "height": H},
        "registration": {"template_size": [100, 80]},
    }))
    env = {k: v for k, v in os.environ.items() if not k.startswith("DDVS_ZENOH_")}
    proc = subprocess.Popen([sys.executable, "-m", "ddvs.cli", "serve", "--config", str(serve_file)],
                            stderr=subprocess.PIPE, text=True, env=env)
    try:
        operator, observer, plant = (
            zenoh.open(_zenoh_config(client_config(role, [endpoint], TlsFiles.for_role(certs, role))))
            for role in ("operator", "observer", "plant"))
        sessions += [operator, observer, plant]
        deadline = time.monotonic() + 60.0
        while command(operator, timeout=1.0, op="get_state") is None:
            assert proc.poll() is None, f"ddvs serve exited: {proc.stderr.read() if proc.stderr else ''}"
            assert time.monotonic() < deadline, "ddvs serve did not answer the operator"
        gains = command(operator, op="get_config")
        assert gains is not None and gains.ok and gains.data is not None
        gains_before = gains.data["control"]["gains"]

        for intruder in (observer, plant):
            assert command(intruder, op="set_reference", source="next_frame") is None
            assert command(intruder, op="set_config", config={"control": {"gains": 0.9}}) is None
            assert command(intruder, op="get_state") is None
        state = command(operator, op="get_state")
        assert state is not None and state.data is not None
        assert state.data["state"] == "IDLE" and state.data["has_reference"] is False
        config = command(operator, op="get_config")
        assert config is not None and config.data is not None and config.data["control"]["gains"] == gains_before

        observed = Inbox(observer, KEYS.servo_status)
        frames_seen_by_observer = Inbox(observer, KEYS.camera_image)
        reply = command(operator, op="set_reference", source="next_frame")
        assert reply is not None and reply.ok, reply
        frame = encode_image(image_from_array(texture(), "mono8", Header(Time.now(), "camera")))
        deadline = time.monotonic() + 60.0
        while not any(json.loads(p).get("state") == "READY" for p in observed.payloads):
            assert time.monotonic() < deadline, "the plant's frame never became the reference"
            plant.put(KEYS.camera_image, frame)
            time.sleep(0.1)
        state = command(operator, op="get_state")
        assert state is not None and state.data is not None and state.data["has_reference"] is True
        assert frames_seen_by_observer.payloads == []  # configured: observers do not read frames
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=30)
        for session in reversed(sessions):
            session.close()
    assert code == 0


@pytest.mark.slow
def test_only_the_bridge_moves_the_real_arm_sim_over_mtls(certs: Path, tmp_path: Path) -> None:
    """`ddvs sim arm` (SAPIEN, realtime clock) as the plant client of the secured hub: joint velocities from the
    operator and the observer leave the arm still; the same commands from the bridge move it."""
    endpoint = f"tls/localhost:{free_port()}"
    router = zenoh.open(_zenoh_config(router_config(
        KEYS, certificate_identities(SCOPE), [endpoint], TlsFiles.for_role(certs, "router"))))
    sessions = [router]
    plant_file = tmp_path / "plant.json5"
    plant_file.write_text(render_json5(client_config("plant", [endpoint], TlsFiles.for_role(certs, "plant")),
                                       "ddvs sim arm as the plant role"))
    scene = Path(__file__).resolve().parents[1] / "configs" / "arm" / "ur5_poster.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "ddvs.cli", "sim", "arm", "--config", str(scene), "--clock", "realtime",
         "--fps", "30", "--deadman", "0.1", "--start", "reference", "--mode", "client", "--connect", endpoint,
         "--zenoh-config", str(plant_file), "--prefix", KEYS.prefix, "--robot", KEYS.robot],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env={k: v for k, v in os.environ.items() if not k.startswith("DDVS_ZENOH_")})
    try:
        bridge, operator, observer = (
            zenoh.open(_zenoh_config(client_config(role, [endpoint], TlsFiles.for_role(certs, role))))
            for role in ("bridge", "operator", "observer"))
        sessions += [bridge, operator, observer]
        states: list[JointState] = []
        watch = observer.declare_subscriber(KEYS.arm_joint_states,
                                            lambda s: states.append(decode_joint_state(s.payload.to_bytes())))
        deadline = time.monotonic() + 60.0
        while not states:
            assert proc.poll() is None, "ddvs sim arm exited"
            assert time.monotonic() < deadline, "no joint states from the sim through the hub"
            time.sleep(0.05)
        names = states[-1].name

        def drive(session: zenoh.Session, seconds: float = 1.0) -> float:
            """Command joint 0 at 0.2 rad/s for `seconds`; returns how far joint 0 moved (rad)."""
            start = states[-1].position[0]
            t0 = time.monotonic()
            while time.monotonic() - t0 < seconds:
                velocity = np.array([0.2] + [0.0] * (len(names) - 1))
                session.put(KEYS.arm_joint_velocity, encode_joint_state(
                    JointState(Header(Time.now(), ""), list(names), velocity=velocity)))
                time.sleep(0.02)
            time.sleep(0.3)
            return float(states[-1].position[0] - start)

        assert abs(drive(operator)) < 1e-6
        assert abs(drive(observer)) < 1e-6
        assert drive(bridge) > 0.1  # ≈ 0.2 rad/s × 1 s: the authorised path works in the same network
        watch.undeclare()
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
        for session in reversed(sessions):
            session.close()


@pytest.mark.slow
def test_ddvs_serve_refuses_a_router_that_holds_a_role_certificate(certs: Path, tmp_path: Path) -> None:
    """The rogue-router attack on the real `ddvs serve`: its router goes down and, one after the other, a router
    holding each role's certificate takes over the endpoint and the attacker sends frames, `get_state` and `stop`
    through it. The service never joins it (no reply, no status, no twist), logs a clear error, and joins the real
    router's certificate on the same endpoint at once (control)."""
    endpoint = f"tls/localhost:{free_port()}"

    def router_as(holder: str) -> zenoh.Session:
        config = router_config(KEYS, certificate_identities(SCOPE), [endpoint], TlsFiles.for_role(certs, holder))
        if holder != "router":
            del config["access_control"]  # the impostor lets everything through
        return zenoh.open(_zenoh_config(config))

    zenoh_file = tmp_path / "service.json5"
    zenoh_file.write_text(render_json5(client_config("service", [endpoint], TlsFiles.for_role(certs, "service")),
                                       "ddvs serve as the service role"))
    serve_file = tmp_path / "serve.json"
    serve_file.write_text(json.dumps({
        "robot": KEYS.robot, "zenoh": {"mode": "client", "connect": [endpoint], "zenoh_config": str(zenoh_file)},
        "state_dir": str(tmp_path / "state"),
        "intrinsics": {"fx": 420.0, "fy": 420.0, "cx": (W - 1) / 2, "cy": (H - 1) / 2, "width": W, "height": H},
    }))
    real = router_as("router")
    real_zid = real.info.zid()
    log_path = tmp_path / "serve.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith("DDVS_ZENOH_")}
    with log_path.open("w") as log_file:
        proc = subprocess.Popen([sys.executable, "-m", "ddvs.cli", "serve", "--config", str(serve_file)],
                                stderr=log_file, text=True, env=env)
    operator = zenoh.open(_zenoh_config(client_config("operator", [endpoint], TlsFiles.for_role(certs, "operator"))))
    frame = encode_image(image_from_array(texture(), "mono8", Header(Time.now(), "camera")))
    try:
        deadline = time.monotonic() + 60.0
        while command(operator, timeout=1.0, op="get_state") is None:
            assert proc.poll() is None and time.monotonic() < deadline, log_path.read_text()
        operator.close()
        real.close()
        for holder in (*ROLES, "router"):
            rogue = router_as(holder)
            heard = Inbox(rogue, f"{KEYS.base}/servo/**").payloads
            replies = []
            deadline = time.monotonic() + (4.5 if holder != "router" else 30.0)  # clients retry every 1–4 s
            while time.monotonic() < deadline and not replies:
                rogue.put(KEYS.camera_image, frame)
                replies = [r for r in rogue.get(KEYS.servo_command, payload=dump(Command(op="get_state")),
                                                timeout=0.3) if r.ok is not None]
            rogue.close()
            assert proc.poll() is None, log_path.read_text()
            if holder != "router":
                assert replies == [] and heard == [], f"ddvs serve joined a router holding the {holder} certificate"
        assert replies, "control: the service must join a router holding the router's certificate"
        lines = [json.loads(line) for line in log_path.read_text().splitlines() if line.startswith("{")]
        lost = [e for e in lines if e["level"] == "ERROR" and "lost the connection to the router" in e["msg"]]
        assert lost and lost[0]["endpoints"] == [endpoint]
        joined = [e["router"] for e in lines if e["msg"] == "connected to router"]
        assert joined[0] == str(real_zid) and len(joined) == 2  # at start, then the real router's certificate again
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)


@pytest.mark.parametrize("node", ["serve", "bridge", "sim arm"])
def test_nodes_refuse_a_robot_their_router_configuration_does_not_cover(tmp_path: Path, node: str) -> None:
    """`ddvs security init --robot ur5` beside the node's Zenoh configuration, the node run for robot0: it refuses
    to start (exit 2) and says why and how to fix it, instead of running with every message silently dropped."""
    subprocess.run([sys.executable, "-m", "ddvs.cli", "security", "init", "--robot", "ur5", "--configs-only",
                    str(tmp_path / "secure")], check=True, capture_output=True)
    role = {"serve": "service", "bridge": "bridge", "sim arm": "plant"}[node]
    zenoh_file = str(tmp_path / "secure" / f"{role}-mtls.json5")
    if node == "serve":
        serve_file = tmp_path / "serve.json"
        serve_file.write_text(json.dumps({"robot": "robot0", "state_dir": str(tmp_path / "state"), "zenoh": {
            "mode": "client", "connect": ["tls/localhost:7447"], "zenoh_config": zenoh_file}}))
        args = ["serve", "--config", str(serve_file)]
    else:
        config = "ur5_bridge.json" if node == "bridge" else "ur5_poster.json"
        args = [*node.split(), "--config", str(REPO / "configs" / "arm" / config), "--robot", "robot0", "--mode",
                "client", "--connect", "tls/localhost:7447", "--zenoh-config", zenoh_file]
    env = {k: v for k, v in os.environ.items() if not k.startswith("DDVS_ZENOH_")}
    result = subprocess.run([sys.executable, "-m", "ddvs.cli", *args], capture_output=True, text=True, timeout=120,
                            env=env)
    assert result.returncode == 2, result.stderr
    errors = [json.loads(line) for line in result.stderr.splitlines() if line.startswith("{")]
    assert any(e["level"] == "ERROR" and e.get("robot") == "ddvs/robot0" and "is not covered" in e["msg"]
               and "ddvs security init --robot robot0" in e["msg"] for e in errors), result.stderr
