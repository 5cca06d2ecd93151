"""Which mode a node runs in — plain ddvs keys or ROS 2 over rmw_zenoh — and its ROS names (docs/ros2.md).

`RosSettings.domain_id = None` (the default) keeps the plain `<prefix>/<robot>/…` keys. A domain id switches the
ROS-typed topics to rmw_zenoh keys under ROS names: each row of `keys.TOPICS` with a ROS type has a default ROS name
(`ros_name`), relative names resolve in `namespace`, and `topics` remaps rows (`{"camera_image": "/cam/image_raw"}`).
Every node's CLI has `--ros-domain-id N`, `--ros-namespace NS` and `--ros-topic ROW:=NAME` (`add_ros_arguments`).
"""

from __future__ import annotations

import argparse
import os

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from ddvs_service.protocol.ros_graph import check_ros_name


class RosSettings(BaseModel):
    """ROS 2 mode of one node: `domain_id` (None: plain ddvs keys), `namespace`, node name override, remapping."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    domain_id: int | None = Field(default=None, ge=0, le=232)
    namespace: str = "/"
    node_name: str | None = None
    topics: dict[str, str] = Field(default_factory=dict)

    @field_validator("namespace")
    @classmethod
    def _namespace(cls, value: str) -> str:
        check_ros_name("ROS namespace", value)
        return value

    @property
    def enabled(self) -> bool:
        return self.domain_id is not None

    def resolve(self, name: str) -> str:
        """Fully qualified ROS name of `name`: absolute names as they are, relative ones under `namespace`."""
        if name.startswith("~"):
            raise ValueError(f"ROS name {name!r}: private names ('~') are not supported here; give the full name")
        full = name if name.startswith("/") else f"{self.namespace.rstrip('/')}/{name}"
        check_ros_name("ROS topic", full)
        return full


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
        from ddvs_service.protocol.keys import Keys

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
