"""A robot's certificates are its own (docs/security.md, "One CA per robot"): `ddvs security init` for robots cell7
and cell8 as the docs tell a user, the real `ddvs router` of cell7, real client sessions over mutual TLS on loopback.

- `security init` never mixes two robots: an OUT holding another robot's CA (or its configurations, or a CA that
  names no robot) is refused before anything is written.
- cell8's certificates, every role's, fail cell7's TLS handshake (cell7's router trusts cell7's CA only), and the
  router's audit counts each refusal; cell7's own operator is answered in the same network (control).
- cell8's router certificate on cell7's router endpoint is refused by every cell7 client, which stays disconnected
  and sends nothing there; cell7's router back on the same endpoint is joined again (control).
- Even under a CA the robots would share (not what the docs set up: made by hand here), cell8's identities are
  `<role>@ddvs/cell8`, which matches no role of cell7's rules: nothing of theirs is delivered, and the audit lists each
  as a session without a role, named with its robot.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import zenoh
from conftest import free_port
from test_security import Inbox, _put_until
from test_security_audit import audit_lines, ddvs_router, newest_report

from ddvs_service.protocol import Keys
from ddvs_service.protocol.audit import audit_key
from ddvs_service.protocol.security import ROLES, TlsFiles, client_config

CELL7, CELL8 = Keys("ddvs", "cell7"), Keys("ddvs", "cell8")
RETRY_S = 5.0  # clients retry their router every 1–4 s


def init(robot: str, out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "ddvs.cli", "security", "init", "--robot", robot, *extra, str(out)],
                          capture_output=True, text=True)


def tree(out: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}


def open_role(out: Path, role: str, endpoint: str) -> zenoh.Session:
    config = zenoh.Config.from_file(str(out / f"{role}-mtls.json5"))
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return zenoh.open(config)


def test_security_init_never_mixes_two_robots(tmp_path: Path) -> None:
    cell7 = tmp_path / "cell7"
    assert init("cell7", cell7).returncode == 0
    before = tree(cell7)
    into_cell7 = init("cell8", cell7)  # cell8 into cell7's folder
    assert into_cell7.returncode != 0 and "is the CA of ddvs/cell7, not of ddvs/cell8" in into_cell7.stderr
    configs_only = init("cell8", cell7, "--configs-only")
    assert configs_only.returncode != 0 and "is the CA of ddvs/cell7" in configs_only.stderr
    assert tree(cell7) == before  # nothing of cell7's was touched
    cell8 = tmp_path / "cell8"  # cell7's CA copied beside cell8's files: refused, not reused
    shutil.copytree(cell7 / "ca", cell8 / "ca")
    copied = init("cell8", cell8)
    assert copied.returncode != 0 and "each robot has its own CA" in copied.stderr
    assert sorted(p.name for p in cell8.iterdir()) == ["ca"]
    configs = tmp_path / "configs"  # configurations of another robot, without a CA: refused too
    assert init("cell7", configs, "--configs-only").returncode == 0
    mixed = init("cell8", configs, "--configs-only")
    assert mixed.returncode != 0 and "holds the configurations of ddvs/cell7, not of ddvs/cell8" in mixed.stderr
    legacy = tmp_path / "legacy" / "ca"  # a CA naming no robot (as issued before certificates named one)
    legacy.mkdir(parents=True)
    subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
                    "-keyout", str(legacy / "ca.key"), "-out", str(legacy / "ca.pem"), "-days", "1", "-subj",
                    "/CN=ddvs development CA"], check=True, capture_output=True)
    old = init("cell8", legacy.parent)
    assert old.returncode != 0 and "names no robot" in old.stderr and f"delete {legacy}/" in old.stderr
    again = init("cell7", cell7)  # the robot's own folder: idempotent, as before
    assert again.returncode == 0 and "created" not in again.stdout and tree(cell7) == before
    common_names = subprocess.run(["openssl", "x509", "-in", str(cell7 / "operator" / "operator.pem"), "-noout",
                                   "-subject", "-issuer"], capture_output=True, text=True, check=True).stdout
    assert "CN = operator@ddvs/cell7" in common_names and "CN = ddvs CA for ddvs/cell7" in common_names


@pytest.mark.slow
def test_another_robots_certificates_and_router_are_refused(tmp_path: Path) -> None:
    endpoint = f"tls/localhost:{free_port()}"
    cell7, cell8 = tmp_path / "cell7", tmp_path / "cell8"
    for keys, out in ((CELL7, cell7), (CELL8, cell8)):  # absolute OUT: the files hold absolute paths
        assert init(keys.robot, out, "--router", endpoint).returncode == 0
    log = tmp_path / "router.log"
    sessions: list[zenoh.Session] = []
    try:
        with ddvs_router(cell7, endpoint, log):
            own = {role: open_role(cell7, role, endpoint) for role in ("service", "bridge", "operator", "observer")}
            sessions += own.values()
            own["service"].declare_queryable(CELL7.servo_command, lambda q: q.reply(q.key_expr, b"ok"))
            reports = Inbox(own["observer"], audit_key(CELL7.base))
            time.sleep(0.5)
            for role in ROLES:
                with pytest.raises(zenoh.ZError, match="Unable to connect"):
                    sessions.append(open_role(cell8, role, endpoint))
                    pytest.fail(f"cell8's {role} certificate joined cell7's router")
            replies = [r.ok.payload.to_bytes() for r in own["operator"].get(CELL7.servo_command, timeout=2.0) if r.ok]
            assert replies == [b"ok"]  # control: cell7's own operator is answered
            report = newest_report(reports, lambda r: r["tls_refused"] >= len(ROLES))
            assert report["tls_refused"] >= len(ROLES) and report["denied"] == report["no_role"] == {}, report
            assert sum(e["msg"] == "TLS handshake refused" for e in audit_lines(log)) >= len(ROLES)
        # cell7's router is down; cell8's router certificate takes its endpoint (rules off: it lets anything through)
        rogue_config = zenoh.Config.from_file(str(cell8 / "router-mtls.json5"))
        rogue_config.insert_json5("access_control", json.dumps({"enabled": False}))
        rogue = zenoh.open(rogue_config)
        heard = Inbox(rogue, f"{CELL7.base}/**")
        deadline = time.monotonic() + RETRY_S
        while time.monotonic() < deadline:
            own["service"].put(CELL7.servo_twist, b"twist")
            time.sleep(0.1)
        joined = [role for role, s in own.items() if s.info.routers_zid()]
        rogue.close()
        assert joined == [] and heard.payloads == [], f"cell7's {joined} joined cell8's router"
        with ddvs_router(cell7, endpoint, tmp_path / "router2.log"):  # control: cell7's own router, same endpoint
            twists = Inbox(own["bridge"], CELL7.servo_twist)
            assert _put_until(own["service"], CELL7.servo_twist, b"back", twists, timeout=RETRY_S + 3.0)
    finally:
        for session in reversed(sessions):
            session.close()


def _issue_by_hand(ca: Path, out: Path, common_name: str) -> TlsFiles:
    """A client certificate named `common_name` signed by the CA in `ca/`: what sharing one CA between robots
    would give (`ddvs security init` refuses to)."""
    out.mkdir(parents=True)
    key, pem = out / "node.key", out / "node.pem"
    with tempfile.TemporaryDirectory() as tmp:
        ext, csr = Path(tmp) / "ext.cnf", Path(tmp) / "req.csr"
        ext.write_text("extendedKeyUsage=clientAuth\n", encoding="utf-8")
        subprocess.run(["openssl", "req", "-new", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
                        "-keyout", str(key), "-subj", "/CN=" + common_name.replace("/", "\\/"), "-out", str(csr)],
                       check=True, capture_output=True)
        subprocess.run(["openssl", "x509", "-req", "-in", str(csr), "-CA", str(ca / "ca.pem"), "-CAkey",
                        str(ca / "ca.key"), "-CAcreateserial", "-CAserial", str(Path(tmp) / "ca.srl"), "-days", "1",
                        "-extfile", str(ext), "-out", str(pem)], check=True, capture_output=True)
    return TlsFiles(ca / "ca.pem", pem, key)


@pytest.mark.slow
def test_another_robots_identities_under_a_shared_ca_reach_nothing_and_are_named(tmp_path: Path) -> None:
    endpoint = f"tls/localhost:{free_port()}"
    cell7 = tmp_path / "cell7"
    assert init(CELL7.robot, cell7, "--router", endpoint).returncode == 0
    foreign = {role: _issue_by_hand(cell7 / "ca", tmp_path / "cell8" / role, f"{role}@{CELL8.base}")
               for role in ("service", "plant", "operator")}
    log = tmp_path / "router.log"
    sessions: list[zenoh.Session] = []
    with ddvs_router(cell7, endpoint, log):
        try:
            own = {role: open_role(cell7, role, endpoint) for role in ("service", "plant", "bridge", "observer",
                                                                       "operator")}
            sessions += own.values()
            served: list[bytes] = []

            def serve(query: zenoh.Query) -> None:
                served.append(query.payload.to_bytes() if query.payload is not None else b"")
                query.reply(query.key_expr, b"ok")

            own["service"].declare_queryable(CELL7.servo_command, serve)
            frames, twists = Inbox(own["service"], CELL7.camera_image), Inbox(own["bridge"], CELL7.servo_twist)
            reports = Inbox(own["observer"], audit_key(CELL7.base))
            intruders = {role: zenoh.open(zenoh.Config.from_json5(json.dumps(client_config(role, [endpoint], files))))
                         for role, files in foreign.items()}
            sessions += intruders.values()
            time.sleep(0.5)
            assert _put_until(own["plant"], CELL7.camera_image, b"frame", frames)  # controls: cell7's own roles
            assert _put_until(own["service"], CELL7.servo_twist, b"twist", twists)
            for _ in range(5):
                intruders["plant"].put(CELL7.camera_image, b"forged frame")
                intruders["service"].put(CELL7.servo_twist, b"forged twist")
            assert [r for r in intruders["operator"].get(CELL7.servo_command, payload=b"stop", timeout=1.0)
                    if r.ok] == []
            time.sleep(0.6)
            assert b"forged frame" not in frames.payloads and b"forged twist" not in twists.payloads and served == []
            assert [r for r in own["operator"].get(CELL7.servo_command, payload=b"get_state", timeout=2.0) if r.ok]
            assert served == [b"get_state"]  # control: cell7's own operator is answered
            named = {f"{role}@{CELL8.base}": 1 for role in foreign}
            report = newest_report(reports, lambda r: r["no_role"] == named)
            assert report["no_role"] == named and report["denied"] == {}, report
            lines = [e["identity"] for e in audit_lines(log) if e["msg"].startswith("session without a role")]
            assert sorted(lines) == sorted(named)
        finally:
            for session in reversed(sessions):
                session.close()
