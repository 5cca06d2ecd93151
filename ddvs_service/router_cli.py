"""`ddvs router`: a Zenoh router in this Python process (no `zenohd` needed), until SIGTERM/SIGINT.

One router per host of a multi-host deployment: the host's nodes are its clients (`--mode client --connect
<this router>`), and the routers link the hosts (`--connect tcp/<other host>:7447` on one side). Routers do not
forward between two peers, so nodes that rely on a router must be clients (PLATFORM-NOTES). Multicast scouting
stays off unless `--multicast-scouting` is given. When the session is open the router prints one line
`router <zid> listening on <endpoints>` (flushed), which scripts and tests wait for. See docs/deployment.md.
"""

from __future__ import annotations

import argparse

READY_LINE = "router {zid} listening on {endpoints}"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ddvs_service.protocol.session import add_zenoh_arguments

    add_zenoh_arguments(parser)
    parser.set_defaults(mode="router")


def run(args: argparse.Namespace) -> int:
    import signal
    import threading

    from ddvs_service.protocol.session import open_session, session_config_from_args

    config = session_config_from_args(args)
    if config.mode != "router":
        raise SystemExit(f"ddvs router: --mode {config.mode} given; a router runs in mode 'router' only")
    if not config.listen and not config.connect:
        raise SystemExit("ddvs router: no --listen and no --connect endpoint; give at least one "
                         "(e.g. --listen tcp/0.0.0.0:7447)")
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    with open_session(config) as session:
        print(READY_LINE.format(zid=session.info.zid(), endpoints=",".join(config.listen) or "-"), flush=True)
        while not stop.wait(0.5):
            pass
    return 0
