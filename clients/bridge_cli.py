"""`ddvs bridge`: camera twists from the servo → joint velocities for the arm (`clients.bridge_node.BridgeNode`)."""

from __future__ import annotations

import argparse
import logging
import signal
import threading


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ddvs_service.protocol import add_zenoh_arguments
    from ddvs_service.protocol.ros_cli import add_ros_arguments

    parser.add_argument("--config", required=True, help="bridge JSON file (e.g. configs/arm/ur5_bridge.json)")
    parser.add_argument("--rate", type=float, default=100.0, help="command republishing rate in Hz (default 100)")
    parser.add_argument("--prefix", default="ddvs", help="key prefix (default ddvs)")
    parser.add_argument("--robot", default="robot0", help="robot name in the keys (default robot0)")
    add_zenoh_arguments(parser)
    add_ros_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from clients.bridge import load_bridge
    from clients.bridge_node import BridgeNode
    from ddvs_service.logs import setup_logging
    from ddvs_service.protocol import Keys, open_session, session_config_from_args
    from ddvs_service.protocol.ros_cli import ros_settings_from_args
    from ddvs_service.protocol.security import check_robot_covered

    setup_logging("INFO")
    session_config = session_config_from_args(args)
    keys = Keys(args.prefix, args.robot, ros_settings_from_args(args))
    if not check_robot_covered(keys, session_config.zenoh_config):
        return 2  # logged: the router configuration beside ours would drop everything of this robot
    bridge = load_bridge(args.config)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with open_session(session_config) as session:
        node = BridgeNode(bridge, session, keys, args.rate)
        try:
            node.run(stop)
        finally:
            node.close()
    logging.getLogger(__name__).info("published %d joint velocity commands", node.published)
    return 0
