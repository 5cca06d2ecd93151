"""A secured fleet end to end: `ddvs security init --robot sf_a --robot sf_b --robot sf_c` writes the certificates and
the rules, the real `ddvs router` enforces them (mutual TLS on a port chosen here), and one `ddvs serve --robots sf_a
sf_b` process connects with the service's files. Its process commands (`ddvs/serve/sf_a/command`) answer the operator
and never the observer, a robot the rules do not cover is refused at `add_robot`, and a covered one is added; robot
sf_b's frames (a photograph warped by known motions, tests/test_service_node.py; intrinsics from the configuration)
are answered with twists. The router's log shows that only the observer was denied anything. A process named
otherwise than the rules allow refuses to start."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from conftest import free_port
from test_security import Inbox
from test_security_audit import audit_lines, ddvs_router, open_roles
from test_service_node import Service, answered_frames, scene, service_config, shifted

from ddvs_service.protocol import (
    Command,
    Keys,
    Reply,
    SessionConfig,
    decode_twist_stamped,
    dump,
    encode_image,
    image_from_array,
)
from ddvs_service.protocol.control import process_command_key
from ddvs_service.protocol.ros import Header, Time

SERVED, ADDED, UNCOVERED = ("sf_a", "sf_b"), "sf_c", "sf_d"
PROCESS_KEY = process_command_key("ddvs", SERVED[0])  # the process is named after its first robot
START_LIMIT_S = 120.0  # certificates issued, router up, the service's kernels compiled on a loaded host


def ask(session: zenoh.Session, key: str, timeout: float = 2.0, **command: Any) -> Reply | None:
    """The reply to a command query on `key`, None when nothing answers (the router dropped the query)."""
    for reply in session.get(key, payload=dump(Command(**command)), timeout=timeout):
        if reply.ok is not None:
            return Reply.model_validate_json(reply.ok.payload.to_bytes())
    return None


def send_frame(put: Callable[[bytes], object], statuses: list[bytes], twists: list[bytes], image: np.ndarray,
               n: int) -> dict[str, Any]:
    """Publish frame `n` (mono8, stamped n × 33 ms) with `put`; the status it produced, once its twist came back too
    (`statuses`, `twists`: the payloads received so far)."""
    n_status, n_twist = len(statuses), len(twists)
    put(encode_image(image_from_array(image, "mono8", Header(Time.from_ns(n * 33_000_000), "cam"))))
    until = time.monotonic() + 30.0
    while len(statuses) <= n_status or len(twists) <= n_twist:
        assert time.monotonic() < until, f"frame {n} not answered"
        time.sleep(0.005)
    return dict(json.loads(statuses[-1]))


def served_robots(reply: Reply | None) -> list[str]:
    assert reply is not None and reply.ok and reply.data is not None, reply
    return [robot["robot"] for robot in reply.data["robots"]]


def test_a_secured_fleet_process_serves_its_robots_and_answers_only_the_operator(tmp_path: Path) -> None:
    out, endpoint = tmp_path / "secure", f"tls/localhost:{free_port()}"
    subprocess.run([sys.executable, "-m", "ddvs.cli", "security", "init", *(a for r in (*SERVED, ADDED)
                    for a in ("--robot", r)), "--router", endpoint, str(out)], check=True, capture_output=True)
    config = service_config(0, tmp_path / "state").model_copy(update={"zenoh": SessionConfig(
        mode="client", connect=[endpoint], zenoh_config=out / "service-mtls.json5")})
    robot_b = Keys("ddvs", SERVED[1])
    log = tmp_path / "router.log"
    with ExitStack() as stack:
        stack.enter_context(ddvs_router(out, endpoint, log))
        operator, observer, plant = open_roles(stack, out, "operator", "observer", "plant")
        service = Service(config, tmp_path, "--robots", *SERVED)
        stack.callback(service.stop)  # on failure; a second stop returns at once

        deadline = time.monotonic() + START_LIMIT_S
        while (listed := ask(operator, PROCESS_KEY, op="list_robots")) is None:
            assert service.proc.poll() is None, service.stop()[1][-4000:]
            assert time.monotonic() < deadline, "the fleet process never answered list_robots"
            time.sleep(0.2)
        assert served_robots(listed) == list(SERVED)

        # the observer may not use the process's commands: its queries are dropped by the router
        assert ask(observer, PROCESS_KEY, op="list_robots") is None
        assert ask(observer, PROCESS_KEY, op="add_robot", robot=ADDED) is None
        refused = ask(operator, PROCESS_KEY, timeout=30.0, op="add_robot", robot=UNCOVERED)
        assert refused is not None and not refused.ok and "not covered" in (refused.error or ""), refused
        assert served_robots(ask(operator, PROCESS_KEY, op="list_robots")) == list(SERVED)
        added = ask(operator, PROCESS_KEY, timeout=60.0, op="add_robot", robot=ADDED)
        assert added is not None and added.ok, added
        assert served_robots(ask(operator, PROCESS_KEY, op="list_robots")) == [*SERVED, ADDED]

        # robot sf_b servos: the plant's frames are answered with twists, the operator commands it
        twists, statuses = Inbox(operator, robot_b.servo_twist), Inbox(operator, robot_b.servo_status)
        frames = answered_frames(plant, robot_b.camera_image)
        stack.callback(frames.undeclare)

        def send(image: np.ndarray, n: int) -> dict[str, Any]:
            return send_frame(frames.put, statuses.payloads, twists.payloads, image, n)

        time.sleep(0.5)  # the subscriptions and the publisher reach the router
        reply = ask(operator, robot_b.servo_command, op="set_reference", source="next_frame")
        assert reply is not None and reply.ok, reply
        assert send(scene(), 1)["state"] == "READY"
        reply = ask(operator, robot_b.servo_command, op="start")
        assert reply is not None and reply.ok, reply
        states = [send(shifted(scene(), 3.0, -2.0, 1.0), n)["state"] for n in range(2, 5)]
        assert states == ["SERVOING"] * 3, states
        twist = decode_twist_stamped(twists.payloads[-1]).vector
        assert np.all(np.isfinite(twist)) and np.linalg.norm(twist) > 0.0, twist

        code, stderr = service.stop()
        assert code == 0, stderr[-4000:]
    denied = [e for e in audit_lines(log) if e["msg"] == "access denied"]
    observer = f"observer@ddvs/{SERVED[0]}"  # the fleet's identities name its process
    assert {(e["identity"], e["action"], e["key"]) for e in denied} == {(observer, "Query", PROCESS_KEY)}, denied


def test_ddvs_serve_refuses_a_process_name_the_rules_do_not_allow(tmp_path: Path) -> None:
    """Rules made for the process named after sf_a, a process started as `--process cell1`: its add_robot,
    remove_robot and list_robots would all be dropped, so it exits 2 and says how to fix it (the test above is the
    control: the same rules, the process's default name, served)."""
    out = tmp_path / "secure"
    subprocess.run([sys.executable, "-m", "ddvs.cli", "security", "init", "--robot", SERVED[0], "--robot", SERVED[1],
                    "--configs-only", str(out)], check=True, capture_output=True)
    config = service_config(0, tmp_path / "state").model_copy(update={"zenoh": SessionConfig(
        mode="client", connect=["tls/localhost:7447"], zenoh_config=out / "service-mtls.json5")})
    service = Service(config, tmp_path, "--robots", *SERVED, "--process", "cell1", "--no-warmup")
    service.proc.wait(timeout=120)
    code, stderr = service.stop()
    assert code == 2, stderr[-4000:]
    assert "process command key 'ddvs/serve/cell1/command' is not allowed" in stderr, stderr[-4000:]
    assert "['ddvs/serve/sf_a/command']" in stderr and "--process NAME" in stderr
