"""The ROS 2 graph over rmw_zenoh: liveliness tokens in rmw_zenoh's format, and the QoS string they carry.

Each ROS entity holds a Zenoh liveliness token while it exists (rmw_zenoh docs/design.md, "Graph Cache";
`rmw_zenoh_cpp/src/detail/liveliness_utils.cpp`, Jazzy 0.2.x, Kilted, Rolling); `ros2 node list`, `ros2 topic list`,
`ros2 topic info -v` and `ros2 service list` are answered from these tokens:

    node:     @ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node name>
    endpoint: @ros2_lv/<domain>/<zid>/<node id>/<entity id>/<MP|MS|SS|SC>/<enclave>/<namespace>/<node name>/
              <topic>/<DDS type name>/<type hash>/<qos>

`zid` is the Zenoh session id as Zenoh prints it, ids are decimal counters of the session (the context), every name
is mangled ('/' → '%'; the root namespace and the default enclave "/" become "%"). The qos chunk is
`<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<s>,<ns>` with the
`rmw_qos_*` enum values, each left empty where it equals rmw_zenoh's default (reliable, volatile, keep last 42,
infinite durations, automatic liveliness): keep-last 1 reliable is `::,1:,:,:,,`. rmw_zenoh's entity gid (the
publisher gid in attachments, `ros2 topic info -v`) is the XXH3-128 hash of the token, low then high 64 bits.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

import xxhash
import zenoh

ADMIN_SPACE = "@ros2_lv"
SERVO_NODE, CAMERA_NODE, BRIDGE_NODE, ARM_SIM_NODE = "ddvs_servo", "ddvs_camera", "ddvs_bridge", "ddvs_arm_sim"
"""The default ROS node names of `ddvs serve`, `ddvs camera`, `ddvs bridge` and `ddvs sim arm` (docs/ros2.md)."""
TRIGGER = "std_srvs/srv/Trigger"
EntityKind = Literal["NN", "MP", "MS", "SS", "SC"]
ENTITY_KINDS: tuple[EntityKind, ...] = ("NN", "MP", "MS", "SS", "SC")
_KIND_OF: dict[str, EntityKind] = {kind: kind for kind in ENTITY_KINDS}  # a token's chunk → its kind

_RELIABILITY = {"reliable": 1, "best_effort": 2}
_DURABILITY = {"transient_local": 1, "volatile": 2}
_HISTORY = {"keep_last": 1, "keep_all": 2}
_DEFAULT_DEPTH = 42  # rmw_zenoh's depth for KEEP_LAST with depth 0 ("system default"), and its token default
_NAME_TOKEN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclass(frozen=True)
class RosQos:
    """The QoS an entity announces: `reliability`, `durability`, `history` and `depth` (deadline, lifespan and
    liveliness stay at rmw_zenoh's defaults, the only ones it implements)."""

    reliability: Literal["reliable", "best_effort"] = "reliable"
    durability: Literal["volatile", "transient_local"] = "volatile"
    history: Literal["keep_last", "keep_all"] = "keep_last"
    depth: int = _DEFAULT_DEPTH

    def __post_init__(self) -> None:
        for what, value, table in (("reliability", self.reliability, _RELIABILITY),
                                   ("durability", self.durability, _DURABILITY),
                                   ("history", self.history, _HISTORY)):
            if value not in table:
                raise ValueError(f"QoS {what} {value!r}; expected one of {', '.join(table)}")
        if not (isinstance(self.depth, int) and self.depth >= 1):
            raise ValueError(f"QoS depth {self.depth!r}; expected an integer ≥ 1")

    def encode(self) -> str:
        """rmw_zenoh's `qos_to_keyexpr`: fields equal to its defaults are left empty."""
        reliability = "" if self.reliability == "reliable" else str(_RELIABILITY[self.reliability])
        durability = "" if self.durability == "volatile" else str(_DURABILITY[self.durability])
        history = "" if self.history == "keep_last" else str(_HISTORY[self.history])
        depth = "" if self.depth == _DEFAULT_DEPTH else str(self.depth)
        return f"{reliability}:{durability}:{history},{depth}:,:,:,,"


SENSOR_DATA_QOS = RosQos(reliability="best_effort", depth=5)
"""rclcpp's `SensorDataQoS` (camera drivers publish images and camera info with it)."""
LATEST_QOS = RosQos(depth=1)
"""Reliable, keep the newest sample only: commands, twists, joint states."""
SERVICE_QOS = RosQos(depth=10)
"""`rmw_qos_profile_services_default`."""


def mangle(name: str) -> str:
    return name.replace("/", "%")


def check_ros_name(what: str, name: str) -> None:
    """A fully qualified ROS name: '/' or '/'-separated tokens `[A-Za-z_][A-Za-z0-9_]*` after a leading '/'."""
    if name == "/":
        return
    tokens = name[1:].split("/") if name.startswith("/") else None
    if tokens is None or not all(_NAME_TOKEN.match(t) for t in tokens):
        raise ValueError(f"{what} {name!r} is not a fully qualified ROS name: expected '/' followed by "
                         "'/'-separated tokens of letters, digits and '_' not starting with a digit")


@dataclass(frozen=True)
class GraphNode:
    """A ROS node as the graph sees it: domain, namespace ('/' or '/a/b'), name, enclave."""

    domain_id: int
    namespace: str
    name: str
    enclave: str = "/"

    def __post_init__(self) -> None:
        if not 0 <= self.domain_id <= 232:
            raise ValueError(f"ROS domain id {self.domain_id}: expected an integer in [0, 232]")
        check_ros_name("namespace", self.namespace)
        if not _NAME_TOKEN.match(self.name):
            raise ValueError(f"node name {self.name!r}: expected letters, digits and '_', not starting with a digit")


@dataclass(frozen=True)
class GraphEntity:
    """One liveliness token's content (`parse_token`), or what `token()` writes."""

    zid: str
    node_id: int
    entity_id: int
    kind: EntityKind
    node: GraphNode
    topic: str | None = None  # fully qualified topic or service name
    dds_type: str | None = None
    type_hash: str | None = None
    qos: str | None = None

    def token(self) -> str:
        node = self.node
        parts = [ADMIN_SPACE, str(node.domain_id), self.zid, str(self.node_id), str(self.entity_id), self.kind,
                 mangle(node.enclave), mangle(node.namespace), node.name]
        if self.kind != "NN":
            if None in (self.topic, self.dds_type, self.type_hash, self.qos):
                raise ValueError(f"a {self.kind} token needs a topic, a type, a type hash and a QoS")
            parts += [mangle(self.topic or ""), self.dds_type or "", self.type_hash or "", self.qos or ""]
        return "/".join(parts)

    def gid(self) -> bytes:
        """rmw_zenoh's gid of this entity: XXH3-128 of its token, low 64 bits then high 64 bits, little-endian."""
        h = xxhash.xxh3_128_intdigest(self.token().encode())
        return (h & (2**64 - 1)).to_bytes(8, "little") + (h >> 64).to_bytes(8, "little")


def parse_token(keyexpr: str) -> GraphEntity:
    """Read a liveliness token as rmw_zenoh's `Entity::make(keyexpr)` does; ValueError names what is wrong."""
    parts = keyexpr.split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE or not all(parts):
        raise ValueError(f"{keyexpr!r}: expected '{ADMIN_SPACE}/<domain>/<zid>/<nid>/<id>/<kind>/<enclave>/"
                         "<namespace>/<name>[/<topic>/<type>/<hash>/<qos>]' with no empty chunk")
    kind = _KIND_OF.get(parts[5])
    if kind is None:
        raise ValueError(f"{keyexpr!r}: entity kind {parts[5]!r}; expected one of {', '.join(ENTITY_KINDS)}")
    node = GraphNode(int(parts[1]), parts[7].replace("%", "/"), parts[8], parts[6].replace("%", "/"))
    if kind == "NN":
        return GraphEntity(parts[2], int(parts[3]), int(parts[4]), kind, node)
    if len(parts) != 13:
        raise ValueError(f"{keyexpr!r}: a {kind} token has 13 chunks, this one {len(parts)}")
    if len(parts[12].split(":")) != 6:
        raise ValueError(f"{keyexpr!r}: QoS {parts[12]!r} does not have rmw_zenoh's 6 ':'-separated fields")
    return GraphEntity(parts[2], int(parts[3]), int(parts[4]), kind, node, parts[9].replace("%", "/"), parts[10],
                       parts[11], parts[12])


def discover(session: zenoh.Session, domain_id: int, timeout: float = 1.0) -> list[GraphEntity]:
    """Every entity of ROS domain `domain_id` in the graph now, as rmw_zenoh builds its graph cache (a liveliness
    query on `@ros2_lv/<domain>/**`): what `ros2 node list` / `ros2 topic list` would show. Tokens that do not parse
    as rmw_zenoh's are skipped."""
    entities = []
    for reply in session.liveliness().get(f"{ADMIN_SPACE}/{domain_id}/**", timeout=timeout):
        if reply.ok is None:
            continue
        try:
            entities.append(parse_token(str(reply.ok.key_expr)))
        except ValueError:
            continue
    return entities
