"""The publishers, subscriptions and ROS services of one ddvs node, in plain-key or ROS 2 (rmw_zenoh) mode.

`Endpoints(session, keys, node_name)` declares what a node asks for and undeclares all of it in `close()`. With
`keys.rmw` false it is the plain ddvs protocol (`session.declare_publisher` with the row's QoS). In ROS 2 mode it
also declares the node's graph token and one token per ROS-typed endpoint (`ros_graph`), so the node shows in
`ros2 node list` / `ros2 topic list -t` / `ros2 topic info -v`, and each publisher of a ROS type puts every sample
with rmw_zenoh's attachment (sequence number, source time, the entity gid), without which rmw_zenoh subscriptions
drop it. JSON rows stay on their plain keys and outside the ROS graph in both modes.

In ROS 2 mode it also watches the graph (a liveliness subscription, as rmw_zenoh's graph cache): each ROS publisher
on a topic this node subscribes to is logged when it appears, and one with another type or type hash — a sample of
which can never arrive, the key holds the type hash — is a WARNING naming both types (logger `ddvs.endpoints`).

ROS services (`trigger_service`) are `std_srvs/srv/Trigger` queryables in rmw_zenoh's service layout: declared
complete on the service key, the request's attachment read back (sequence number and client gid) and echoed in the
reply's attachment with a new source time, a `SS` graph token.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from ddvs_service.protocol.errors import ProtocolError
from ddvs_service.protocol.keys import TOPICS, Keys
from ddvs_service.protocol.rmw import TYPE_HASHES, RmwAttachment, RmwPublisherIdentity, dds_type_name, rmw_zenoh_key
from ddvs_service.protocol.ros import decode_trigger_request, encode_trigger_response
from ddvs_service.protocol.ros_graph import (
    ADMIN_SPACE,
    SERVICE_QOS,
    TRIGGER,
    EntityKind,
    GraphEntity,
    GraphNode,
    parse_token,
)
from ddvs_service.protocol.session import LatestSubscriber, declare_publisher

log = logging.getLogger("ddvs.endpoints")


class Publisher:
    """`put(payload)` on one row's key; in ROS 2 mode each sample carries rmw_zenoh's attachment."""

    def __init__(self, publisher: zenoh.Publisher, identity: RmwPublisherIdentity | None) -> None:
        self._publisher, self._identity = publisher, identity

    def put(self, payload: bytes) -> None:
        if self._identity is None:
            self._publisher.put(payload)
        else:
            self._publisher.put(payload, attachment=self._identity.next_attachment())

    @property
    def matching_status(self) -> Any:
        """Whether some subscriber matches the key now (`.matching`). A `zenoh.MatchingStatus` at run time; zenoh
        1.10's type stub says `bool`."""
        return self._publisher.matching_status

    def declare_matching_listener(self, handler: Callable[[zenoh.MatchingStatus], None]) -> zenoh.MatchingListener:
        """Call `handler` whenever subscribers start or stop matching the key."""
        return self._publisher.declare_matching_listener(handler)

    def undeclare(self) -> None:
        self._publisher.undeclare()


class Endpoints:
    """Everything one node declares on `session`; `close()` undeclares it (idempotent). Not thread-safe: declare
    from one thread."""

    def __init__(self, session: zenoh.Session, keys: Keys, node_name: str) -> None:
        self.session, self.keys = session, keys
        self._undeclare: list[Callable[[], None]] = []  # in declaration order; undone in reverse
        self.node: GraphNode | None = None
        self.entities: list[GraphEntity] = []
        self._lock = threading.Lock()
        self._inputs: dict[str, tuple[str, str]] = {}  # subscribed ROS topic → (DDS type, type hash)
        self._publishers: dict[str, GraphEntity] = {}  # token → publisher seen in the graph
        if keys.rmw:
            ros = keys.ros
            assert ros.domain_id is not None
            self.node = GraphNode(ros.domain_id, ros.namespace, ros.node_name or node_name)
            self._zid = str(session.info.zid())
            self._declare_token(GraphEntity(self._zid, 0, 0, "NN", self.node))
            graph = session.liveliness().declare_subscriber(f"{ADMIN_SPACE}/{ros.domain_id}/**", self._on_graph,
                                                            history=True)
            self._undeclare.append(graph.undeclare)

    @property
    def node_fqn(self) -> str:
        """The node's fully qualified name (`/<namespace>/<name>`), the prefix of its private services."""
        assert self.node is not None
        return f"{self.node.namespace.rstrip('/')}/{self.node.name}"

    def _declare_token(self, entity: GraphEntity) -> GraphEntity:
        self._undeclare.append(self.session.liveliness().declare_token(entity.token()).undeclare)
        self.entities.append(entity)
        return entity

    def _endpoint(self, kind: EntityKind, topic: str, ros_type: str, qos: str) -> GraphEntity:
        assert self.node is not None
        entity = GraphEntity(self._zid, 0, len(self.entities), kind, self.node, topic, dds_type_name(ros_type),
                             TYPE_HASHES[ros_type], qos)
        return self._declare_token(entity)

    def _ros_row(self, name: str) -> bool:
        return self.keys.rmw and TOPICS[name].ros_type is not None

    def _row_endpoint(self, kind: EntityKind, name: str) -> GraphEntity:
        spec = TOPICS[name]
        assert spec.ros_type is not None and spec.ros_qos is not None
        entity = self._endpoint(kind, self.keys.ros_topic(name), spec.ros_type, spec.ros_qos.encode())
        if kind == "MS":
            assert entity.topic is not None and entity.dds_type is not None and entity.type_hash is not None
            with self._lock:
                self._inputs[entity.topic] = (entity.dds_type, entity.type_hash)
                present = [p for p in self._publishers.values() if p.topic == entity.topic]
            for publisher in present:
                self._report(publisher, (entity.dds_type, entity.type_hash))
        return entity

    def _on_graph(self, sample: zenoh.Sample) -> None:
        """Zenoh thread: remember ROS publishers, report those on this node's input topics (logging only)."""
        token = str(sample.key_expr)
        if sample.kind != zenoh.SampleKind.PUT:
            with self._lock:
                self._publishers.pop(token, None)
            return
        try:
            entity = parse_token(token)
        except ValueError:
            return
        if entity.kind != "MP" or entity.zid == self._zid:
            return
        with self._lock:
            self._publishers[token] = entity
            expected = self._inputs.get(entity.topic or "")
        if expected is not None:
            self._report(entity, expected)

    @staticmethod
    def _report(publisher: GraphEntity, expected: tuple[str, str]) -> None:
        node = f"{publisher.node.namespace.rstrip('/')}/{publisher.node.name}"
        found = (publisher.dds_type or "", publisher.type_hash or "")
        info = {"topic": publisher.topic, "node": node, "type": found[0], "type_hash": found[1]}
        if found == expected:
            log.info("ROS publisher on an input topic", extra={"fields": info})
        else:
            log.warning("ROS publisher on an input topic with another type: none of its samples can arrive (rmw_zenoh "
                        "keys hold the type hash); expected %s %s", *expected,
                        extra={"fields": {**info, "expected_type": expected[0], "expected_type_hash": expected[1]}})

    def publisher(self, name: str) -> Publisher:
        """A publisher of row `name` of `TOPICS` (with its QoS; a graph token and attachments in ROS 2 mode)."""
        identity = RmwPublisherIdentity(self._row_endpoint("MP", name).gid()) if self._ros_row(name) else None
        publisher = Publisher(declare_publisher(self.session, self.keys, name), identity)
        self._undeclare.append(publisher.undeclare)
        return publisher

    def subscriber(self, name: str, handler: Callable[[zenoh.Sample], None]) -> zenoh.Subscriber:
        """A callback subscription to row `name` (a graph token in ROS 2 mode)."""
        if self._ros_row(name):
            self._row_endpoint("MS", name)
        subscriber = self.session.declare_subscriber(self.keys.key(name), handler)
        self._undeclare.append(subscriber.undeclare)
        return subscriber

    def latest(self, name: str) -> LatestSubscriber:
        """A `LatestSubscriber` on row `name` (a graph token in ROS 2 mode)."""
        if self._ros_row(name):
            self._row_endpoint("MS", name)
        subscriber = LatestSubscriber(self.session, self.keys.key(name))
        self._undeclare.append(subscriber.close)
        return subscriber

    def trigger_service(self, service: str, handler: Callable[[zenoh.Query], None]) -> str:
        """Declare the ROS service `<node>/<service>` (`std_srvs/srv/Trigger`); returns its full name. `handler`
        gets each query (from a Zenoh thread: hand it on, reply with `reply_trigger`). ROS 2 mode only."""
        if not self.keys.rmw or self.node is None:
            raise ValueError("ROS services exist in ROS 2 mode only (set a ROS domain id)")
        name = f"{self.node_fqn}/{service}"
        assert self.keys.ros.domain_id is not None
        key = rmw_zenoh_key(self.keys.ros.domain_id, name, TRIGGER)
        self._endpoint("SS", name, TRIGGER, SERVICE_QOS.encode())
        self._undeclare.append(self.session.declare_queryable(key, handler, complete=True).undeclare)
        return name

    def close(self) -> None:
        while self._undeclare:
            self._undeclare.pop()()


def read_trigger_request(query: zenoh.Query) -> RmwAttachment:
    """Check a Trigger request and return its attachment (the client's sequence number and gid to echo)."""
    if query.attachment is None:
        raise ProtocolError("service request without rmw_zenoh's attachment (sequence number, time, client gid)")
    attachment = RmwAttachment.decode(query.attachment.to_bytes())
    decode_trigger_request(query.payload.to_bytes() if query.payload is not None else b"")
    return attachment


def reply_trigger(query: zenoh.Query, request: RmwAttachment, success: bool, message: str) -> None:
    """Reply to a Trigger request as rmw_zenoh's service server does: the response CDR, the request's sequence
    number and client gid with a new source time in the attachment."""
    attachment = RmwAttachment(request.sequence_number, time.time_ns(), request.gid).encode()
    query.reply(query.key_expr, encode_trigger_response(success, message), attachment=attachment)
