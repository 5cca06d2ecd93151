"""Certificates per purpose for one robot's Zenoh network (docs/security.md), issued with the `openssl` command.

Every certificate belongs to one robot, or to one fleet (the robots one `ddvs serve` process serves): its *scope*,
`<prefix>/<robot>` (a fleet's: `<prefix>/<process>`, e.g. `ddvs/cell7`). Layout of a certificate directory `DIR`
(each node gets only its own sub-directory):

- `DIR/ca/ca.pem`, `ca.key`: the scope's own certificate authority, common name `ddvs CA for <scope>` (keep
  `ca.key` offline in production); one CA per scope, never shared by two robots;
- `DIR/router/ca.pem`, `router.pem`, `router.key`: the hub router's; common name `router@<scope>`, extended key
  usage **serverAuth only**, subject alternative names = the names clients connect to (`localhost`, `127.0.0.1` by
  default);
- `DIR/<role>/ca.pem`, `<role>.pem`, `<role>.key`: one node role's (`security.ROLES`); common name
  `<role>@<scope>` (`security.identity_name`), extended key usage **clientAuth only**, no subject alternative name.

Why per purpose: a client verifies the router's certificate chain, its serverAuth usage and that one of its names is
the host of the endpoint it connects to (Zenoh's `verify_name_on_connect`, on in every generated configuration), so
a role certificate cannot serve as a router (no serverAuth, no names). The router refuses client certificates without
clientAuth, so its own certificate cannot open a session either. The router's key lives in its own directory, never
where a node's configuration points.

Why per robot: a router and its clients trust their own robot's CA only, so another robot's certificates — its
router's included — fail the TLS handshake; the common names carry the scope as well, so the router's access control
(which matches common names) gives nothing to another robot's identity even under a CA they would share, and the
audit names the robot of each identity.

Idempotent: existing files are kept, missing ones issued; a new CA re-issues every certificate; a certificate whose
common name or (the router's) names differ from those asked for is re-issued. A CA of another scope (or of none) is
refused (`ValueError`), never reused. Rotation: delete a certificate (or the whole `ca/`) and run again. Keys are
ECDSA P-256 (PKCS#8 PEM, mode 0600); `DIR/.gitignore` is `*` so that no key gets committed.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import re
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from ddvs_service.protocol.security import ROLES, check_scope, identity_name

ROUTER = "router"
DEFAULT_ROUTER_NAMES = ("localhost", "127.0.0.1")
DAYS = 3650
_NAME = re.compile(r"^[A-Za-z0-9_-]+$")
CA_NAME = "ddvs CA for {scope}"


def _openssl(*args: str) -> str:
    if shutil.which("openssl") is None:
        raise RuntimeError("the openssl command was not found; install it (apt-get install openssl)")
    result = subprocess.run(["openssl", *args], capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"openssl {' '.join(args[:2])} failed: {result.stderr.strip()}")
    return result.stdout


def _new_key(path: Path) -> None:
    path.unlink(missing_ok=True)
    _openssl("genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", str(path))
    path.chmod(0o600)


def subject_alt_names(names: Sequence[str]) -> str:
    """The `subjectAltName` value for host `names` (`IP:` for addresses, `DNS:` otherwise), in the given order."""
    out = []
    for name in names:
        try:
            out.append(f"IP:{ipaddress.ip_address(name)}")
        except ValueError:
            out.append(f"DNS:{name}")
    return ",".join(out)


def _extensions(purpose: str, names: Sequence[str]) -> str:
    lines = ["basicConstraints=critical,CA:FALSE", "keyUsage=critical,digitalSignature,keyEncipherment",
             f"extendedKeyUsage={purpose}"]
    if names:
        lines.append(f"subjectAltName={subject_alt_names(names)}")
    return "\n".join(lines) + "\n"


def _subject(common_name: str) -> str:
    """`openssl -subj` of a common name ('/' escaped)."""
    return "/CN=" + common_name.replace("/", "\\/")


def _issue(directory: Path, name: str, common_name: str, ca: Path, ca_key: Path, purpose: str,
           names: Sequence[str]) -> Path:
    key, pem = directory / f"{name}.key", directory / f"{name}.pem"
    _new_key(key)
    with tempfile.TemporaryDirectory() as tmp:
        csr, ext = Path(tmp) / "req.csr", Path(tmp) / "ext.cnf"
        ext.write_text(_extensions(purpose, names), encoding="utf-8")
        _openssl("req", "-new", "-key", str(key), "-subj", _subject(common_name), "-out", str(csr))
        _openssl("x509", "-req", "-in", str(csr), "-CA", str(ca), "-CAkey", str(ca_key), "-CAcreateserial",
                 "-CAserial", str(Path(tmp) / "ca.srl"), "-sha256", "-days", str(DAYS), "-extfile", str(ext),
                 "-out", str(pem))
    _openssl("verify", "-CAfile", str(ca), str(pem))
    pem.chmod(0o644)
    return pem


def common_name(pem: Path) -> str:
    """The common name of a certificate's subject (empty when it has none)."""
    subject = _openssl("x509", "-in", str(pem), "-noout", "-subject", "-nameopt", "RFC2253").strip()
    parts = subject.removeprefix("subject=").split(",")
    return next((part[3:] for part in parts if part.startswith("CN=")), "")


def check_ca(ca: Path, scope: str) -> None:
    """ValueError unless the CA `ca` is `scope`'s (`CA_NAME`): a CA is never shared by two robots."""
    found = common_name(ca)
    if found == CA_NAME.format(scope=scope):
        return
    replace = (f"or delete {ca.parent}/ and run again to replace that CA (every certificate is then re-issued: "
               "redeploy them all)")
    if found.startswith(CA_NAME.format(scope="")):
        raise ValueError(f"{ca} is the CA of {found.removeprefix(CA_NAME.format(scope=''))}, not of {scope}: each "
                         f"robot has its own CA, so that no certificate of one robot passes another's TLS handshake. "
                         f"Write {scope}'s certificates into another directory, {replace}")
    raise ValueError(f"{ca} ({found!r}) names no robot (made before certificates were tied to one robot, or by "
                     f"hand), so it cannot be {scope}'s own CA: write {scope}'s certificates into another directory, "
                     f"{replace}")


def certificate_names(pem: Path) -> list[str]:
    """The subject alternative names of a certificate, as `subject_alt_names` writes them (empty when none)."""
    text = _openssl("x509", "-in", str(pem), "-noout", "-ext", "subjectAltName")
    values = text.split("\n", 1)[1] if "\n" in text else ""
    out = []
    for item in values.replace("\n", ",").split(","):
        kind, _, value = item.strip().partition(":")
        if value:
            out.append(f"{'IP' if kind == 'IP Address' else kind}:{value}")
    return out


def issue_certificates(
    directory: str | Path, roles: Sequence[str], scope: str, router_names: Sequence[str] = DEFAULT_ROUTER_NAMES
) -> list[Path]:
    """Make `directory` hold `scope`'s CA (`<prefix>/<robot>`, a fleet's `<prefix>/<process>`), the router's and each
    role's certificate (layout in the module docstring); returns the certificates issued now (empty when everything
    was already there). Raises ValueError, before writing anything, for a bad role or scope and when `directory`
    holds the CA of another scope."""
    check_scope(scope)
    for role in roles:
        if not _NAME.match(role) or role in (ROUTER, "ca"):
            raise ValueError(f"role {role!r}: expected letters, digits, '_' or '-', and not 'router' or 'ca'")
    if not router_names:
        raise ValueError("router_names: expected at least one host name or address the clients connect to")
    root = Path(directory)
    ca_dir = root / "ca"
    ca, ca_key = ca_dir / "ca.pem", ca_dir / "ca.key"
    if ca.is_file():
        check_ca(ca, scope)
    new_ca = not (ca.is_file() and ca_key.is_file())
    root.mkdir(parents=True, exist_ok=True)
    gitignore = root / ".gitignore"
    if not gitignore.exists():
        gitignore.write_text("*\n", encoding="utf-8")  # private keys never go into git
    ca_dir.mkdir(mode=0o700, exist_ok=True)
    issued: list[Path] = []
    if new_ca:
        _new_key(ca_key)
        _openssl("req", "-x509", "-new", "-key", str(ca_key), "-sha256", "-days", str(DAYS),
                 "-subj", _subject(CA_NAME.format(scope=scope)), "-addext", "basicConstraints=critical,CA:TRUE",
                 "-addext", "keyUsage=critical,keyCertSign,cRLSign", "-out", str(ca))
        ca.chmod(0o644)
        issued.append(ca)
    wanted = subject_alt_names(router_names).split(",")
    for name, purpose, names in ((ROUTER, "serverAuth", router_names),
                                 *((role, "clientAuth", ()) for role in roles)):
        node = root / name
        node.mkdir(exist_ok=True)
        pem, key = node / f"{name}.pem", node / f"{name}.key"
        stale = new_ca or not (pem.is_file() and key.is_file()) or common_name(pem) != identity_name(name, scope)
        if not stale and name == ROUTER:
            stale = certificate_names(pem) != wanted
        if stale:
            issued.append(_issue(node, name, identity_name(name, scope), ca, ca_key, purpose, names))
        if new_ca or not (node / "ca.pem").is_file():
            shutil.copyfile(ca, node / "ca.pem")
    return issued


def roles_from_env(default: Sequence[str]) -> list[str]:
    """`DDVS_CERT_ROLES` (space- or comma-separated role names) when set, else `default`."""
    value = os.environ.get("DDVS_CERT_ROLES", "")
    return value.replace(",", " ").split() or list(default)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="issue the development CA, the router's and each role's "
                                                 "certificate (idempotent)")
    parser.add_argument("directory")
    parser.add_argument("--robot", default="robot0",
                        help="the robot the certificates belong to (a fleet's: its `ddvs serve` process name); "
                             "default robot0, the robot of the shipped configs/security files")
    parser.add_argument("--prefix", default="ddvs", help="key prefix (default ddvs)")
    parser.add_argument("--roles", nargs="+", default=roles_from_env(ROLES),
                        help="role certificates to issue (default: $DDVS_CERT_ROLES or every role)")
    parser.add_argument("--router-name", action="append", dest="router_names", metavar="HOST",
                        help="a name clients use to reach the router (repeat; default localhost and 127.0.0.1)")
    args = parser.parse_args(argv)
    try:
        issued = issue_certificates(args.directory, args.roles, f"{args.prefix}/{args.robot}",
                                    args.router_names or DEFAULT_ROUTER_NAMES)
    except (RuntimeError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for path in issued:
        print(f"created {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
