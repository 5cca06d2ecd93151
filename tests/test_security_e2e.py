"""End to end with security on: the paper's UR5 set-up (`ddvs sim arm` lockstep, `ddvs serve`, `ddvs bridge`, each its
own process) where every node is a mutual-TLS client of the hub router with the generated deny-by-default rules. The
servo converges to the reference pose while an observer keeps trying to stop the servo, to publish joint velocities
and twists, and to read frames — none of which has any effect."""

from __future__ import annotations

import json
import subprocess
import time
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest
import zenoh
from conftest import free_port
from test_security import SCRIPT, Inbox, _zenoh_config

from ddvs_service.lie import so3_log
from ddvs_service.protocol import (
    Command,
    GroundTruth,
    Header,
    JointState,
    Keys,
    ReferenceImage,
    Reply,
    Time,
    TwistStamped,
    dump,
    encode_joint_state,
    encode_twist_stamped,
    parse_message,
)
from ddvs_service.protocol.security import (
    TlsFiles,
    certificate_identities,
    client_config,
    render_json5,
    router_config,
)
from ddvs_service.protocol.upload import encode_upload
from orchestration.arm_run import BRIDGE, SCENE, ArmRunSettings, child, render_reference, service_config

KEYS = Keys("ddvs", "secure_e2e")
TIME_LIMIT_S = 240.0
SETTLE_STATUSES = 5
# Pose tolerance at the service's stop threshold ‖ε‖ < 1e-3: the same run without security ends 3.1 mm / 0.24° from
# the reference (reports/e2e_arm/ddvs_70x70), from 276 mm / 25° away.
MAX_TRANSLATION_MM = 5.0
MAX_ROTATION_DEG = 0.5


def command(session: zenoh.Session, cmd: Command, timeout: float = 30.0) -> Reply | None:
    for reply in session.get(KEYS.servo_command, payload=dump(cmd), timeout=timeout):
        if reply.ok is not None:
            return Reply.model_validate_json(reply.ok.payload.to_bytes())
    return None


def pose_error(T_ref: np.ndarray, T: np.ndarray) -> tuple[float, float]:
    """(translation error mm, rotation error degrees) between two camera poses."""
    dt = float(np.linalg.norm(T[:3, 3] - T_ref[:3, 3])) * 1e3
    dr = float(np.degrees(np.linalg.norm(so3_log(T_ref[:3, :3].T @ T[:3, :3]))))
    return dt, dr


@pytest.mark.slow
def test_arm_servo_converges_with_mtls_and_access_control_while_an_observer_interferes(tmp_path: Path) -> None:
    certs = tmp_path / "certs"
    subprocess.run(["bash", str(SCRIPT), str(certs)], check=True, capture_output=True)
    endpoint = f"tls/localhost:{free_port()}"
    settings = ArmRunSettings(out_dir=tmp_path, law="ddvs", template=(70, 70), clock="lockstep",
                              robot=KEYS.robot, prefix=KEYS.prefix)
    reference, T_world_ref = render_reference(SCENE)

    def role_file(role: str) -> Path:
        path = tmp_path / f"{role}.json5"
        path.write_text(render_json5(client_config(role, [endpoint], TlsFiles.for_role(certs, role)), role))
        return path

    serve = service_config(settings, 0, 0)
    serve["zenoh"] = {"mode": "client", "connect": [endpoint], "zenoh_config": str(role_file("service"))}
    (tmp_path / "serve.json").write_text(json.dumps(serve))
    common = ["--prefix", KEYS.prefix, "--robot", KEYS.robot]
    secure = ["--mode", "client", "--connect", endpoint]
    with ExitStack() as stack:
        router = zenoh.open(_zenoh_config(router_config(
            KEYS, certificate_identities(), [endpoint], TlsFiles.for_role(certs, "router"),
            observers_read_frames=False)))
        stack.callback(router.close)
        children = {
            "sim": ["sim", "arm", "--config", str(SCENE), "--clock", "lockstep", "--fps", "30",
                    "--lockstep-timeout", "2", "--start", "start", *secure, "--zenoh-config", str(role_file("plant")),
                    *common],
            "serve": ["serve", "--config", str(tmp_path / "serve.json"), "--fresh"],
            "bridge": ["bridge", "--config", str(BRIDGE), *secure, "--zenoh-config", str(role_file("bridge")),
                       *common],
        }
        procs = {name: stack.enter_context(child(name, args, tmp_path / "logs")) for name, args in children.items()}
        operator, observer = (zenoh.open(_zenoh_config(client_config(r, [endpoint], TlsFiles.for_role(certs, r))))
                              for r in ("operator", "observer"))
        stack.callback(operator.close)
        stack.callback(observer.close)
        statuses = Inbox(operator, KEYS.servo_status)
        truths = Inbox(operator, KEYS.arm_ground_truth)
        frames_to_observer = Inbox(observer, KEYS.camera_image)

        def check_children() -> None:
            for name, proc in procs.items():
                log = (tmp_path / "logs" / f"{name}.log").read_text(errors="replace")[-2000:]
                assert proc.poll() is None, f"ddvs {name} exited ({proc.returncode}):\n{log}"

        started = time.monotonic()
        while not statuses.payloads:
            check_children()
            assert time.monotonic() - started < TIME_LIMIT_S, "no status from the service"
            time.sleep(0.2)
        upload = ReferenceImage(format="png", data=encode_upload(reference, "png"))
        assert command(observer, Command(op="set_reference", source="upload", image=upload), timeout=2.0) is None
        for cmd in (Command(op="set_reference", source="upload", image=upload), Command(op="start")):
            reply = command(operator, cmd)
            assert reply is not None and reply.ok, (cmd.op, reply)

        converged = 0
        interfering = 0
        while converged < SETTLE_STATUSES:
            check_children()
            assert time.monotonic() - started < TIME_LIMIT_S, f"not converged; logs in {tmp_path / 'logs'}"
            status = json.loads(statuses.payloads[-1])
            converged = converged + 1 if status["state"] == "CONVERGED" else 0
            if interfering < 20:  # the observer's attempts, spread over the run
                interfering += 1
                assert command(observer, Command(op="stop"), timeout=0.2) is None
                observer.put(KEYS.arm_joint_velocity, encode_joint_state(JointState(
                    Header(Time.now(), ""), ["shoulder_pan_joint"], velocity=np.array([1.0]))))
                observer.put(KEYS.servo_twist, encode_twist_stamped(TwistStamped(
                    Header(Time.now(), "camera"), np.array([0.2, 0.0, 0.0]), np.zeros(3))))
            time.sleep(0.1)
        final = json.loads(statuses.payloads[-1])
        first, last = (parse_message(GroundTruth, truths.payloads[i]) for i in (0, -1))
        T_ref = np.asarray(T_world_ref)
        start_mm, start_deg = pose_error(T_ref, np.asarray(first.camera_pose).reshape(4, 4))
        dt_mm, dr_deg = pose_error(T_ref, np.asarray(last.camera_pose).reshape(4, 4))
        print(json.dumps({"wall_s": round(time.monotonic() - started, 1), "error_norm": final.get("error_norm"),
                          "start_mm": start_mm, "start_deg": start_deg, "final_mm": dt_mm, "final_deg": dr_deg}))
        assert start_mm > 250.0 and start_deg > 20.0  # it really started at the paper's displacement
        assert final["error_norm"] < 1e-3
        assert dt_mm < MAX_TRANSLATION_MM and dr_deg < MAX_ROTATION_DEG
        assert frames_to_observer.payloads == []
