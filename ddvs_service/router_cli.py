"""`ddvs router`: a Zenoh router in this Python process (no `zenohd` needed), until SIGTERM/SIGINT.

One router per host of a multi-host deployment: the host's nodes are its clients (`--mode client --connect
<this router>`), and the routers link the hosts (`--connect tcp/<other host>:7447` on one side). Routers do not
forward between two peers, so nodes that rely on a router must be clients (PLATFORM-NOTES). Multicast scouting
stays off unless `--multicast-scouting` is given. When the session is open the router prints one line
`router <zid> listening on <endpoints>` (flushed), which scripts and tests wait for. See docs/deployment.md.

With access control on (`--zenoh-config` with an enabled `access_control` section, e.g. from `ddvs security init`)
the router audits it (`protocol/audit.py`): every denied message, session without a role and refused TLS handshake
is logged as a JSON line on stderr (logger `ddvs.audit`, at most `--audit-rate` lines per second, every one counted
per identity), and the counts of each robot its rules grant are published every second on
`<prefix>/<robot>/router/audit` for `ddvs monitor`. `--no-audit` turns that off.
"""

from __future__ import annotations

import argparse

READY_LINE = "router {zid} listening on {endpoints}"
AUDIT_PERIOD_S = 1.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ddvs_service.protocol.session import add_zenoh_arguments

    add_zenoh_arguments(parser)
    parser.set_defaults(mode="router")
    parser.add_argument("--no-audit", action="store_true", help="do not log nor count access-control denials")
    parser.add_argument("--audit-rate", type=float, default=10.0, metavar="LINES_PER_S",
                        help="most audit log lines per second on average (bursts of twice that); default 10")
    parser.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])


def run(args: argparse.Namespace) -> int:
    import json
    import signal
    import threading
    import time

    import zenoh

    from ddvs_service.logs import setup_logging
    from ddvs_service.protocol.audit import Audit, ZenohLogTap, audit_key
    from ddvs_service.protocol.security import robots_granted
    from ddvs_service.protocol.session import open_session, session_config_from_args

    setup_logging(args.log_level)
    config = session_config_from_args(args)
    if config.mode != "router":
        raise SystemExit(f"ddvs router: --mode {config.mode} given; a router runs in mode 'router' only")
    if not config.listen and not config.connect:
        raise SystemExit("ddvs router: no --listen and no --connect endpoint; give at least one "
                         "(e.g. --listen tcp/0.0.0.0:7447)")
    if not args.audit_rate > 0:
        raise SystemExit(f"ddvs router: --audit-rate {args.audit_rate}: expected a positive number of lines per second")
    access_control = json.loads(config.to_zenoh_config().get_json("access_control"))
    audited = not args.no_audit and bool(access_control.get("enabled"))
    sessions: list[zenoh.Session] = []

    def identity_of(zid: str) -> str | None:
        links = sessions[0].info.links() if sessions else []
        return next((link.auth_identifier for link in links if str(link.zid) == zid and link.auth_identifier), None)

    audit = Audit(identity_of, rate=args.audit_rate, burst=max(1, int(2 * args.audit_rate)))
    if audited:
        ZenohLogTap(audit.feed).start()
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    with open_session(config) as session:
        sessions.append(session)
        robots = sorted(robots_granted(access_control)) if audited else []
        publishers = {base: session.declare_publisher(audit_key(base)) for base in robots}
        print(READY_LINE.format(zid=session.info.zid(), endpoints=",".join(config.listen) or "-"), flush=True)
        zid, published = str(session.info.zid()), 0.0
        while not stop.wait(0.5):
            if not audited:
                continue
            audit.flush()
            if time.monotonic() - published >= AUDIT_PERIOD_S:
                published = time.monotonic()
                for base, publisher in publishers.items():
                    others = [other for other in robots if other != base]
                    publisher.put(json.dumps({"router": zid, "robot": base, **audit.report(base, others)}))
        for publisher in publishers.values():
            publisher.undeclare()
    return 0
