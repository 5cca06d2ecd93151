"""Transport security and access control with real Zenoh sessions on loopback: a Python router with the generated
deny-by-default rules as the hub, one client session per role, TLS certificates made by `scripts/make_dev_certs.sh`.

Every "refused" check is paired with an authorised control in the same network, so a test cannot pass because
nothing was delivered at all.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import zenoh
from conftest import free_port

from ddvs_service.protocol import TOPICS, Keys, SessionConfig
from ddvs_service.protocol.audit import audit_key
from ddvs_service.protocol.control import process_command_key
from ddvs_service.protocol.security import (
    ROLE_GRANTS,
    ROLES,
    Fleet,
    Identity,
    TlsFiles,
    certificate_identities,
    check_process_covered,
    check_robot_covered,
    client_config,
    password_identities,
    render_json5,
    robots_granted,
    router_config,
    warn_if_insecure,
    write_configs,
)

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "make_dev_certs.sh"
KEYS = Keys("ddvs", "ur5")
SCOPE = KEYS.base  # the certificates' robot: common names `<role>@ddvs/ur5`
SETTLE_S = 0.4  # declarations propagating through the router
WAIT_S = 0.6


def _zenoh_config(config: dict[str, Any]) -> zenoh.Config:
    out = zenoh.Config()
    for key, value in config.items():
        out.insert_json5(key, json.dumps(value))
    return out


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("certs")
    subprocess.run(["bash", str(SCRIPT), str(directory), "--robot", KEYS.robot], check=True, capture_output=True)
    return directory


@pytest.fixture(scope="module")
def rogue_certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Certificates with the right common names from another CA (an attacker's)."""
    directory = tmp_path_factory.mktemp("rogue")
    subprocess.run(["bash", str(SCRIPT), str(directory), "--robot", KEYS.robot], check=True, capture_output=True)
    return directory


class Network:
    """A hub router (TLS on a free loopback port) and the client sessions opened through it; all closed on exit."""

    def __init__(self, router: dict[str, Any], endpoint: str) -> None:
        self.endpoint = endpoint
        self.sessions: list[zenoh.Session] = [zenoh.open(_zenoh_config(router))]

    def open(self, config: dict[str, Any]) -> zenoh.Session:
        session = zenoh.open(_zenoh_config(config))
        self.sessions.append(session)
        return session

    def close(self) -> None:
        for session in reversed(self.sessions):
            session.close()


@contextmanager
def network(router_for: Callable[[str], dict[str, Any]]) -> Iterator[Network]:
    endpoint = f"tls/localhost:{free_port()}"
    net = Network(router_for(endpoint), endpoint)
    try:
        yield net
    finally:
        net.close()


def mtls_network(certs: Path, observers_read_frames: bool = True) -> Any:
    return network(lambda ep: router_config(KEYS, certificate_identities(SCOPE), [ep],
                                            TlsFiles.for_role(certs, "router"),
                                            mtls=True, observers_read_frames=observers_read_frames))


def mtls_client(net: Network, certs: Path, role: str) -> zenoh.Session:
    return net.open(client_config(role, [net.endpoint], TlsFiles.for_role(certs, role), mtls=True))


class Inbox:
    """A callback subscriber collecting payloads (the callback only appends: it never blocks the session)."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.payloads: list[bytes] = []
        self._sub = session.declare_subscriber(key, lambda s: self.payloads.append(s.payload.to_bytes()))

    def wait_for(self, payload: bytes, timeout: float = WAIT_S) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if payload in self.payloads:
                return True
            time.sleep(0.01)
        return payload in self.payloads


def _put_until(session: zenoh.Session, key: str, payload: bytes, inbox: Inbox, timeout: float = 3.0) -> bool:
    """Publish every 50 ms until the inbox has it (authorised paths: waits out declaration propagation)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        session.put(key, payload)
        if inbox.wait_for(payload, 0.05):
            return True
    return False


class CommandServer:
    """A queryable on `servo/command` that records every query it is handed and replies `{"ok": true}`."""

    def __init__(self, session: zenoh.Session) -> None:
        self.received: list[bytes] = []
        self._lock = threading.Lock()
        self._q = session.declare_queryable(KEYS.servo_command, self._on_query)

    def _on_query(self, query: zenoh.Query) -> None:
        with self._lock:
            self.received.append(query.payload.to_bytes() if query.payload is not None else b"")
        query.reply(query.key_expr, b'{"ok": true}')


def _replies(session: zenoh.Session, payload: bytes, timeout: float = 1.0) -> list[bytes]:
    out = []
    for reply in session.get(KEYS.servo_command, payload=payload, timeout=timeout):
        if reply.ok is not None:
            out.append(reply.ok.payload.to_bytes())
    return out


# --- certificates ---------------------------------------------------------------------------------------------------


def _x509(pem: Path) -> str:
    return subprocess.run(["openssl", "x509", "-in", str(pem), "-noout", "-subject", "-ext",
                           "subjectAltName,extendedKeyUsage"], check=True, capture_output=True, text=True).stdout


def test_certificates_per_purpose_router_serves_roles_only_connect(tmp_path: Path) -> None:
    first = subprocess.run(["bash", str(SCRIPT), str(tmp_path)], check=True, capture_output=True, text=True)
    assert "created" in first.stdout
    for name in ("router", *ROLES):
        pem = tmp_path / name / f"{name}.pem"
        subprocess.run(["openssl", "verify", "-CAfile", str(tmp_path / name / "ca.pem"), str(pem)], check=True,
                       capture_output=True)
        text = _x509(pem)
        assert f"CN = {name}@ddvs/robot0" in text  # the script's default robot, that of configs/security
        if name == "router":
            assert "TLS Web Server Authentication" in text and "Client Authentication" not in text
            assert "DNS:localhost" in text and "IP Address:127.0.0.1" in text
        else:
            assert "TLS Web Client Authentication" in text and "Server Authentication" not in text
            assert "Alternative Name" not in text and "localhost" not in text
        assert {p.name for p in (tmp_path / name).iterdir()} == {"ca.pem", f"{name}.key", f"{name}.pem"}
        assert (tmp_path / name / f"{name}.key").stat().st_mode & 0o077 == 0
    assert not any(list((tmp_path / role).glob("router*")) for role in ROLES)  # the router's key is only in router/


def test_certificates_are_idempotent_and_reissued_when_missing_renamed_or_rotated(tmp_path: Path) -> None:
    subprocess.run(["bash", str(SCRIPT), str(tmp_path)], check=True, capture_output=True)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    second = subprocess.run(["bash", str(SCRIPT), str(tmp_path)], check=True, capture_output=True, text=True)
    assert second.stdout == ""
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
    (tmp_path / "bridge" / "bridge.pem").unlink()  # a missing certificate is re-issued, the others are kept
    third = subprocess.run(["bash", str(SCRIPT), str(tmp_path)], check=True, capture_output=True, text=True)
    assert third.stdout.strip() == f"created {tmp_path}/bridge/bridge.pem"
    assert (tmp_path / "ca" / "ca.pem").read_bytes() == before[tmp_path / "ca" / "ca.pem"]
    renamed = subprocess.run(["bash", str(SCRIPT), str(tmp_path), "--router-name", "robot-host.lab"], check=True,
                             capture_output=True, text=True)
    assert renamed.stdout.strip() == f"created {tmp_path}/router/router.pem"
    assert "DNS:robot-host.lab" in _x509(tmp_path / "router" / "router.pem")
    shutil.rmtree(tmp_path / "ca")  # rotating the CA re-issues every certificate, each directory gets the new CA
    rotated = subprocess.run(["bash", str(SCRIPT), str(tmp_path)], check=True, capture_output=True, text=True)
    assert len(rotated.stdout.splitlines()) == 2 + len(ROLES)
    for name in ("router", *ROLES):
        pem = tmp_path / name / f"{name}.pem"
        assert pem.read_bytes() != before[pem] and (tmp_path / name / "ca.pem").read_bytes() != before[
            tmp_path / name / "ca.pem"]
        subprocess.run(["openssl", "verify", "-CAfile", str(tmp_path / "ca" / "ca.pem"), str(pem)], check=True,
                       capture_output=True)


def test_certificate_roles_come_from_ddvs_cert_roles(tmp_path: Path) -> None:
    env = {**os.environ, "DDVS_CERT_ROLES": "service operator"}
    subprocess.run(["bash", str(SCRIPT), str(tmp_path)], check=True, capture_output=True, env=env)
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_dir()) == ["ca", "operator", "router", "service"]
    env["DDVS_CERT_ROLES"] = "router"
    refused = subprocess.run(["bash", str(SCRIPT), str(tmp_path)], capture_output=True, text=True, env=env)
    assert refused.returncode == 2 and "not 'router' or 'ca'" in refused.stderr


def test_make_dev_certs_without_directory_explains_usage() -> None:
    result = subprocess.run(["bash", str(SCRIPT)], capture_output=True, text=True)
    assert result.returncode == 2 and "usage:" in result.stderr


# --- mutual TLS + access control ------------------------------------------------------------------------------------


def test_authorised_roles_reach_each_other(certs: Path) -> None:
    with mtls_network(certs) as net:
        service, plant, bridge, operator, observer = (mtls_client(net, certs, r) for r in ROLES)
        plant_commands = Inbox(plant, KEYS.arm_joint_velocity)
        bridge_twists = Inbox(bridge, KEYS.servo_twist)
        service_frames = Inbox(service, KEYS.camera_image)
        observer_status = Inbox(observer, KEYS.servo_status)
        server = CommandServer(service)
        time.sleep(SETTLE_S)
        assert _put_until(bridge, KEYS.arm_joint_velocity, b"qd", plant_commands)
        assert _put_until(service, KEYS.servo_twist, b"twist", bridge_twists)
        assert _put_until(plant, KEYS.camera_image, b"frame", service_frames)
        assert _put_until(service, KEYS.servo_status, b"status", observer_status)
        assert _replies(operator, b"get_state") == [b'{"ok": true}']
        assert server.received == [b"get_state"]


def test_liveliness_token_of_the_service_is_seen_by_bridge_and_observer(certs: Path) -> None:
    with mtls_network(certs) as net:
        service, bridge, observer = (mtls_client(net, certs, r) for r in ("service", "bridge", "observer"))
        token = service.liveliness().declare_token(KEYS.liveliness)
        time.sleep(SETTLE_S)
        for watcher in (bridge, observer):
            alive = [str(r.ok.key_expr) for r in watcher.liveliness().get(KEYS.liveliness, timeout=1.0)
                     if r.ok is not None]
            assert alive == [KEYS.liveliness]
        token.undeclare()


@pytest.mark.parametrize("intruder", ["service", "operator", "observer"])
def test_only_the_bridge_can_send_joint_velocities(certs: Path, intruder: str) -> None:
    with mtls_network(certs) as net:
        plant = mtls_client(net, certs, "plant")
        bridge = mtls_client(net, certs, "bridge")
        attacker = mtls_client(net, certs, intruder)
        commands = Inbox(plant, KEYS.arm_joint_velocity)
        time.sleep(SETTLE_S)
        assert _put_until(bridge, KEYS.arm_joint_velocity, b"authorised", commands)
        for _ in range(5):
            attacker.put(KEYS.arm_joint_velocity, b"forged")
        time.sleep(WAIT_S)
        assert b"forged" not in commands.payloads


@pytest.mark.parametrize("intruder", ["bridge", "operator", "observer"])
def test_only_the_service_can_send_twists(certs: Path, intruder: str) -> None:
    """The plant (free flyer) subscribes twists; a session's own puts reach its own subscribers locally, so the
    subscriber is never the intruder."""
    with mtls_network(certs) as net:
        service = mtls_client(net, certs, "service")
        attacker = mtls_client(net, certs, intruder)
        twists = Inbox(mtls_client(net, certs, "plant"), KEYS.servo_twist)
        time.sleep(SETTLE_S)
        assert _put_until(service, KEYS.servo_twist, b"authorised", twists)
        for _ in range(5):
            attacker.put(KEYS.servo_twist, b"forged")
        time.sleep(WAIT_S)
        assert b"forged" not in twists.payloads


@pytest.mark.parametrize("intruder", ["service", "plant", "bridge", "observer"])
def test_only_the_operator_can_call_the_command_queryable(certs: Path, intruder: str) -> None:
    with mtls_network(certs) as net:
        server = CommandServer(mtls_client(net, certs, "service"))
        operator = mtls_client(net, certs, "operator")
        attacker = mtls_client(net, certs, intruder)
        time.sleep(SETTLE_S)
        assert _replies(attacker, b"forged set_reference", timeout=0.5) == []
        assert _replies(operator, b"authorised") == [b'{"ok": true}']
        assert server.received == [b"authorised"]


def test_only_the_service_can_serve_the_command_queryable(certs: Path) -> None:
    """A rogue queryable (a valid identity that is not the service) never sees the operator's commands."""
    with mtls_network(certs) as net:
        rogue = CommandServer(mtls_client(net, certs, "plant"))
        server = CommandServer(mtls_client(net, certs, "service"))
        operator = mtls_client(net, certs, "operator")
        time.sleep(SETTLE_S)
        assert _replies(operator, b"set_config") == [b'{"ok": true}']
        assert server.received == [b"set_config"] and rogue.received == []


def test_observers_can_be_denied_frames(certs: Path) -> None:
    with mtls_network(certs, observers_read_frames=False) as net:
        plant, service, observer = (mtls_client(net, certs, r) for r in ("plant", "service", "observer"))
        served = Inbox(service, KEYS.camera_image)
        watched = Inbox(observer, KEYS.camera_image)
        status = Inbox(observer, KEYS.servo_status)
        time.sleep(SETTLE_S)
        assert _put_until(plant, KEYS.camera_image, b"frame", served)
        assert _put_until(service, KEYS.servo_status, b"status", status)  # observers still see the status
        time.sleep(WAIT_S)
        assert watched.payloads == []


def test_no_escape_from_the_robots_exact_keys(certs: Path) -> None:
    """A role cannot reach beyond its robot's exact keys: the bridge of this robot cannot command another robot's arm,
    and its wildcard subscription gets no frame (a session's wildcard sees only what the session itself may receive:
    its own puts and what its exact subscriptions are granted)."""
    other = Keys("ddvs", "other_robot")
    with mtls_network(certs) as net:
        plant, bridge, service = (mtls_client(net, certs, r) for r in ("plant", "bridge", "service"))
        commands = Inbox(plant, KEYS.arm_joint_velocity)
        foreign = Inbox(plant, other.arm_joint_velocity)
        wildcard = Inbox(bridge, "ddvs/**")
        frames = Inbox(service, KEYS.camera_image)
        time.sleep(SETTLE_S)
        assert _put_until(bridge, KEYS.arm_joint_velocity, b"own", commands)
        assert _put_until(plant, KEYS.camera_image, b"frame", frames)
        for _ in range(5):
            bridge.put(other.arm_joint_velocity, b"foreign")
            plant.put(KEYS.camera_image, b"frame")
        time.sleep(WAIT_S)
        assert foreign.payloads == [] and b"frame" not in wildcard.payloads


def test_sessions_without_a_valid_certificate_cannot_connect(certs: Path, rogue_certs: Path, tmp_path: Path) -> None:
    self_signed, self_signed_key = tmp_path / "operator.pem", tmp_path / "operator.key"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
                    "-keyout", str(self_signed_key), "-out", str(self_signed), "-days", "1",
                    "-subj", "/CN=operator@ddvs\\/ur5",
                    "-addext", "extendedKeyUsage=clientAuth"], check=True, capture_output=True)
    with mtls_network(certs) as net:
        port = net.endpoint.rsplit(":", 1)[1]
        attempts = {
            "no certificate": client_config("operator", [net.endpoint], TlsFiles(ca=certs / "operator" / "ca.pem"),
                                            mtls=False),
            "certificate of another CA": client_config(
                "operator", [net.endpoint], TlsFiles(certs / "operator" / "ca.pem",
                                                     rogue_certs / "operator" / "operator.pem",
                                                     rogue_certs / "operator" / "operator.key")),
            "a self-signed certificate": client_config(
                "operator", [net.endpoint], TlsFiles(certs / "operator" / "ca.pem", self_signed, self_signed_key)),
            "the router's own certificate (serverAuth only)": client_config(
                "operator", [net.endpoint], TlsFiles.for_role(certs, "router")),
            "plain TCP": client_config("operator", [f"tcp/127.0.0.1:{port}"]),
        }
        for what, config in attempts.items():
            with pytest.raises(zenoh.ZError, match="Unable to connect"):
                net.open(config)
                pytest.fail(f"a client with {what} connected")
        assert _replies(mtls_client(net, certs, "operator"), b"x", timeout=0.3) == []  # the router itself still runs


@pytest.mark.slow
@pytest.mark.parametrize("impostor", ROLES)
def test_a_router_with_a_role_certificate_is_refused_by_every_client(certs: Path, impostor: str) -> None:
    """The rogue-router attack: the real router goes down and one holding a role's certificate (right CA) listens
    on the same endpoint. Every role's client refuses it (no serverAuth, no router name), stays disconnected, and
    nothing it publishes reaches the impostor; the real router's certificate on the same spot is accepted (control)."""
    endpoint = f"tls/localhost:{free_port()}"
    real = zenoh.open(_zenoh_config(router_config(KEYS, certificate_identities(SCOPE), [endpoint],
                                                  TlsFiles.for_role(certs, "router"))))
    clients = {role: zenoh.open(_zenoh_config(client_config(role, [endpoint], TlsFiles.for_role(certs, role))))
               for role in ROLES}
    try:
        assert all(c.info.routers_zid() == [real.info.zid()] for c in clients.values())
        real.close()
        for attempt, listen_as in enumerate((impostor, "router")):
            rogue_config = router_config(KEYS, {}, [endpoint], TlsFiles.for_role(certs, listen_as))
            del rogue_config["access_control"]  # the impostor's router lets everything through
            rogue = zenoh.open(_zenoh_config(rogue_config))
            heard = Inbox(rogue, f"{KEYS.base}/**").payloads
            deadline = time.monotonic() + 5.0  # clients retry every 1–4 s
            while time.monotonic() < deadline and not (attempt == 1 and heard):
                for role, session in clients.items():
                    session.put(KEYS.key(ROLE_GRANTS[role].publish[0]) if ROLE_GRANTS[role].publish
                                else KEYS.servo_status, role.encode())
                time.sleep(0.1)
            joined = [r for r, c in clients.items() if c.info.routers_zid()]
            rogue.close()
            if attempt == 0:
                assert joined == [] and heard == [], f"a router holding the {impostor} certificate was accepted"
            else:
                assert joined and heard, "control: the router's own certificate must be accepted"
    finally:
        for session in clients.values():
            session.close()


# --- user/password over server-side TLS -----------------------------------------------------------------------------


def test_password_identities_wrong_credentials_refused_and_roles_enforced(certs: Path, tmp_path: Path) -> None:
    passwords = tmp_path / "passwords.txt"
    passwords.write_text("".join(f"{role}@{SCOPE}:pw-{role}\n" for role in ROLES), encoding="utf-8")
    tls_router = TlsFiles.for_role(certs, "router")
    with network(lambda ep: router_config(KEYS, password_identities(SCOPE), [ep], tls_router, mtls=False,
                                          password_file=passwords)) as net:
        ca_only = TlsFiles(ca=certs / "operator" / "ca.pem")

        def client(role: str, user: str, password: str) -> zenoh.Session:
            return net.open(client_config(role, [net.endpoint], ca_only, mtls=False, credentials=(user, password)))

        for user, password in ((f"bridge@{SCOPE}", "wrong"), ("mallory", "pw-bridge"), ("bridge", "pw-bridge")):
            with pytest.raises(zenoh.ZError, match="Unable to connect"):
                client("bridge", user, password)
        with pytest.raises(zenoh.ZError, match="Unable to connect"):
            net.open(client_config("bridge", [net.endpoint], ca_only, mtls=False))  # anonymous
        plant = client("plant", f"plant@{SCOPE}", "pw-plant")
        bridge = client("bridge", f"bridge@{SCOPE}", "pw-bridge")
        observer = client("observer", f"observer@{SCOPE}", "pw-observer")
        commands = Inbox(plant, KEYS.arm_joint_velocity)
        time.sleep(SETTLE_S)
        assert _put_until(bridge, KEYS.arm_joint_velocity, b"authorised", commands)
        observer.put(KEYS.arm_joint_velocity, b"forged")
        time.sleep(WAIT_S)
        assert b"forged" not in commands.payloads


# --- generated configurations ---------------------------------------------------------------------------------------


def test_rules_follow_the_key_table_and_grant_each_write_to_one_role() -> None:
    acl = router_config(KEYS, certificate_identities(SCOPE), ["tls/localhost:7447"])["access_control"]
    assert acl["default_permission"] == "deny" and acl["enabled"] is True
    process_key = process_command_key(KEYS.prefix, KEYS.robot)
    all_keys = {KEYS.key(name) for name in TOPICS} | {audit_key(KEYS.base), process_key}
    writers: dict[tuple[str, str], set[str]] = {}
    for rule in acl["rules"]:
        assert rule["permission"] == "allow" and set(rule["key_exprs"]) <= all_keys
        role = rule["id"].split("/")[0]
        if rule["flows"] == ["ingress"]:
            for message in rule["messages"]:
                for key in rule["key_exprs"]:
                    writers.setdefault((message, key), set()).add(role)
    assert writers[("put", KEYS.servo_twist)] == {"service"}
    assert writers[("put", KEYS.arm_joint_velocity)] == writers[("put", KEYS.arm_velocity_commands)] == {"bridge"}
    assert writers[("put", KEYS.camera_image)] == writers[("put", KEYS.arm_joint_states)] == {"plant"}
    assert writers[("query", KEYS.servo_command)] == {"operator"}
    assert writers[("declare_queryable", KEYS.servo_command)] == {"service"}
    assert writers[("query", process_key)] == {"operator"}  # the robot's `ddvs serve` process: add/remove robots
    assert writers[("declare_queryable", process_key)] == {"service"}
    assert ("put", audit_key(KEYS.base)) not in writers  # only the router itself publishes its audit
    assert not any("observer" in roles for (message, _), roles in writers.items()
                   if message not in ("declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"))
    other = Keys("ddvs", "other_robot")
    assert not any(key.startswith(other.base) for rule in acl["rules"] for key in rule["key_exprs"])


def _grants(acl: dict[str, Any], role: str) -> set[tuple[str, str, str]]:
    """(flow, message, key) triples a role's rules allow."""
    return {(flow, message, key) for rule in acl["rules"] if rule["id"].startswith(f"{role}/")
            for flow in rule["flows"] for message in rule["messages"] for key in rule["key_exprs"]}


def test_a_fleet_gets_each_robots_grants_and_its_process_key_and_nothing_else() -> None:
    """Robots a and b served by one process: each role has on each robot's keys exactly what it has for that robot
    alone; the process's command key is the service's to serve and the operator's to query; no third robot's key nor
    another process's, and the rules keep one id per role and flow."""
    a, b, c = (Keys("ddvs", name) for name in ("fleet_a", "fleet_b", "fleet_c"))
    fleet = Fleet((a, b))
    assert fleet.process == "fleet_a" and fleet.command_key == "ddvs/serve/fleet_a/command"  # as `ddvs serve` names it
    acl = router_config(fleet, certificate_identities(SCOPE), ["tls/localhost:7447"])["access_control"]
    alone = {k.robot: router_config(k, certificate_identities(SCOPE), ["tls/localhost:7447"])["access_control"]
             for k in (a, b)}
    ids = [rule["id"] for rule in acl["rules"]]
    assert len(ids) == len(set(ids)) and set(ids) == {rule["id"] for rule in alone["fleet_a"]["rules"]}
    assert {p["id"]: p["rules"] for p in acl["policies"]} == {p["id"]: p["rules"] for p in alone["fleet_a"]["policies"]}
    for role in ROLES:
        granted = _grants(acl, role)
        for keys in (a, b):
            own = {g for g in _grants(alone[keys.robot], role) if g[2].startswith(f"{keys.base}/")}
            assert own, (role, keys.base)
            assert {g for g in granted if g[2].startswith(f"{keys.base}/")} == own, (role, keys.base)
        assert not any(g[2].startswith(f"{c.base}/") for g in granted)
        serve_keys = {key for _, _, key in granted if key.startswith("ddvs/serve/")}
        assert serve_keys == ({fleet.command_key} if role in ("service", "operator") else set()), role
        assert all(key.startswith((f"{a.base}/", f"{b.base}/")) or key == fleet.command_key for _, _, key in granted)
    assert ("ingress", "declare_queryable", fleet.command_key) in _grants(acl, "service")
    assert ("ingress", "query", fleet.command_key) in _grants(acl, "operator")
    assert robots_granted(acl) == {a.base, b.base}
    named = Fleet((a, b), "cell1")
    named_acl = router_config(named, certificate_identities(SCOPE), ["tls/localhost:7447"])["access_control"]
    named_keys = {key for _, _, key in _grants(named_acl, "operator") if key.startswith("ddvs/serve/")}
    assert named_keys == {"ddvs/serve/cell1/command"}
    with pytest.raises(ValueError, match="given twice"):
        Fleet((a, b, a))
    with pytest.raises(ValueError, match="at least one robot"):
        Fleet(())
    with pytest.raises(ValueError, match="process name 'cell\\*'"):
        Fleet((a,), "cell*")


def test_a_fleets_configurations_name_every_robot_and_cover_each(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Each robot of the fleet is covered, a third is not; the process's command key is allowed, another process's
    is not (a `ddvs serve` process named otherwise than the rules would have its commands dropped)."""
    fleet = Fleet((Keys("ddvs", "fleet_a"), Keys("ddvs", "fleet_b")))
    for path in write_configs(tmp_path, fleet, "certs", "tls/localhost:7447"):
        assert "for ddvs/fleet_a, ddvs/fleet_b served by process 'fleet_a'; do not edit." in path.read_text()
        zenoh.Config.from_file(str(path))
    service_file = tmp_path / "service-mtls.json5"
    assert check_robot_covered(Keys("ddvs", "fleet_a"), service_file)
    assert check_robot_covered(Keys("ddvs", "fleet_b"), service_file)
    assert not check_robot_covered(Keys("ddvs", "fleet_c"), service_file)
    caplog.clear()
    with caplog.at_level(logging.ERROR, logger="ddvs.security"):
        assert check_process_covered("ddvs/serve/fleet_a/command", service_file)
        assert check_process_covered("ddvs/serve/fleet_b/command", None)  # no router configuration: nothing to check
        assert caplog.records == []
        assert not check_process_covered("ddvs/serve/fleet_b/command", service_file)
    [record] = caplog.records
    assert re.search(r"process command key 'ddvs/serve/fleet_b/command' is not allowed .* which allows "
                     r"\['ddvs/serve/fleet_a/command'\].*--process NAME", record.getMessage()), record.getMessage()


def test_every_topic_of_the_key_table_has_exactly_one_writing_role() -> None:
    """A topic added to `TOPICS` without a role that may write it fails here (the rules would silently deny it)."""
    for name in TOPICS:
        writers = [role for role, g in ROLE_GRANTS.items() if name in (*g.publish, *g.serve, *g.tokens)]
        assert len(writers) == 1, f"TOPICS[{name!r}] is written by {writers}; expected exactly one role"
        readers = [role for role, g in ROLE_GRANTS.items() if name in (*g.subscribe, *g.query, *g.watch)]
        assert readers, f"TOPICS[{name!r}] has no reading role"


def test_identity_and_role_errors_say_what_was_expected() -> None:
    with pytest.raises(ValueError, match="at least one certificate common name or username"):
        Identity()
    with pytest.raises(ValueError, match="unknown roles"):
        router_config(KEYS, {"admin": Identity(usernames=("root",))}, ["tls/localhost:7447"])
    with pytest.raises(ValueError, match="unknown role"):
        client_config("admin", ["tls/localhost:7447"])
    with pytest.raises(ValueError, match="certificate and key"):
        client_config("operator", ["tls/localhost:7447"], TlsFiles(ca=Path("ca.pem")), mtls=True)


def test_example_configurations_are_generated_and_load_in_zenoh(tmp_path: Path) -> None:
    shipped = REPO / "configs" / "security"
    written = write_configs(tmp_path, Keys("ddvs", "robot0"), "certs", "tls/localhost:7447")
    for path in written:
        assert (shipped / path.name).read_text(encoding="utf-8") == path.read_text(encoding="utf-8"), (
            f"configs/security/{path.name} is out of date: run "
            "`ddvs security init --robot robot0 --certs-dir certs --configs-only configs/security`")
        zenoh.Config.from_file(str(path))  # valid JSON5 with keys Zenoh knows
    assert render_json5({"mode": "client"}, "a\nb").startswith("// a\n// b\n{")


def _init(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "ddvs.cli", "security", "init", *args], capture_output=True,
                          text=True, cwd=cwd)


def test_security_init_is_idempotent_and_refuses_bad_input_before_writing(tmp_path: Path) -> None:
    first = _init("--robot", "ur5", "--roles", "service,operator", "secure", cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    out = tmp_path / "secure"
    written = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert {p.name for p in out.iterdir()} == {".gitignore", "ca", "router", "service", "operator",
                                               "router-mtls.json5", "router-password.json5", "service-mtls.json5",
                                               "service-password.json5", "operator-mtls.json5",
                                               "operator-password.json5"}
    service = json.loads(zenoh.Config.from_file(str(out / "service-mtls.json5")).get_json("transport"))
    assert service["link"]["tls"]["connect_certificate"] == "secure/service/service.pem"  # relative, as given
    assert (out / "service-password.json5").stat().st_mode & 0o077 == 0
    assert (out / "router" / "passwords.txt").stat().st_mode & 0o077 == 0
    again = _init("--robot", "ur5", "--roles", "service,operator", "secure", cwd=tmp_path)
    assert again.returncode == 0 and "created" not in again.stdout
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == written  # keys, certificates, passwords kept
    for args, error in ((["--robot", "ur5", "--roles", "admin"], "roles ['admin']: expected some of"),
                        (["--robot", "ur*"], "wildcard"),
                        ([], "no robot: give --robot NAME"),
                        (["--robot", "ur5", "--robot", "ur6", "--robot", "ur5"], "['ddvs/ur5'] given twice"),
                        (["--robot", "ur5", "--robot", "ur6", "--process", "cell*"], "process name 'cell*'"),
                        (["--robot", "ur5", "--router", "localhost:7447"], "expected '<protocol>/<address>'")):
        refused = _init(*args, "refused", cwd=tmp_path)
        assert refused.returncode != 0 and error in refused.stderr, refused.stderr
        assert not (tmp_path / "refused").exists()


def test_shipped_examples_agree_on_the_robot() -> None:
    """Every shipped service configuration names a robot the shipped router rules cover, and the one the clients use
    by default (`Keys()`): run as shipped, the operator's commands reach the service."""
    router = REPO / "configs" / "security" / "router-mtls.json5"
    granted = robots_granted(json.loads(zenoh.Config.from_file(str(router)).get_json("access_control")))
    assert granted == {Keys().base}
    for path in sorted((REPO / "configs" / "serve").glob("*.json")):
        config = json.loads(path.read_text(encoding="utf-8"))
        robot = Keys(config.get("prefix", "ddvs"), config.get("robot", Keys().robot))
        assert robot.base in granted, f"{path.name}: robot {robot.base} is not covered by {router.name}"
        assert check_robot_covered(robot, REPO / "configs" / "security" / "service-mtls.json5")


def test_a_robot_not_covered_by_the_router_beside_the_node_config_is_refused(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    write_configs(tmp_path, Keys("ddvs", "ur5"), "certs", "tls/localhost:7447", roles=["service", "operator"])
    service_file = tmp_path / "service-mtls.json5"
    with caplog.at_level(logging.ERROR, logger="ddvs.security"):
        assert check_robot_covered(Keys("ddvs", "ur5"), service_file)  # covered: nothing to say
        assert caplog.records == []
        assert not check_robot_covered(Keys("ddvs", "robot0"), service_file)
    [record] = caplog.records
    assert re.search(r"robot 'ddvs/robot0' is not covered .* grants \['ddvs/ur5'\].*ddvs security init --robot "
                     r"robot0", record.getMessage())
    lone = tmp_path / "alone" / "service.json5"
    lone.parent.mkdir()
    lone.write_text(service_file.read_text())
    assert check_robot_covered(Keys("ddvs", "robot0"), lone)  # no router configuration in sight: nothing to check
    assert check_robot_covered(Keys("ddvs", "robot0"), None)
    assert robots_granted({"enabled": False, "rules": []}) == set()


# --- warnings -------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("listen", "mode", "warned"),
    [
        (["tcp/127.0.0.1:7447"], "peer", []),
        (["tcp/localhost:7447", "tcp/[::1]:7448"], "router", []),
        (["tcp/0.0.0.0:7447"], "peer", ["tcp/0.0.0.0:7447"]),
        (["tcp/192.168.1.10:7447", "tls/0.0.0.0:7448"], "router", ["tcp/192.168.1.10:7447"]),
        (["udp/[::]:7447#iface=eth0"], "peer", ["udp/[::]:7447#iface=eth0"]),
        (["tls/[::]:7447", "quic/0.0.0.0:7448"], "router", []),
        ([], "peer", ["tcp/[::]:0"]),  # Zenoh's default for a peer listens on every interface
        ([], "client", []),
    ],
)
def test_warn_if_insecure(listen: list[str], mode: str, warned: list[str], caplog: pytest.LogCaptureFixture) -> None:
    connect = ["tcp/127.0.0.1:7447"] if mode == "client" else []
    config = SessionConfig(mode=mode, listen=listen, connect=connect)  # type: ignore[arg-type]
    logger = logging.getLogger("test.security")
    with caplog.at_level(logging.WARNING, logger="test.security"):
        assert warn_if_insecure(config, logger) == warned
    assert [r.fields["endpoint"] for r in caplog.records] == warned  # type: ignore[attr-defined]
    assert all("without TLS" in r.getMessage() for r in caplog.records)


def test_warn_if_insecure_reads_the_zenoh_config_file(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "router.json5"
    path.write_text(render_json5({"mode": "router", "listen": {"endpoints": ["tcp/0.0.0.0:7447"]}}, "x"))
    with caplog.at_level(logging.WARNING):
        bad = warn_if_insecure(SessionConfig(mode="router", zenoh_config=path), logging.getLogger("t"))
    assert bad == ["tcp/0.0.0.0:7447"]
