"""`ddvs ros`: the ROS 2 graph of a domain over rmw_zenoh — what `ros2 node list`, `ros2 topic list -t` and
`ros2 service list -t` show — read from rmw_zenoh's liveliness tokens without a ROS installation (docs/ros2.md).

Connect it where the ROS nodes' Zenoh traffic is (e.g. `--connect tcp/127.0.0.1:7447`, the `rmw_zenohd` router).
"""

from __future__ import annotations

import argparse
import os
from collections import defaultdict

from ddvs_service.protocol.ros_graph import GraphEntity


def _ros_type(dds_type: str) -> str:
    """The ROS type name of a token's DDS type name; the name as it is when it is not a ROS one."""
    from ddvs_service.protocol.rmw import ros_type_name

    try:
        return ros_type_name(dds_type)
    except ValueError:
        return dds_type


def listing(entities: list[GraphEntity], verbose: bool = False) -> list[str]:
    """The graph as text lines: nodes, then topics (type, publisher and subscription counts), then services; with
    `verbose` every endpoint under its topic or service (node, kind, QoS)."""
    nodes = sorted({f"{e.node.namespace.rstrip('/')}/{e.node.name}" for e in entities})
    endpoints: dict[tuple[str, str], list[GraphEntity]] = defaultdict(list)
    for e in entities:
        if e.kind != "NN" and e.topic is not None and e.dds_type is not None:
            endpoints[(e.topic, _ros_type(e.dds_type))].append(e)
    lines = ["nodes:", *(f"  {n}" for n in nodes)]
    for title, kinds in (("topics:", ("MP", "MS")), ("services:", ("SS", "SC"))):
        lines.append(title)
        for (name, ros_type), group in sorted(endpoints.items()):
            counts = [sum(e.kind == k for e in group) for k in kinds]
            if not any(counts):
                continue
            what = ("publishers", "subscriptions") if kinds[0] == "MP" else ("servers", "clients")
            lines.append(f"  {name} [{ros_type}] {what[0]} {counts[0]}, {what[1]} {counts[1]}")
            if verbose:
                lines += [f"    {e.kind} {e.node.namespace.rstrip('/')}/{e.node.name} qos {e.qos} {e.type_hash}"
                          for e in sorted(group, key=lambda e: (e.kind, e.node.name)) if e.kind in kinds]
    return lines


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ddvs_service.protocol import add_zenoh_arguments

    parser.add_argument("--ros-domain-id", type=int, default=None,
                        help="the ROS domain (default: $ROS_DOMAIN_ID, else 0)")
    parser.add_argument("--timeout", type=float, default=1.0, help="seconds to collect the graph (default 1)")
    parser.add_argument("-v", "--verbose", action="store_true", help="every endpoint: node, QoS, type hash")
    add_zenoh_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from ddvs_service.protocol import open_session, session_config_from_args
    from ddvs_service.protocol.ros_graph import discover

    domain = args.ros_domain_id if args.ros_domain_id is not None else int(os.environ.get("ROS_DOMAIN_ID", "0"))
    with open_session(session_config_from_args(args)) as session:
        entities = discover(session, domain, args.timeout)
    print("\n".join(listing(entities, args.verbose)))
    return 0
