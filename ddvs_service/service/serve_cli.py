"""`ddvs serve --config FILE`: run the servo service until SIGTERM/SIGINT (then zero twist, close, exit 0)."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ddvs_service.protocol.ros_settings import add_ros_arguments
    from ddvs_service.protocol.session import add_zenoh_arguments

    parser.add_argument("--config", metavar="FILE", help="service configuration (JSON); defaults apply without it")
    parser.add_argument("--state-dir", metavar="DIR", help="where the reference, configuration and state persist")
    parser.add_argument("--robot", help="robot name in the key expressions (overrides the configuration)")
    parser.add_argument("--fresh", action="store_true",
                        help="ignore (and delete) the persisted state instead of resuming it")
    parser.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    add_zenoh_arguments(parser)
    add_ros_arguments(parser)


def run(args: argparse.Namespace) -> int:
    import shutil
    import signal
    import threading

    from ddvs_service.logs import setup_logging
    from ddvs_service.protocol.ros_settings import ros_settings_from_args
    from ddvs_service.protocol.session import session_config_from_args
    from ddvs_service.service.config import ServiceConfig
    from ddvs_service.service.node import ServoNode

    setup_logging(args.log_level)
    config = ServiceConfig.from_file(args.config) if args.config else ServiceConfig()
    update: dict[str, object] = {"zenoh": session_config_from_args(args, base=config.zenoh),
                                 "ros": ros_settings_from_args(args, base=config.ros)}
    if args.state_dir:
        update["state_dir"] = args.state_dir
    if args.robot:
        update["robot"] = args.robot
    config = config.model_copy(update=update)
    config.check()
    if args.fresh:
        shutil.rmtree(config.state_dir, ignore_errors=True)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    ServoNode(config).run(stop)
    return 0
