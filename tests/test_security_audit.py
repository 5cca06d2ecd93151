"""The audit of a secured router: the real `ddvs router` (a subprocess) with the configurations `ddvs security init`
writes, real client sessions on loopback. Every denied message is counted per identity and logged as a JSON line at a
bounded rate, sessions without a role and refused TLS handshakes are reported, `ddvs monitor` shows the counts, and
a network where every node only does what its role allows produces no denial at all."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import pytest
import zenoh
from conftest import free_port
from test_security import Inbox, _put_until

from clients.monitor import Monitor, render
from ddvs_service.protocol import Keys
from ddvs_service.protocol.audit import audit_key
from ddvs_service.protocol.pki import issue_certificates
from ddvs_service.protocol.security import ROLES, TlsFiles, client_config

KEYS = Keys("ddvs", "arm7")
OBSERVER, MALLORY = f"observer@{KEYS.base}", f"mallory@{KEYS.base}"  # identities name their robot
REPORT_WAIT_S = 3.0  # the router publishes its audit every second


@pytest.fixture(scope="module")
def secured(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """`ddvs security init` output for robot arm7 on a free port, plus a certificate of the same CA for an identity
    that has no role ('mallory')."""
    out = tmp_path_factory.mktemp("secured")
    endpoint = f"tls/localhost:{free_port()}"
    subprocess.run([sys.executable, "-m", "ddvs.cli", "security", "init", "--robot", KEYS.robot, "--router", endpoint,
                    str(out)], check=True, capture_output=True, cwd=out.parent)
    issue_certificates(out, ["mallory"], KEYS.base)
    return out, endpoint


@contextmanager
def ddvs_router(out: Path, endpoint: str, log: Path, *extra: str) -> Iterator[subprocess.Popen[str]]:
    with log.open("w") as stderr:
        proc = subprocess.Popen([sys.executable, "-m", "ddvs.cli", "router", "--zenoh-config",
                                 str(out / "router-mtls.json5"), "--listen", endpoint, *extra],
                                stdout=subprocess.PIPE, stderr=stderr, text=True, cwd=out.parent)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().startswith("router "), log.read_text()
        yield proc
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def audit_lines(log: Path) -> list[dict[str, Any]]:
    return [e for e in (json.loads(line) for line in log.read_text().splitlines() if line.startswith("{"))
            if e["logger"] == "ddvs.audit"]


def open_role(out: Path, role: str) -> zenoh.Session:
    return zenoh.open(zenoh.Config.from_file(str(out / f"{role}-mtls.json5")))


def open_roles(stack: ExitStack, out: Path, *roles: str) -> list[zenoh.Session]:
    """A session per role of `roles` (its `<role>-mtls.json5` in `out`), closed when `stack` closes."""
    sessions = [open_role(out, role) for role in roles]
    for session in sessions:
        stack.callback(session.close)
    return sessions


def newest_report(inbox: Inbox, predicate: Any, timeout: float = REPORT_WAIT_S) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if inbox.payloads and predicate(report := json.loads(inbox.payloads[-1])):
            return report
        time.sleep(0.05)
    return json.loads(inbox.payloads[-1]) if inbox.payloads else {}


@pytest.mark.slow
def test_intrusions_are_logged_counted_and_shown_while_legitimate_traffic_is_not(
    secured: tuple[Path, str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out, endpoint = secured
    monkeypatch.chdir(out.parent)  # the configurations' paths are relative to where `ddvs security init` ran
    log = tmp_path / "router.log"
    with ddvs_router(out, endpoint, log):
        sessions = {role: open_role(out, role) for role in ROLES}
        try:
            service, plant, bridge, operator, observer = (sessions[r] for r in ROLES)
            reports = Inbox(observer, audit_key(KEYS.base))
            monitor = Monitor(operator, KEYS)
            commands, twists = Inbox(plant, KEYS.arm_joint_velocity), Inbox(bridge, KEYS.servo_twist)
            status = Inbox(observer, KEYS.servo_status)
            queryable = service.declare_queryable(KEYS.servo_command, lambda q: q.reply(q.key_expr, b"ok"))
            token = service.liveliness().declare_token(KEYS.liveliness)
            time.sleep(0.5)
            # every role does what it may: no denial
            assert _put_until(bridge, KEYS.arm_joint_velocity, b"qd", commands)
            assert _put_until(service, KEYS.servo_twist, b"twist", twists)
            assert _put_until(service, KEYS.servo_status, b"status", status)
            assert [r.ok.payload.to_bytes() for r in operator.get(KEYS.servo_command, timeout=2.0) if r.ok] == [b"ok"]
            assert [r.ok for r in bridge.liveliness().get(KEYS.liveliness, timeout=2.0) if r.ok]
            quiet = newest_report(reports, lambda r: False, timeout=2.0)
            assert quiet == {**quiet, "denied": {}, "no_role": {}, "tls_refused": 0, "auth_refused": 0}
            assert audit_lines(log) == []

            # intrusions: the observer sends joint velocities, a certificate with no role connects and sends, the
            # router's own certificate is tried as a client
            for _ in range(7):
                observer.put(KEYS.arm_joint_velocity, b"forged")
            mallory = zenoh.open(zenoh.Config.from_json5(json.dumps(client_config(
                "operator", [endpoint], TlsFiles.for_role(out.name, "mallory")))))
            mallory.put(KEYS.arm_joint_velocity, b"forged")
            with pytest.raises(zenoh.ZError, match="Unable to connect"):
                zenoh.open(zenoh.Config.from_json5(json.dumps(client_config(
                    "operator", [endpoint], TlsFiles.for_role(out.name, "router")))))
            report = newest_report(reports, lambda r: r["denied"].get(OBSERVER) == 7 and r["no_role"]
                                   and r["tls_refused"])
            mallory.close()
            assert report["denied"] == {OBSERVER: 7}, report
            assert report["no_role"] == {MALLORY: 1} and report["tls_refused"] >= 1, report
            assert b"forged" not in commands.payloads
            lines = audit_lines(log)
            denied = [e for e in lines if e["msg"] == "access denied"]
            assert [e["count"] for e in denied] == list(range(1, 8))
            assert {(e["identity"], e["action"], e["key"]) for e in denied} == {
                (OBSERVER, "Put", KEYS.arm_joint_velocity)}
            assert [e["identity"] for e in lines if e["msg"].startswith("session without a role")] == [MALLORY]
            assert any(e["msg"] == "TLS handshake refused" for e in lines)
            time.sleep(1.2)
            shown = monitor.snapshot()["audit"]
            assert shown["denied"] == {OBSERVER: 7} and shown["no_role"] == {MALLORY: 1}
            assert f"denied {OBSERVER} 7" in render(monitor.snapshot(), "t")
            monitor.close()
            queryable.undeclare()
            token.undeclare()
        finally:
            for session in sessions.values():
                session.close()


@pytest.mark.slow
def test_audit_lines_are_rate_bounded_but_every_denial_is_counted(
    secured: tuple[Path, str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out, endpoint = secured
    monkeypatch.chdir(out.parent)
    log = tmp_path / "router.log"
    with ddvs_router(out, endpoint, log, "--audit-rate", "5"):
        observer = open_role(out, "observer")
        try:
            reports = Inbox(observer, audit_key(KEYS.base))
            time.sleep(0.3)
            started = time.monotonic()
            for _ in range(300):
                observer.put(KEYS.servo_twist, b"forged")
            report = newest_report(reports, lambda r: r["denied"].get(OBSERVER) == 300)
            elapsed = time.monotonic() - started
            time.sleep(1.0)  # the router's next flush logs what is still suppressed
        finally:
            observer.close()
    assert report["denied"] == {OBSERVER: 300}, report
    lines = audit_lines(log)
    individual = [e for e in lines if e["msg"] == "access denied"]
    summarised = sum(e["suppressed"] for e in lines if e["msg"] == "access denials not logged individually")
    summarised += sum(e["suppressed"] for e in individual)
    assert len(individual) <= 10 + 5 * elapsed + 1  # burst of 2 × rate, then 5 lines per second
    assert len(individual) + summarised == 300  # nothing lost: each denial is either a line or in a summary count


def test_security_init_password_variant_admits_each_role_and_refuses_wrong_passwords(
    secured: tuple[Path, str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The user/password files `ddvs security init` writes work as they are: each role connects with its generated
    password and its rights, a wrong password is refused and logged; a role that may not read the audit gets none."""
    out, endpoint = secured
    monkeypatch.chdir(out.parent)
    log = tmp_path / "router.log"
    with log.open("w") as stderr:
        proc = subprocess.Popen([sys.executable, "-m", "ddvs.cli", "router", "--zenoh-config",
                                 str(out / "router-password.json5"), "--listen", endpoint],
                                stdout=subprocess.PIPE, stderr=stderr, text=True, cwd=out.parent)
    sessions = []
    try:
        assert proc.stdout is not None and proc.stdout.readline().startswith("router "), log.read_text()
        plant, bridge, observer = (zenoh.open(zenoh.Config.from_file(str(out / f"{role}-password.json5")))
                                   for role in ("plant", "bridge", "observer"))
        sessions += [plant, bridge, observer]
        commands = Inbox(plant, KEYS.arm_joint_velocity)
        time.sleep(0.3)
        assert _put_until(bridge, KEYS.arm_joint_velocity, b"qd", commands)
        observer.put(KEYS.arm_joint_velocity, b"forged")
        wrong = json.loads(zenoh.Config.from_file(str(out / "bridge-password.json5")).get_json("transport"))
        wrong["auth"]["usrpwd"]["password"] = "not-the-password"
        config = zenoh.Config.from_file(str(out / "bridge-password.json5"))
        config.insert_json5("transport", json.dumps(wrong))
        with pytest.raises(zenoh.ZError, match="Unable to connect"):
            zenoh.open(config)
        reports = Inbox(plant, audit_key(KEYS.base))  # the plant may not read the audit: it gets nothing
        time.sleep(1.5)
        assert b"forged" not in commands.payloads and reports.payloads == []
        lines = audit_lines(log)
        denied = [e for e in lines if e["msg"] == "access denied"]
        assert sorted((e["identity"], e["key"]) for e in denied) == [(OBSERVER, KEYS.arm_joint_velocity),
                                                                      (f"plant@{KEYS.base}", audit_key(KEYS.base))]
        assert [e["detail"] for e in lines if e["msg"] == "authentication refused"] == ["Invalid password"]
    finally:
        for session in sessions:
            session.close()
        proc.terminate()
        proc.wait(timeout=30)
