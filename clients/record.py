"""`ddvs record`: record a servo run from Zenoh into a rosbag2 bag (MCAP storage; `clients/bag.py`,
docs/recording.md) with `clients.bag_recorder.BagRecorder`; `ddvs record --recover BAG` makes a killed recorder's
bag whole."""

from __future__ import annotations

import argparse
import json
import logging
import threading
import time
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ddvs_service.protocol import Keys

log = logging.getLogger(__name__)


def recording_meta(keys: Keys, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """A bag's `ddvs` metadata: the robot's key prefix and name, the start time (ns since the epoch), and `extra`
    (e.g. a reference pose)."""
    return {"prefix": keys.prefix, "robot": keys.robot, "started_ns": time.time_ns(), **(extra or {})}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ddvs_service.protocol import add_zenoh_arguments
    from ddvs_service.protocol.ros_cli import add_ros_arguments

    parser.add_argument("out", help="new (or empty) bag directory; with --recover: the bag of a killed recorder")
    parser.add_argument("--recover", action="store_true",
                        help="make a killed recorder's bag readable: rewrite its files from their complete chunks "
                             "and write metadata.yaml, then print the messages kept per topic")
    parser.add_argument("--frames", choices=("raw", "png", "jpeg", "none"), default="raw",
                        help="camera frames as published (raw sensor_msgs/Image, default), re-encoded as "
                             "sensor_msgs/CompressedImage (png, jpeg), or not at all")
    parser.add_argument("--frame-every", type=int, default=1, help="keep every N-th camera frame (default 1)")
    parser.add_argument("--jpeg-quality", type=int, default=90, help="with --frames jpeg (default 90)")
    parser.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd",
                        help="MCAP chunk compression (default zstd)")
    parser.add_argument("--flush-period", type=float, default=0.5,
                        help="seconds between chunk closes, at most 1 (crash safety; default 0.5)")
    parser.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: Ctrl-C)")
    parser.add_argument("--meta", action="append", default=[], metavar="KEY=JSON",
                        help="extra metadata entry, e.g. reference_pose='[1,0,...]' (repeatable)")
    parser.add_argument("--prefix", default="ddvs", help="key prefix (default ddvs)")
    parser.add_argument("--robot", default="robot0", help="robot name in the keys (default robot0)")
    add_zenoh_arguments(parser)
    add_ros_arguments(parser)  # ROS 2 mode: the ROS-typed topics are on rmw_zenoh keys (docs/ros2.md)


def _parse_meta(items: list[str]) -> dict[str, Any]:
    meta = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise SystemExit(f"--meta {item!r}: expected KEY=JSON")
        try:
            meta[key] = json.loads(text)
        except json.JSONDecodeError:
            meta[key] = text
    return meta


def run(args: argparse.Namespace) -> int:
    import signal

    from clients.bag import BagWriter, recover_bag
    from clients.bag_recorder import BagRecorder
    from clients.channels import run_channels
    from ddvs_service.logs import setup_logging
    from ddvs_service.protocol import Keys, open_session, session_config_from_args
    from ddvs_service.protocol.ros_cli import ros_settings_from_args

    setup_logging("INFO")
    if args.recover:
        print(json.dumps(recover_bag(args.out, args.compression), indent=2))
        return 0
    keys = Keys(args.prefix, args.robot, ros_settings_from_args(args))
    writer = BagWriter(args.out, run_channels(keys, args.frames), recording_meta(keys, _parse_meta(args.meta)),
                       compression=args.compression, flush_period_s=args.flush_period)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    if args.duration is not None:
        timer = threading.Timer(args.duration, stop.set)
        timer.daemon = True
        timer.start()
    with open_session(session_config_from_args(args)) as session:
        recorder = BagRecorder(session, keys, writer, args.frames, args.frame_every, args.jpeg_quality)
        try:
            recorder.run(stop)
        finally:
            recorder.close()
            recorder.drain()
            writer.close()
    log.info("recorded %s into %s (received %s, rejected %d, frames dropped %d)", writer.counts, args.out,
             recorder.received, recorder.rejected, recorder.frames_dropped)
    return 0
