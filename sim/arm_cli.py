"""`ddvs sim arm`: run the SAPIEN arm plant (`sim.arm_node.ArmNode`) in this process until interrupted."""

from __future__ import annotations

import argparse
import logging
import signal
import threading

START_POSES = ("home", "reference", "start")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ddvs_service.protocol import add_zenoh_arguments
    from ddvs_service.protocol.ros_cli import add_ros_arguments

    parser.add_argument("--config", required=True, help="scene JSON file (e.g. configs/arm/ur5_poster.json)")
    parser.add_argument("--clock", choices=["realtime", "lockstep"], default="realtime",
                        help="realtime: fixed fps, frames dropped when late; lockstep: step when command k arrives")
    parser.add_argument("--fps", type=float, default=30.0, help="frames (control periods) per second (default 30)")
    parser.add_argument("--deadman", type=float, default=0.1,
                        help="realtime: seconds after which a command is replaced by zero velocities (default 0.1)")
    parser.add_argument("--lockstep-timeout", type=float, default=1.0,
                        help="lockstep: seconds to wait for the command of a frame, then step still (default 1)")
    parser.add_argument("--start", choices=START_POSES, default="start",
                        help="initial arm pose: home joints, reference camera pose, or reference·displacement")
    parser.add_argument("--frames", type=int, default=None, help="stop after this many frames (default: never)")
    parser.add_argument("--prefix", default="ddvs", help="key prefix (default ddvs)")
    parser.add_argument("--robot", default="robot0", help="robot name in the keys (default robot0)")
    add_zenoh_arguments(parser)
    add_ros_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from ddvs_service.logs import setup_logging
    from ddvs_service.protocol import Keys, open_session, session_config_from_args
    from ddvs_service.protocol.ros_cli import ros_settings_from_args
    from ddvs_service.protocol.security import check_robot_covered
    from sim.arm import ArmSim
    from sim.arm_node import ArmNode, ArmNodeSettings
    from sim.arm_scene import load_scene_config

    setup_logging("INFO")
    session_config = session_config_from_args(args)
    keys = Keys(args.prefix, args.robot, ros_settings_from_args(args))
    if not check_robot_covered(keys, session_config.zenoh_config):
        return 2  # logged: the router configuration beside ours would drop everything of this robot
    config = load_scene_config(args.config)
    settings = ArmNodeSettings(args.clock, args.fps, args.deadman, args.lockstep_timeout, args.frames)
    sim = ArmSim(config)
    if args.start == "reference":
        if config.start is None:
            raise SystemExit(f"{args.config} has no 'start' section: cannot place the reference pose")
        sim.place_camera(config.start.T_target_ref, config.start.target)
    elif args.start == "start":
        if config.start is None:
            raise SystemExit(f"{args.config} has no 'start' section: use --start home")
        sim.place_start()
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with open_session(session_config) as session:
        node = ArmNode(sim, session, keys, settings)
        try:
            node.run(stop)
        finally:
            node.close()
    mean_ms = 1e3 * node.render_seconds / max(node.frames, 1)
    logging.getLogger(__name__).info(
        "published %d frames, dropped %d, render %.1f ms/frame on average", node.frames, node.dropped, mean_ms
    )
    return 0
