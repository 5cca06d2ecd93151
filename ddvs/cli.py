"""The `ddvs` command line: one subcommand per tool, each implemented in its own module.

Every subcommand module exposes `add_arguments(parser: argparse.ArgumentParser) -> None` and
`run(args: argparse.Namespace) -> int`. Modules are imported only when their subcommand runs, so `ddvs --help`
stays fast and works even when an optional part (e.g. the SAPIEN renderer) cannot start on this machine.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

# name -> (module implementing it, one-line help). Add a line when an issue builds a new subcommand.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "serve": ("ddvs_service.service.serve_cli", "run the servo service: frames in, camera twists out (Zenoh)"),
    "register": ("ddvs_service.register_cli", "planar direct registration of two images (prints one JSON line)"),
    "sim": ("sim.sim_cli", "run a simulated plant over Zenoh (`ddvs sim arm`: the SAPIEN arm)"),
    "bridge": ("clients.bridge_cli", "camera twist → arm joint velocities (Pinocchio, any URDF + camera mount)"),
    "experiment": ("orchestration.experiment_cli", "run the paper's experiments on the simulated plant (synthetic)"),
    "camera": ("clients.camera", "publish frames + camera info from a webcam or a video file"),
    "ctl": ("clients.ctl", "send one command to the servo service (reference, start/stop, config) and print the reply"),
    "monitor": ("clients.monitor", "live view of a servo: terminal (--once: JSON) or Foxglove (--foxglove)"),
    "record": ("clients.record", "record a servo run to a rosbag2 bag (MCAP): frames, twists, joints, status, …"),
    "plot": ("clients.plot", "plot a bag or recording: velocities, error norm, 3-D camera trajectory, pose error"),
    "router": ("ddvs_service.router_cli", "a Zenoh router in Python (one per host; the host's nodes are its clients)"),
    "security": ("ddvs_service.security_cli", "secure a robot's Zenoh network: `ddvs security init --robot NAME OUT/`"),
    "ros": ("clients.ros_graph", "the ROS 2 graph over rmw_zenoh, as `ros2 node/topic/service list` show it"),
    "demo": ("orchestration.demo", "the paper's real-data experiment on the simulated UR5, real time, with a report"),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The `ddvs` parser; only `command`'s module is imported, to add its arguments (the others: their help line)."""
    parser = argparse.ArgumentParser(
        prog="ddvs", description="Decoupled Direct Visual Servoing: tools, plants and the servo service."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        sp = sub.add_parser(name, help=help_text, description=help_text)
        sp.set_defaults(_module=module_name)
        if name == command:
            importlib.import_module(module_name).add_arguments(sp)
    return parser


def requested_command(argv: Sequence[str]) -> str | None:
    """The subcommand named in `argv` (the first word that is not an option), or None."""
    return next((word for word in argv if not word.startswith("-")), None)


def main(argv: Sequence[str] | None = None) -> int:
    words = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(requested_command(words))
    args = parser.parse_args(words)
    if getattr(args, "_module", None) is None:
        parser.print_help()
        return 0
    return int(importlib.import_module(args._module).run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
