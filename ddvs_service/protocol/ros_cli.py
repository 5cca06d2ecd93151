"""The ROS 2 options every node's command line has (`--ros-domain-id`, `--ros-namespace`, `--ros-topic ROW:=NAME`)
and their reading into `RosSettings`, checked against the topic table of `protocol.keys` (docs/ros2.md)."""

from __future__ import annotations

import argparse
import os

from pydantic import ValidationError

from ddvs_service.protocol.keys import Keys
from ddvs_service.protocol.ros_settings import RosSettings


def add_ros_arguments(parser: argparse.ArgumentParser) -> None:
    """`--ros-domain-id`, `--ros-namespace`, `--ros-topic ROW:=NAME` (repeatable)."""
    group = parser.add_argument_group("ROS 2 (rmw_zenoh) mode")
    group.add_argument("--ros-domain-id", type=int, metavar="N",
                       help="speak ROS 2 over rmw_zenoh in this ROS domain (default: plain ddvs keys; "
                            "environment DDVS_ROS_DOMAIN_ID)")
    group.add_argument("--ros-namespace", metavar="NS", help="ROS namespace of this node and its relative topics")
    group.add_argument("--ros-topic", action="append", default=[], metavar="ROW:=NAME",
                       help="remap a topic, e.g. camera_image:=/camera/color/image_raw (rows: docs/ros2.md)")


def ros_settings_from_args(args: argparse.Namespace, base: RosSettings | None = None) -> RosSettings:
    """Flags over the environment (`DDVS_ROS_DOMAIN_ID`) over `base` (a configuration file's settings). A bad value
    exits the command (`SystemExit`) with a message naming it and what is expected."""
    try:
        settings = _settings_from_args(args, base)
        Keys(ros=settings)  # checks the remapped rows and every ROS name now
    except (ValueError, ValidationError) as exc:
        raise SystemExit(f"ddvs: ROS 2 options: {exc}") from None
    return settings


def _settings_from_args(args: argparse.Namespace, base: RosSettings | None) -> RosSettings:
    update: dict[str, object] = {}
    domain = args.ros_domain_id if args.ros_domain_id is not None else os.environ.get("DDVS_ROS_DOMAIN_ID")
    if domain is not None:
        update["domain_id"] = domain
    if args.ros_namespace:
        update["namespace"] = args.ros_namespace
    topics = dict(base.topics) if base else {}
    for item in args.ros_topic:
        row, sep, name = item.partition(":=")
        if not sep or not row or not name:
            raise ValueError(f"--ros-topic {item!r}: expected ROW:=NAME, e.g. camera_image:=/camera/image_raw")
        topics[row] = name
    update["topics"] = topics
    return RosSettings.model_validate({**(base or RosSettings()).model_dump(), **update})
