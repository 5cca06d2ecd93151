"""Zenoh transport security and access control for the servo system of one robot or of a fleet (docs/security.md).

Roles and what each may do, by entry of `keys.TOPICS` (deny by default, everything else is refused):

| role | publishes | subscribes | other |
|---|---|---|---|
| service | twist, status, config, state, reference (‡) | camera images (*), info | serves `servo/command`, token |
| plant | camera images (*) + info, joint states, ground truth | joint velocities (†), servo twist (free flyer) | |
| bridge | joint velocities (†) | servo twist, joint states | watches `servo/alive` token |
| operator | | every topic, the router's audit | queries `servo/command`, watches `servo/alive` |
| observer | | every topic (frames only if allowed), the router's audit | watches `servo/alive` |

(†) and the ROS 2 mode's `arm/velocity_commands` (`std_msgs/Float64MultiArray`). (‡) and the residual image
(`servo/residual`), withheld from observers with the frames. (*) raw, rectified, and both compressed
(`keys.CAMERA_IMAGES`).

A fleet is the robots one `ddvs serve` process serves (docs/deployment.md, "Many robots, one process"): each role gets
the same grants on every robot's keys (one rule per role and flow, naming the keys of every robot), and the process's
command key `<prefix>/serve/<process>/command` (`PROCESS_COMMAND`) is the service's to serve and the operator's to
query; no other robot's or process's key is allowed.

The rules are generated from `Keys`/`TOPICS` (`access_control`) so that they follow the key table; each role is
mapped to a Zenoh identity (`Identity`: TLS certificate common names and/or usernames of user/password
authentication), `<role>@<prefix>/<robot>` (`identity_name`; a fleet's: `<prefix>/<process>`), so that another
robot's identities match no role here (docs/security.md, "One CA per robot"). The rules are enforced by the router
that every client connects to (`router_config`); each role's client configuration comes from `client_config`. Flows
are seen from the router: `ingress` = sent by that client, `egress` = delivered to it, so a publication needs the
publisher's `put` (ingress) and the subscriber's `put` (egress).

`warn_if_insecure` logs a warning for every endpoint a session would listen on beyond loopback without TLS;
`check_robot_covered` tells whether the router configurations beside a node's own cover its robot, and
`check_process_covered` whether they allow a `ddvs serve` process's command key.
`write_configs` writes the configurations of a robot or a fleet (`ddvs security init`, which also issues the
certificates: `pki`).
"""

from __future__ import annotations

import ipaddress
import json
import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ddvs_service.protocol.audit import audit_key
from ddvs_service.protocol.control import process_command_key
from ddvs_service.protocol.keys import CAMERA_IMAGES, TOPICS, Keys
from ddvs_service.protocol.rmw import rmw_zenoh_key
from ddvs_service.protocol.ros_graph import (
    ADMIN_SPACE,
    ARM_SIM_NODE,
    BRIDGE_NODE,
    CAMERA_NODE,
    SERVO_NODE,
    TRIGGER,
)
from ddvs_service.protocol.session import SessionConfig

ROLES = ("service", "plant", "bridge", "operator", "observer")
FRAME_TOPICS = (*CAMERA_IMAGES, "servo_reference", "servo_residual")
AUDIT_READERS = ("operator", "observer")  # may read the router's audit summary (`audit.audit_key`)
SECURE_PROTOCOLS = ("tls", "quic")
_SCOPE = re.compile(r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$")
LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe", "vsock")


@dataclass(frozen=True)
class Grants:
    """What one role may do, as entries of `TOPICS`: `publish`/`subscribe` samples, `serve`/`query` queryables,
    hold (`tokens`) or `watch` liveliness tokens. `PROCESS_COMMAND` among `serve`/`query` names the command key of
    the `ddvs serve` process serving the robots (`<prefix>/serve/<process>/command`: add/remove/list robots; the
    process is named after its first robot unless named otherwise: `Fleet`). In ROS 2 mode only (`Keys.rmw`; nothing
    otherwise): `ROS_SERVICES` among `serve`/`query` names the service node's `std_srvs/srv/Trigger` services,
    `ROS_NODE_TOKENS` among `tokens` the graph tokens of the role's own ROS nodes (`ROLE_NODES`), `ROS_GRAPH` among
    `watch` every graph token of the ROS domain."""

    publish: tuple[str, ...] = ()
    subscribe: tuple[str, ...] = ()
    serve: tuple[str, ...] = ()
    query: tuple[str, ...] = ()
    tokens: tuple[str, ...] = ()
    watch: tuple[str, ...] = ()


PROCESS_COMMAND = "process_command"
ROS_SERVICES = "ros_services"
ROS_NODE_TOKENS = "ros_node_tokens"
ROS_GRAPH = "ros_graph"
ROLE_NODES: dict[str, tuple[str, ...]] = {
    "service": (SERVO_NODE,), "plant": (ARM_SIM_NODE, CAMERA_NODE), "bridge": (BRIDGE_NODE,),
}
"""The ROS node names (rmw_zenoh graph, ROS 2 mode) each role's programs declare."""
_SAMPLE_TOPICS = tuple(n for n in TOPICS if n not in ("servo_command", "liveliness"))

ROLE_GRANTS: dict[str, Grants] = {
    "service": Grants(
        publish=("servo_twist", "servo_status", "servo_config", "servo_state", "servo_reference", "servo_residual"),
        subscribe=(*CAMERA_IMAGES, "camera_info"),
        serve=("servo_command", PROCESS_COMMAND, ROS_SERVICES),
        tokens=("liveliness", ROS_NODE_TOKENS),
        watch=(ROS_GRAPH,),
    ),
    "plant": Grants(
        publish=(*CAMERA_IMAGES, "camera_info", "arm_joint_states", "arm_ground_truth"),
        subscribe=("arm_joint_velocity", "arm_velocity_commands", "servo_twist"),
        tokens=(ROS_NODE_TOKENS,), watch=(ROS_GRAPH,),
    ),
    "bridge": Grants(
        publish=("arm_joint_velocity", "arm_velocity_commands"), subscribe=("servo_twist", "arm_joint_states"),
        tokens=(ROS_NODE_TOKENS,), watch=("liveliness", ROS_GRAPH),
    ),
    "operator": Grants(subscribe=_SAMPLE_TOPICS, query=("servo_command", PROCESS_COMMAND, ROS_SERVICES),
                       watch=("liveliness", ROS_GRAPH)),
    "observer": Grants(subscribe=_SAMPLE_TOPICS, watch=("liveliness", ROS_GRAPH)),
}


def identity_name(role: str, scope: str) -> str:
    """The common name of `role`'s certificate in `scope` (the username of the user/password variant too):
    `<role>@<scope>`, e.g. `operator@ddvs/cell7`; `router` gives the router's."""
    return f"{role}@{scope}"


def check_scope(scope: str) -> str:
    """`scope` (`<prefix>/<robot>`, a fleet's `<prefix>/<process>`) when it can name certificates; else ValueError."""
    if not _SCOPE.match(scope):
        raise ValueError(f"certificate scope {scope!r}: expected '<prefix>/<robot>' of letters, digits, '_', '-', '.' "
                         "and '/' between chunks (e.g. 'ddvs/cell7')")
    return scope


@dataclass(frozen=True)
class Identity:
    """How the router recognises a role's sessions: certificate common names (mutual TLS) and/or usernames
    (user/password authentication). Names within a list are alternatives; both lists given means both must match
    (Zenoh's subject semantics)."""

    cert_common_names: tuple[str, ...] = ()
    usernames: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.cert_common_names and not self.usernames:
            raise ValueError("Identity: expected at least one certificate common name or username (an empty "
                             "identity would match every session)")


def certificate_identities(scope: str) -> dict[str, Identity]:
    """Each role recognised by its certificate's common name `<role>@<scope>` (`identity_name`, what
    `pki.issue_certificates` issues for `scope`, e.g. `ddvs/cell7`): another robot's certificates match no role."""
    return {role: Identity(cert_common_names=(identity_name(role, scope),)) for role in ROLES}


def password_identities(scope: str) -> dict[str, Identity]:
    """Each role recognised by its user/password username `<role>@<scope>`."""
    return {role: Identity(usernames=(identity_name(role, scope),)) for role in ROLES}


@dataclass(frozen=True)
class Fleet:
    """The robots whose keys a secured network carries, all served by one `ddvs serve` process named `process`
    (default: the first robot's name, as `service.fleet_config` names it); its command key is under the first robot's
    prefix. One robot is a fleet of one. Raises `ValueError` for no robot or a robot given twice."""

    robots: tuple[Keys, ...]
    process: str = ""

    def __post_init__(self) -> None:
        if not self.robots:
            raise ValueError("expected at least one robot")
        bases = [k.base for k in self.robots]
        twice = sorted({base for base in bases if bases.count(base) > 1})
        if twice:
            raise ValueError(f"robots {twice} given twice; expected each robot once")
        object.__setattr__(self, "process", self.process or self.robots[0].robot)
        try:
            Keys(self.robots[0].prefix, self.process)  # the same rules as a robot name
        except ValueError as exc:
            raise ValueError(f"process name {self.process!r}: {exc}") from None

    @classmethod
    def of(cls, keys: Keys | Fleet) -> Fleet:
        return keys if isinstance(keys, Fleet) else cls((keys,))

    @property
    def command_key(self) -> str:
        return process_command_key(self.robots[0].prefix, self.process)

    @property
    def scope(self) -> str:
        """`<prefix>/<process>` (one robot: `<prefix>/<robot>`): what every certificate, common name and username of
        this network belongs to (`pki`). ValueError when it cannot name certificates (`check_scope`)."""
        return check_scope(f"{self.robots[0].prefix}/{self.process}")

    def describe(self) -> str:
        """`ddvs/robot0` for one robot served by the process named after it; otherwise every robot and the
        process (`ddvs/a, ddvs/b served by process 'a'`)."""
        bases = ", ".join(k.base for k in self.robots)
        if len(self.robots) == 1 and self.process == self.robots[0].robot:
            return bases
        return f"{bases} served by process '{self.process}'"


def _rule(rule_id: str, flow: str, messages: Sequence[str], keys: Sequence[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": list(messages),
            "key_exprs": sorted(set(keys))}


def _ros_keys(name: str, keys: Keys, role: str) -> list[str]:
    """The key expressions of ROS 2 entry `name` (`ROS_SERVICES`, `ROS_NODE_TOKENS`, `ROS_GRAPH`) for `role` of one
    robot; none in plain mode. Graph tokens are `@ros2_lv/<domain>/<zid>/<nid>/<id>/<kind>/<enclave>/<namespace>/
    <node>/...` (`ros_graph`): a role's own are those of its node names, in any namespace, from any session."""
    domain = keys.ros.domain_id
    if domain is None:
        return []
    if name == ROS_GRAPH:
        return [f"{ADMIN_SPACE}/{domain}/**"]
    if name == ROS_NODE_TOKENS:
        return [f"{ADMIN_SPACE}/{domain}/{'*/' * 6}{node}/**" for node in ROLE_NODES.get(role, ())]
    return [rmw_zenoh_key(domain, f"{keys.ros.namespace.rstrip('/')}/{SERVO_NODE}/*", TRIGGER)]


def _role_rules(role: str, grants: Grants, fleet: Fleet) -> list[dict[str, Any]]:
    """The allow rules of one role (ids `<role>/<what>`), flows seen from the router; each names the keys of every
    robot of `fleet` (the process's command key once)."""
    def k(names: Sequence[str]) -> list[str]:
        out = []
        for keys in fleet.robots:
            for name in names:
                if name == PROCESS_COMMAND:
                    out.append(fleet.command_key)
                elif name in (ROS_SERVICES, ROS_NODE_TOKENS, ROS_GRAPH):
                    out.extend(_ros_keys(name, keys, role))
                else:
                    out.append(keys.key(name))
        return out

    pub, sub = k(grants.publish), k(grants.subscribe)
    if role in AUDIT_READERS:  # published by the router itself (`ddvs router`), so no role writes it
        sub.extend(audit_key(keys.base) for keys in fleet.robots)
    serve, query = k(grants.serve), k(grants.query)
    tokens, watch = k(grants.tokens), k(grants.watch)
    candidates = [
        ("publish", "ingress", ["put"], pub),
        ("publish-interest", "egress", ["declare_subscriber"], pub),
        ("subscribe", "ingress", ["declare_subscriber"], sub),
        ("subscribe-deliver", "egress", ["put"], sub),
        ("serve", "ingress", ["declare_queryable", "reply"], serve),
        ("serve-deliver", "egress", ["query"], serve),
        ("query", "ingress", ["query"], query),
        ("query-deliver", "egress", ["reply", "declare_queryable"], query),
        ("token", "ingress", ["liveliness_token"], tokens),
        ("token-interest", "egress", ["declare_liveliness_subscriber", "liveliness_query"], tokens),
        ("watch", "ingress", ["declare_liveliness_subscriber", "liveliness_query"], watch),
        ("watch-deliver", "egress", ["liveliness_token"], watch),
    ]
    return [_rule(f"{role}/{what}", flow, msgs, ks) for what, flow, msgs, ks in candidates if ks]


def role_grants(observers_read_frames: bool = True) -> dict[str, Grants]:
    """`ROLE_GRANTS`, with camera frames and the reference image withheld from observers unless allowed."""
    if observers_read_frames:
        return dict(ROLE_GRANTS)
    observer = ROLE_GRANTS["observer"]
    subscribe = tuple(n for n in observer.subscribe if n not in FRAME_TOPICS)
    return {**ROLE_GRANTS, "observer": Grants(subscribe=subscribe, watch=observer.watch)}


def access_control(
    keys: Keys | Fleet, identities: Mapping[str, Identity], observers_read_frames: bool = True
) -> dict[str, Any]:
    """The router's `access_control` section for one robot (`keys`) or a `Fleet`: deny by default, allow rules per
    role of `identities` (roles absent from `identities` get nothing). Raises `ValueError` for an unknown role."""
    unknown = set(identities) - set(ROLES)
    if unknown:
        raise ValueError(f"unknown roles {sorted(unknown)}; expected some of {', '.join(ROLES)}")
    grants = role_grants(observers_read_frames)
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for role in ROLES:
        if role not in identities:
            continue
        ident = identities[role]
        subject: dict[str, Any] = {"id": f"role:{role}"}
        if ident.cert_common_names:
            subject["cert_common_names"] = list(ident.cert_common_names)
        if ident.usernames:
            subject["usernames"] = list(ident.usernames)
        role_rules = _role_rules(role, grants[role], Fleet.of(keys))
        rules.extend(role_rules)
        subjects.append(subject)
        policies.append({"id": f"policy:{role}", "rules": [r["id"] for r in role_rules], "subjects": [subject["id"]]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


@dataclass(frozen=True)
class TlsFiles:
    """PEM files of one node: the CA that signs every peer's certificate (`ca`), and this node's own certificate and
    private key (`certificate`, `key`; required for listening and for mutual TLS)."""

    ca: Path
    certificate: Path | None = None
    key: Path | None = None

    @classmethod
    def for_role(cls, cert_dir: str | Path, role: str) -> TlsFiles:
        """The files `pki.issue_certificates(DIR, ...)` writes for `role` or the router (`DIR/<role>/ca.pem`,
        `DIR/<role>/<role>.pem|.key`)."""
        d = Path(cert_dir) / role
        return cls(ca=d / "ca.pem", certificate=d / f"{role}.pem", key=d / f"{role}.key")

    def section(self, mtls: bool, listening: bool) -> dict[str, Any]:
        """The `transport/link/tls` section (paths as given; Zenoh resolves them against its working directory). A
        connecting node verifies that the server's certificate names the host it connects to
        (`verify_name_on_connect`): only the router's certificate does (`pki`)."""
        out: dict[str, Any] = {"root_ca_certificate": str(self.ca), "enable_mtls": mtls}
        if not listening:
            out["verify_name_on_connect"] = True
        if mtls or listening:
            if self.certificate is None or self.key is None:
                raise ValueError(f"TLS {'mutual authentication' if mtls else 'listening'} needs this node's "
                                 "certificate and key; expected TlsFiles(certificate=..., key=...)")
            if listening:
                out.update(listen_certificate=str(self.certificate), listen_private_key=str(self.key))
            if mtls:
                out.update(connect_certificate=str(self.certificate), connect_private_key=str(self.key))
        return out


def router_config(
    keys: Keys | Fleet,
    identities: Mapping[str, Identity],
    listen: Sequence[str],
    tls: TlsFiles | None = None,
    mtls: bool = True,
    password_file: str | Path | None = None,
    observers_read_frames: bool = True,
) -> dict[str, Any]:
    """The hub router's Zenoh configuration: `listen` endpoints (e.g. `tls/localhost:7447`), TLS (mutual when `mtls`),
    user/password authentication when `password_file` (lines `user:password`) is given, and the access control of
    `access_control`. Multicast scouting is off; clients reach the robot only through this router."""
    config: dict[str, Any] = {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "access_control": access_control(keys, identities, observers_read_frames),
    }
    transport: dict[str, Any] = {}
    if tls is not None:
        transport["link"] = {"tls": tls.section(mtls=mtls, listening=True)}
    if password_file is not None:
        transport["auth"] = {"usrpwd": {"dictionary_file": str(password_file)}}
    if transport:
        config["transport"] = transport
    return config


def client_config(
    role: str,
    router: Sequence[str],
    tls: TlsFiles | None = None,
    mtls: bool = True,
    credentials: tuple[str, str] | None = None,
) -> dict[str, Any]:
    """The Zenoh configuration of a `role`'s node as a client of the hub router at `router` endpoints: TLS with
    this role's certificate (mutual TLS when `mtls`) and/or user/password `credentials = (user, password)`."""
    if role not in ROLES:
        raise ValueError(f"unknown role {role!r}; expected one of {', '.join(ROLES)}")
    if not router:
        raise ValueError(f"client_config({role!r}): expected at least one router endpoint, e.g. 'tls/localhost:7447'")
    config: dict[str, Any] = {
        "mode": "client",
        "connect": {"endpoints": list(router)},
        "scouting": {"multicast": {"enabled": False}},
    }
    transport: dict[str, Any] = {}
    if tls is not None:
        transport["link"] = {"tls": tls.section(mtls=mtls, listening=False)}
    if credentials is not None:
        user, password = credentials
        transport["auth"] = {"usrpwd": {"user": user, "password": password}}
    if transport:
        config["transport"] = transport
    return config


def render_json5(config: Mapping[str, Any], comment: str) -> str:
    """A configuration as a JSON5 file (JSON with a `//` comment header), for `zenoh.Config.from_file`."""
    header = "".join(f"// {line}\n" if line else "//\n" for line in comment.splitlines())
    return header + json.dumps(config, indent=2) + "\n"


@dataclass(frozen=True)
class Endpoint:
    """One Zenoh locator `<protocol>/<address>[?metadata][#config]`, reduced to what security checks need."""

    protocol: str
    host: str
    raw: str = field(compare=False)

    @classmethod
    def parse(cls, endpoint: str) -> Endpoint:
        protocol, sep, rest = endpoint.partition("/")
        if not sep or not protocol or not rest:
            raise ValueError(f"endpoint {endpoint!r}: expected '<protocol>/<address>', e.g. 'tls/localhost:7447'")
        address = rest.split("#", 1)[0].split("?", 1)[0]
        if address.startswith("["):
            host = address[1:].split("]", 1)[0]
        else:
            host = address.rsplit(":", 1)[0] if ":" in address else address
        return cls(protocol.lower(), host, endpoint)

    @property
    def loopback(self) -> bool:
        """True for local-only transports and loopback addresses (`localhost`, 127.0.0.0/8, ::1)."""
        if self.protocol in LOCAL_PROTOCOLS or self.host == "localhost":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False  # a host name other than localhost may resolve to any interface

    @property
    def secure(self) -> bool:
        return self.protocol in SECURE_PROTOCOLS


def listen_endpoints(session_config: SessionConfig) -> list[str]:
    """The endpoints a session with these settings listens on, as Zenoh resolves them (file, fields, overrides and
    Zenoh's defaults, e.g. `tcp/[::]:0` for a peer with no `listen`)."""
    config = session_config.to_zenoh_config()
    value = json.loads(config.get_json("listen/endpoints"))
    if isinstance(value, dict):  # Zenoh's per-mode form {router: [...], peer: [...], client: [...]}
        value = value.get(session_config.mode, [])
    return [str(e) for e in value or []]


def insecure_endpoints(session_config: SessionConfig) -> list[str]:
    """Listen endpoints reachable beyond this host (not loopback) that do not use TLS."""
    return [e for e in listen_endpoints(session_config) if not (Endpoint.parse(e).loopback or Endpoint.parse(e).secure)]


def warn_if_insecure(session_config: SessionConfig, logger: logging.Logger) -> list[str]:
    """Log one warning (structured fields `endpoint`, `mode`) per listen endpoint beyond loopback without TLS; return
    those endpoints (empty: nothing to warn about). Plain TCP is for loopback-only demos (docs/security.md)."""
    bad = insecure_endpoints(session_config)
    for endpoint in bad:
        logger.warning(
            "listening beyond loopback without TLS: any host that reaches this address can join the Zenoh network; "
            "use a tls/ endpoint with access control (docs/security.md) or a loopback address",
            extra={"fields": {"endpoint": endpoint, "mode": session_config.mode}},
        )
    return bad


PASSWORD_PLACEHOLDER = "CHANGE-ME-{role}"


def write_configs(
    out_dir: str | Path,
    keys: Keys | Fleet,
    cert_dir: str,
    router: str,
    roles: Sequence[str] = ROLES,
    passwords: Mapping[str, str] | None = None,
    observers_read_frames: bool = True,
) -> list[Path]:
    """Write every Zenoh configuration of the secured network of one robot or a `Fleet` into `out_dir`:
    `router-mtls.json5` (mutual TLS, identities by certificate), `router-password.json5` (server TLS + user/password
    from `<cert_dir>/router/passwords.txt`), and per role `<role>-mtls.json5` and `<role>-password.json5` client
    configurations; every identity is `<role>@<scope>` (`Fleet.scope`). Certificate paths are
    `<cert_dir>/<role>/...` as written (`pki` layout; Zenoh resolves relative paths against the node's working
    directory). `passwords` (role → password) go into the client files, which are then readable by their owner only;
    without them the files carry `CHANGE-ME-<role>`. Returns the paths written."""
    unknown = [r for r in roles if r not in ROLES]
    if unknown or not roles:
        raise ValueError(f"roles {list(roles)}: expected one or more of {', '.join(ROLES)}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, tuple[dict[str, Any], str]] = {}
    listen, tls_router = [router], TlsFiles.for_role(cert_dir, "router")
    scope = Fleet.of(keys).scope
    by_cert = {r: i for r, i in certificate_identities(scope).items() if r in roles}
    by_user = {r: i for r, i in password_identities(scope).items() if r in roles}
    files["router-mtls.json5"] = (
        router_config(keys, by_cert, listen, tls_router, mtls=True, observers_read_frames=observers_read_frames),
        "Hub router: mutual TLS, each role recognised by its certificate's common name, deny-by-default access "
        "control.",
    )
    files["router-password.json5"] = (
        router_config(keys, by_user, listen, tls_router, mtls=False, password_file=f"{cert_dir}/router/passwords.txt",
                      observers_read_frames=observers_read_frames),
        "Hub router: server-side TLS, each role recognised by its user/password username (dictionary file of "
        "'user:password' lines), deny-by-default access control.",
    )
    for role in roles:
        files[f"{role}-mtls.json5"] = (
            client_config(role, [router], TlsFiles.for_role(cert_dir, role), mtls=True),
            f"The {role}'s node: client of the hub router, mutual TLS with the '{identity_name(role, scope)}' "
            "certificate.",
        )
        password = passwords[role] if passwords else PASSWORD_PLACEHOLDER.format(role=role)
        files[f"{role}-password.json5"] = (
            client_config(role, [router], TlsFiles(ca=Path(cert_dir) / role / "ca.pem"), mtls=False,
                          credentials=(identity_name(role, scope), password)),
            f"The {role}'s node: client of the hub router, server-side TLS and user/password "
            f"'{identity_name(role, scope)}'.",
        )
    written = []
    for name, (config, comment) in files.items():
        path = out / name
        header = f"{comment}\nGenerated by `ddvs security init` for {Fleet.of(keys).describe()}; do not edit."
        path.write_text(render_json5(config, header), encoding="utf-8")
        if passwords and name.endswith("-password.json5") and not name.startswith("router"):
            path.chmod(0o600)
        written.append(path)
    return written


def robots_granted(access_control: Mapping[str, Any]) -> set[str]:
    """The robots (`<prefix>/<robot>`) whose keys the allow rules of a router's `access_control` section name (keys
    ending in a `TOPICS` suffix); empty when access control is off (everything is allowed then)."""
    if not access_control.get("enabled"):
        return set()
    suffixes = [f"/{spec.suffix}" for spec in TOPICS.values()]
    return {key[: -len(suffix)] for rule in access_control.get("rules", []) for key in rule.get("key_exprs", [])
            for suffix in suffixes if key.endswith(suffix)}


def sibling_access_controls(zenoh_config: str | Path | None) -> dict[Path, dict[str, Any]]:
    """The `access_control` section of each router configuration (`router*.json5`) with access control on, in the
    directory of a node's Zenoh configuration file, as `ddvs security init` writes them side by side; empty when
    there is none."""
    if zenoh_config is None:
        return {}
    import zenoh

    sections = {}
    for path in sorted(Path(zenoh_config).parent.glob("router*.json5")):
        section = json.loads(zenoh.Config.from_file(str(path)).get_json("access_control"))
        if section.get("enabled"):
            sections[path] = section
    return sections


def configured_scopes(out_dir: str | Path) -> set[str]:
    """The scopes (`Fleet.scope`) whose identities (`<role>@<scope>`) the router configurations in `out_dir` name."""
    return {name.split("@", 1)[1] for section in sibling_access_controls(Path(out_dir) / "-").values()
            for subject in section.get("subjects", [])
            for name in (*(subject.get("cert_common_names") or []), *(subject.get("usernames") or [])) if "@" in name}


def _allowed_keys(sections: Mapping[Path, Mapping[str, Any]]) -> set[str]:
    """Every key expression the allow rules of these `access_control` sections name."""
    return {key for section in sections.values() for rule in section.get("rules", [])
            for key in rule.get("key_exprs", [])}


def check_robot_covered(keys: Keys, zenoh_config: str | Path | None, logger: logging.Logger | None = None) -> bool:
    """False, with the reason logged as an error (`logger`, default `ddvs.security`), when router configurations
    beside the node's Zenoh configuration file grant nothing to robot `keys.base`, or in ROS 2 mode (`keys.rmw`) do not
    name the rmw_zenoh key of each of its ROS topics (rules made without `--ros-domain-id`, or for another domain,
    namespace or remapping): that router would silently drop every message of this robot, or of its ROS topics. True
    when they grant it or when there is none in sight."""
    log = logger or logging.getLogger("ddvs.security")
    sections = sibling_access_controls(zenoh_config)
    grants = {path: robots_granted(section) for path, section in sections.items()}
    if not grants:
        return True
    if any(keys.base in robots for robots in grants.values()):
        allowed = _allowed_keys(sections)
        missing = [keys.key(row) for row, spec in TOPICS.items() if keys.rmw and spec.ros_type is not None
                   and keys.key(row) not in allowed]
        if not missing:
            return True
        ros = keys.ros
        remaps = "".join(f" --ros-topic {row}:={name}" for row, name in ros.topics.items())
        log.error(f"ROS 2 mode (domain {ros.domain_id}, namespace {ros.namespace!r}) of robot {keys.base!r} is not "
                  f"covered by the access control of {', '.join(str(p) for p in sections)} (beside {zenoh_config}): "
                  f"it names none of {missing}, so that router would drop every ROS topic of this node. Make rules "
                  f"for this ROS set-up: `ddvs security init --robot {keys.robot} --prefix {keys.prefix} "
                  f"--ros-domain-id {ros.domain_id} --ros-namespace {ros.namespace}{remaps} OUT/`",
                  extra={"fields": {"robot": keys.base, "missing": missing,
                                    "router_configs": [str(p) for p in sections]}})
        return False
    granted = sorted(set().union(*grants.values()))
    log.error(
        f"robot {keys.base!r} is not covered by the access control of {', '.join(str(p) for p in grants)} (beside "
        f"{zenoh_config}), which grants {granted or 'no robot'}: that router would drop every message of this robot. "
        f"Use the robot those rules were made for, or make rules for this one: `ddvs security init --robot "
        f"{keys.robot} --prefix {keys.prefix} OUT/` (one --robot per robot of a `ddvs serve` process)",
        extra={"fields": {"robot": keys.base, "granted": granted, "router_configs": [str(p) for p in grants]}})
    return False


def check_process_covered(command_key: str, zenoh_config: str | Path | None,
                          logger: logging.Logger | None = None) -> bool:
    """False, with the reason logged as an error (`logger`, default `ddvs.security`), when router configurations
    beside the node's Zenoh configuration file do not allow the command key of a `ddvs serve` process
    (`<prefix>/serve/<process>/command`): that router would drop every `add_robot`, `remove_robot` and `list_robots`.
    True when they allow it or when there is none in sight."""
    sections = sibling_access_controls(zenoh_config)
    allowed = _allowed_keys(sections)
    if not sections or command_key in allowed:
        return True
    robots = set().union(*(robots_granted(section) for section in sections.values()))
    robot_commands = {f"{base}/{TOPICS['servo_command'].suffix}" for base in robots}  # not a process's key
    processes = sorted(k for k in allowed if "/serve/" in k and k.endswith("/command") and k not in robot_commands)
    (logger or logging.getLogger("ddvs.security")).error(
        f"process command key {command_key!r} is not allowed by the access control of "
        f"{', '.join(str(p) for p in sections)} (beside {zenoh_config}), which allows {processes or 'no process key'}:"
        " that router would drop every add_robot, remove_robot and list_robots. Name the process as those rules do "
        "(`ddvs serve --process NAME`, or `process` in its configuration), or make rules for it: `ddvs security init "
        "--robot A --robot B --process NAME OUT/`",
        extra={"fields": {"command_key": command_key, "allowed": processes,
                          "router_configs": [str(p) for p in sections]}})
    return False
