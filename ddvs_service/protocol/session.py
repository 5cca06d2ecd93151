"""Zenoh session helpers shared by every node: configuration (file, environment, CLI), opening, QoS'd publishers
and latest-only subscriptions.

Precedence: defaults < `--zenoh-config`/`DDVS_ZENOH_CONFIG` JSON5 file (the base Zenoh configuration) <
`SessionConfig` fields (mode, scouting and shared memory always; endpoints when given) < `overrides`.
Environment: `DDVS_ZENOH_MODE` (peer|client|router), `DDVS_ZENOH_CONNECT` and `DDVS_ZENOH_LISTEN` (comma-separated
endpoints such as `tcp/127.0.0.1:7447`), `DDVS_ZENOH_CONFIG` (path). CLI flags override the environment.

Facts this relies on (PLATFORM-NOTES): close every session (a process with live callback subscribers hangs at
exit otherwise); Zenoh callbacks must not block; a full FIFO channel stalls the whole session, so frames are read
through `RingChannel(1)` (only the newest sample is kept).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import zenoh
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from ddvs_service.protocol.keys import TOPICS, Keys

Mode = Literal["peer", "client", "router"]
ENV_MODE = "DDVS_ZENOH_MODE"
ENV_CONNECT = "DDVS_ZENOH_CONNECT"
ENV_LISTEN = "DDVS_ZENOH_LISTEN"
ENV_CONFIG = "DDVS_ZENOH_CONFIG"


def _split_endpoints(values: str | list[str] | None) -> list[str]:
    if values is None:
        return []
    items = [values] if isinstance(values, str) else values
    return [e.strip() for item in items for e in item.split(",") if e.strip()]


class SessionConfig(BaseModel):
    """How a node joins the Zenoh network. Peer mode with multicast scouting off by default: peers then find each
    other only through `connect`/`listen` endpoints (and gossip), which is what tests and lab set-ups want.

    `shm_pool_mib` (MiB; Zenoh's own default is 16) sizes the pool in which this session, when `shm` is on, writes
    its large outgoing messages (frames; Zenoh's threshold is 3 KiB) for zero-copy delivery on the host. Every
    subscriber on the host maps the pool of each publisher it receives from, resident as far as its pages were
    written — a fleet service maps one pool per robot camera —, so the default holds a few frames only (four
    640×480 RGB images, fifty 320×240 grey ones); a message that finds no room is sent over the link instead,
    unchanged, so larger frames still arrive, copied."""

    model_config = ConfigDict(extra="forbid")

    mode: Mode = Field(default="peer", description="Zenoh mode: peer, client (of a router) or router.")
    connect: list[str] = Field(default_factory=list, description=(
        "Endpoints to connect to, '<protocol>/<address>', e.g. 'tcp/127.0.0.1:7447'."))
    listen: list[str] = Field(default_factory=list, description="Endpoints to listen on, '<protocol>/<address>'.")
    multicast_scouting: bool = Field(default=False, description="Discover peers by multicast scouting.")
    shm: bool = Field(default=True, description="Write large outgoing messages to shared memory (same host).")
    shm_pool_mib: float = Field(default=4.0, gt=0.0, le=4096.0, description=(
        "Size of this session's shared-memory pool, MiB."))
    zenoh_config: Path | None = Field(default=None, description=(
        "A Zenoh JSON5 configuration file (security: TLS, access control), the base the other settings change."))
    overrides: dict[str, Any] = Field(default_factory=dict, description=(
        "Zenoh configuration keys set last, as {'<key>/<key>': JSON value}."))

    @field_validator("connect", "listen")
    @classmethod
    def _endpoints_have_protocol(cls, endpoints: list[str]) -> list[str]:
        for e in endpoints:
            proto, _, address = e.partition("/")
            if not proto or not address:
                raise ValueError(f"endpoint {e!r}: expected '<protocol>/<address>', e.g. 'tcp/127.0.0.1:7447'")
        return endpoints

    @model_validator(mode="after")
    def _client_can_find_a_router(self) -> SessionConfig:
        if self.mode == "client" and not self.connect and not self.multicast_scouting:
            raise ValueError("client mode needs a router endpoint in 'connect' (multicast scouting is off)")
        return self

    @classmethod
    def from_file(cls, path: str | os.PathLike[str]) -> SessionConfig:
        """Load the fields from a JSON file (an object with the field names above)."""
        try:
            return cls.model_validate(json.loads(Path(path).read_text(encoding="utf-8")))
        except (OSError, json.JSONDecodeError, ValidationError) as exc:
            raise ValueError(f"session configuration file {path}: {exc}") from exc

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None, base: SessionConfig | None = None) -> SessionConfig:
        """`base` (default: defaults) updated from the `DDVS_ZENOH_*` environment variables that are set."""
        env = os.environ if environ is None else environ
        update: dict[str, Any] = {}
        if env.get(ENV_MODE):
            update["mode"] = env[ENV_MODE].strip()
        if env.get(ENV_CONNECT):
            update["connect"] = _split_endpoints(env[ENV_CONNECT])
        if env.get(ENV_LISTEN):
            update["listen"] = _split_endpoints(env[ENV_LISTEN])
        if env.get(ENV_CONFIG):
            update["zenoh_config"] = env[ENV_CONFIG]
        return (base or cls()).updated(update, f"environment ({', '.join(sorted(update))})")

    def updated(self, update: dict[str, Any], source: str) -> SessionConfig:
        """A validated copy with `update` applied; errors name `source`."""
        try:
            return type(self).model_validate({**self.model_dump(), **update})
        except ValidationError as exc:
            raise ValueError(f"invalid Zenoh session settings from {source}: {exc}") from exc

    def to_zenoh_config(self) -> zenoh.Config:
        """The `zenoh.Config` these settings describe."""
        config = zenoh.Config.from_file(str(self.zenoh_config)) if self.zenoh_config else zenoh.Config()
        config.insert_json5("mode", json.dumps(self.mode))
        if self.connect:
            config.insert_json5("connect/endpoints", json.dumps(self.connect))
        if self.listen:
            config.insert_json5("listen/endpoints", json.dumps(self.listen))
        config.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        config.insert_json5("transport/shared_memory/enabled", json.dumps(self.shm))
        config.insert_json5("transport/shared_memory/transport_optimization/pool_size",
                            json.dumps(int(self.shm_pool_mib * 2**20)))
        for key, value in self.overrides.items():
            config.insert_json5(key, json.dumps(value))
        return config


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    """The Zenoh flags every node accepts (`--mode --connect --listen --zenoh-config --multicast-scouting`)."""
    group = parser.add_argument_group("Zenoh session")
    group.add_argument("--mode", choices=["peer", "client", "router"], help=f"Zenoh mode (default peer; ${ENV_MODE})")
    for flag, env, what in (("--connect", ENV_CONNECT, "connect to"), ("--listen", ENV_LISTEN, "listen on")):
        group.add_argument(flag, action="append", metavar="ENDPOINTS", help=f"endpoints to {what} (comma list) ${env}")
    group.add_argument("--zenoh-config", metavar="PATH", help=f"JSON5 Zenoh configuration used as base ${ENV_CONFIG}")
    group.add_argument(
        "--multicast-scouting", action="store_true", default=None, help="discover peers by UDP multicast (default off)"
    )


def session_config_from_args(
    args: argparse.Namespace, environ: Mapping[str, str] | None = None, base: SessionConfig | None = None
) -> SessionConfig:
    """`base` (e.g. a node's configuration file; defaults when None), then the environment, then the flags of
    `add_zenoh_arguments` that were given."""
    update: dict[str, Any] = {}
    if args.mode is not None:
        update["mode"] = args.mode
    if args.connect is not None:
        update["connect"] = _split_endpoints(args.connect)
    if args.listen is not None:
        update["listen"] = _split_endpoints(args.listen)
    if args.zenoh_config is not None:
        update["zenoh_config"] = args.zenoh_config
    if args.multicast_scouting is not None:
        update["multicast_scouting"] = args.multicast_scouting
    return SessionConfig.from_env(environ, base).updated(update, "command line")


def open_session(cfg: SessionConfig) -> zenoh.Session:
    """Open a Zenoh session; the caller must close it (`with open_session(cfg) as s:` or `s.close()`). A client's
    connections to its router are watched (`watch_router`)."""
    session = zenoh.open(cfg.to_zenoh_config())
    if cfg.mode == "client":
        watch_router(session, cfg.connect)
    return session


def watch_router(session: zenoh.Session, endpoints: list[str], logger: logging.Logger | None = None) -> None:
    """Log (logger `ddvs.session`) each router connection of `session`: INFO when one opens (at once for those
    already open), ERROR when one closes (nothing flows until a router accepts this node again). Zenoh keeps
    reconnecting to `endpoints` by itself; over TLS it accepts only a server whose certificate chains to the CA and
    names the endpoint's host, so a node that took over the endpoint with another certificate stays refused and this
    node stays disconnected (docs/security.md)."""
    log = logger or logging.getLogger("ddvs.session")

    def on_event(event: zenoh.TransportEvent) -> None:
        transport = event.transport
        if transport.whatami != zenoh.WhatAmI.ROUTER:
            return
        extra = {"fields": {"router": str(transport.zid), "endpoints": endpoints}}
        if event.kind == zenoh.SampleKind.PUT:
            log.info("connected to router", extra=extra)
        else:
            log.error("lost the connection to the router: nothing is sent or received until a router at the "
                      "endpoints accepts this node again (over TLS only one whose certificate names the endpoint's "
                      "host: the real router)", extra=extra)

    session.info.declare_transport_events_listener(on_event, history=True)  # history: the router it opened with


def declare_publisher(session: zenoh.Session, keys: Keys, name: str) -> zenoh.Publisher:
    """A publisher on `keys.key(name)` with the priority, congestion control and express flag of `TOPICS[name]`."""
    spec = TOPICS[name]
    return session.declare_publisher(
        keys.key(name),
        priority=getattr(zenoh.Priority, spec.priority),
        congestion_control=getattr(zenoh.CongestionControl, spec.congestion),
        express=spec.express,
    )


class LatestSubscriber:
    """Subscription that keeps only the newest sample (`RingChannel(1)`): a slow reader skips frames, never queues
    them. `recv(timeout)` polls every `poll_interval_s` (adds at most that latency; 0.5 ms by default)."""

    def __init__(self, session: zenoh.Session, key: str, poll_interval_s: float = 0.0005) -> None:
        if poll_interval_s <= 0:
            raise ValueError(f"poll_interval_s = {poll_interval_s}: expected a positive number of seconds")
        self.key = key
        self._poll = poll_interval_s
        self._sub = session.declare_subscriber(key, zenoh.handlers.RingChannel(1))
        self._closed = False

    def try_recv(self) -> zenoh.Sample | None:
        """The newest sample not yet returned, or None at once."""
        if self._closed:
            raise RuntimeError(f"LatestSubscriber on {self.key!r} is closed")
        return self._sub.try_recv()

    def recv(self, timeout: float) -> zenoh.Sample | None:
        """The newest sample not yet returned, waiting up to `timeout` seconds; None if none arrived."""
        deadline = time.monotonic() + timeout
        while True:
            sample = self.try_recv()
            if sample is not None:
                return sample
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            time.sleep(min(self._poll, remaining))

    def close(self) -> None:
        """Undeclare the subscription (idempotent)."""
        if not self._closed:
            self._closed = True
            self._sub.undeclare()

    def __enter__(self) -> LatestSubscriber:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
