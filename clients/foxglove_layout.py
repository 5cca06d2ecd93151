"""The Foxglove layout of a servo run, built with `foxglove.layouts` (foxglove-sdk) for one robot's topics.

Top row: the current image (with its camera info), the reference, and the registration's residual over the ROI
(warped current − reference after the photometric model, `32FC1` grey levels shown from −64 to 64). Bottom row: the
control error norm and the twist (v in m/s, ω in rad/s, camera frame) against time, the servo state over time and
the newest `StateSnapshot`, and the camera pose in 3-D (ground-truth `world → camera` transforms of the live view).

Topics are the live view's (`ddvs monitor --foxglove`, `clients.channels`): in ROS 2 mode the ROS-typed ones have
their ROS names (`/image_raw`, `/servo_node/delta_twist_cmds`, … resolved in the namespace, remapped as the service
is), so a layout is made for one mode. `python -m clients.foxglove_layout [--prefix P --robot R] [ROS 2 options] >
layout.json` writes one; the repository ships `LAYOUTS`: `docs/foxglove/ddvs-layout.json` (plain keys) and
`docs/foxglove/ddvs-layout-ros2.json` (ROS 2 mode, default namespace and names), both for robot `robot0` (tests keep
them equal to this builder's output and check that the live view of that mode publishes every topic they name).
Open one in Foxglove with *Layouts → Import from file*.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import foxglove.layouts as fl

from clients.channels import pose_topic, topic_name
from ddvs_service.protocol import Keys
from ddvs_service.protocol.ros_cli import add_ros_arguments, ros_settings_from_args
from ddvs_service.protocol.ros_settings import RosSettings

RESIDUAL_RANGE = 64.0
"""Grey levels shown at the two ends of the residual image's scale."""
LAYOUTS = {"docs/foxglove/ddvs-layout.json": Keys(), "docs/foxglove/ddvs-layout-ros2.json": Keys(
    ros=RosSettings(domain_id=0))}
"""The shipped layouts (paths from the repository root) and the keys of the mode each is made for (the domain id
changes no topic name)."""
TOPIC_FIELDS = ("imageTopic", "calibrationTopic", "topicPath")
"""Layout fields that hold a topic name; `value` holds a message path (`<topic>.<field>…`), `topics` maps topics."""


def _image(topic: str, title: str, calibration: str | None = None, value_range: float | None = None) -> fl.ImagePanel:
    mode = fl.ImageModeConfig(image_topic=topic, calibration_topic=calibration)
    if value_range is not None:
        mode.min_value, mode.max_value = -value_range, value_range
    return fl.ImagePanel(title=title, config=fl.ImageConfig(image_mode=mode))


def _plot(title: str, series: list[tuple[str, str]], label: str) -> fl.PlotPanel:
    paths = [fl.PlotSeries(value=value, label=name, timestamp_method="receiveTime") for value, name in series]
    return fl.PlotPanel(title=title, config=fl.PlotConfig(paths=paths, y_axis_label=label, show_legend=True))


def build_layout(keys: Keys) -> fl.Layout:
    """The layout for `keys`' robot (topics are the ROS names of its keys)."""
    def t(key_name: str) -> str:
        return topic_name(keys, key_name)

    twist = t("servo_twist")
    top = fl.SplitContainer(direction="row", items=[
        fl.SplitItem(content=_image(t("camera_image"), "current image", calibration=t("camera_info"))),
        fl.SplitItem(content=_image(t("servo_reference"), "reference")),
        fl.SplitItem(content=_image(t("servo_residual"), "residual: warped current − reference (grey levels)",
                                    value_range=RESIDUAL_RANGE)),
    ])
    plots = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(content=_plot("control error norm", [(f"{t('servo_status')}.error_norm", "‖ε̄‖")], "error")),
        fl.SplitItem(content=_plot("linear velocity", [(f"{twist}.twist.linear.{c}", f"v{c}") for c in "xyz"],
                                   "m/s")),
        fl.SplitItem(content=_plot("angular velocity", [(f"{twist}.twist.angular.{c}", f"ω{c}") for c in "xyz"],
                                   "rad/s")),
    ])
    state = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(content=fl.StateTransitionsPanel(title="servo state", config=fl.StateTransitionsConfig(
            paths=[fl.StateTransitionsSeries(value=f"{t('servo_status')}.state", label="state",
                                             timestamp_method="receiveTime")]))),
        fl.SplitItem(proportion=2, content=fl.RawMessagesPanel(
            title="state", config=fl.RawMessagesConfig(topic_path=t("servo_state")))),
    ])
    pose = fl.ThreeDeePanel(title="camera pose (ground truth)", config=fl.ThreeDeeConfig(
        follow_tf="world", topics={pose_topic(keys): fl.BaseRendererPosesTopicSettings(visible=True)}))
    bottom = fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=2, content=plots), fl.SplitItem(content=state), fl.SplitItem(content=pose)])
    return fl.Layout(content=fl.SplitContainer(direction="column", items=[
        fl.SplitItem(content=top), fl.SplitItem(content=bottom)]))


def layout_json(keys: Keys) -> str:
    """The layout as an indented JSON document (the committed file's form)."""
    return json.dumps(json.loads(build_layout(keys).to_json()), indent=2, ensure_ascii=False) + "\n"


def layout_topics(layout: Any) -> set[str]:
    """Every topic a layout (its parsed JSON) names: in topic fields, message paths and 3-D topic settings."""
    topics: set[str] = set()
    if isinstance(layout, list):
        for item in layout:
            topics |= layout_topics(item)
    elif isinstance(layout, dict):
        for field, value in layout.items():
            if field in TOPIC_FIELDS and isinstance(value, str):
                topics.add(value)
            elif field == "value" and isinstance(value, str) and value.startswith("/"):
                topics.add(value.split(".", 1)[0])
            elif field == "topics" and isinstance(value, dict):
                topics |= set(value)
            topics |= layout_topics(value)
    return topics


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--prefix", default="ddvs")
    parser.add_argument("--robot", default="robot0")
    add_ros_arguments(parser)
    args = parser.parse_args()
    print(layout_json(Keys(args.prefix, args.robot, ros_settings_from_args(args))), end="")


if __name__ == "__main__":
    main()
