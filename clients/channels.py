"""The channels a servo run is recorded and watched on: one per Zenoh key, named as its ROS topic, with its schema.

Shared by the recorder (`clients/bag.py`, MCAP channels) and the Foxglove live view (`clients/foxglove_live.py`).
The residual image (`servo/residual`) is among them: the service computes it only while someone subscribes, so a
recorder or a watched live view makes it publish (at most 5 Hz). ROS-typed keys (CDR payloads) become `cdr`
channels whose schema is the full `ros2msg` definition (`ddvs_service.protocol.msgdefs`); JSON keys become `json`
channels whose schema is the message's JSON schema (`ddvs_service/schemas/*.json`, the servo configuration's from
its model). Topic names (`topic_name`) are the ROS
names of the keys (`Keys.ros_topic`). Camera frames have a channel per row they may arrive on (`CAMERA_IMAGES`:
`image_raw`, `image_rect` and their `/compressed`, as `image_transport` names them).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache

from ddvs_service.protocol import TOPICS, Keys
from ddvs_service.protocol.keys import CAMERA_IMAGES
from ddvs_service.protocol.msgdefs import message_definition
from ddvs_service.protocol.schemas import SCHEMA_DIR

JSON_SCHEMAS = {"servo_status": "status", "servo_state": "state_snapshot", "arm_ground_truth": "ground_truth"}
"""JSON key → file name (without `.json`) of its schema under `ddvs_service/schemas/`."""
JSON_SCHEMA_NAMES = {"servo_status": "ddvs/Status", "servo_state": "ddvs/StateSnapshot",
                     "arm_ground_truth": "ddvs/GroundTruth", "servo_config": "ddvs/ServiceConfig"}
ROS_KEYS = ("camera_info", "servo_twist", "arm_joint_states", "servo_reference", "servo_residual")
JSON_KEYS = ("servo_status", "servo_state", "arm_ground_truth", "servo_config")
POSE_SUFFIX = "arm/camera_pose"
"""The live view's ground-truth camera pose (`foxglove.FrameTransform` `world → camera`) is `/<prefix>/<robot>/`
this."""


@dataclass(frozen=True)
class ChannelSpec:
    """One channel: `key_name` (entry of `TOPICS`), ROS `topic`, `message_encoding` (`cdr` or `json`) and schema
    (`schema_name`, `schema_encoding` `ros2msg` or `jsonschema`, `schema` text)."""

    key_name: str
    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    schema: str

    @property
    def is_ros(self) -> bool:
        return self.message_encoding == "cdr"


def topic_name(keys: Keys, key_name: str) -> str:
    """The topic of a key: its ROS name for ROS-typed keys (`Keys.ros_topic`), `/<prefix>/<robot>/<suffix>` for
    JSON keys (which have no ROS name)."""
    spec = TOPICS[key_name]
    return keys.ros_topic(key_name) if spec.ros_type is not None else f"/{keys.base}/{spec.suffix}"


def pose_topic(keys: Keys) -> str:
    """The topic of the live view's ground-truth camera pose."""
    return f"/{keys.base}/{POSE_SUFFIX}"


@cache
def json_schema(key_name: str) -> str:
    """The JSON schema text of a JSON key's messages."""
    if key_name == "servo_config":
        from ddvs_service.service.config import ServiceConfig

        return json.dumps(ServiceConfig.model_json_schema(), sort_keys=True)
    return (SCHEMA_DIR / f"{JSON_SCHEMAS[key_name]}.json").read_text(encoding="utf-8")


def ros_channel(keys: Keys, key_name: str, ros_type: str | None = None, topic: str | None = None) -> ChannelSpec:
    """The `cdr` channel of a ROS-typed key (`ros_type`/`topic` override the key's type and ROS name)."""
    ros_type = ros_type or TOPICS[key_name].ros_type
    if ros_type is None:
        raise ValueError(f"key {key_name!r} carries JSON, not a ROS type")
    return ChannelSpec(key_name, topic or topic_name(keys, key_name), "cdr", ros_type, "ros2msg",
                       message_definition(ros_type))


def json_channel(keys: Keys, key_name: str) -> ChannelSpec:
    """The `json` channel of a JSON key."""
    return ChannelSpec(key_name, topic_name(keys, key_name), "json", JSON_SCHEMA_NAMES[key_name], "jsonschema",
                       json_schema(key_name))


def frame_rows(frames: str) -> tuple[str, ...]:
    """The camera rows with a channel: every one of `CAMERA_IMAGES` with `frames` `raw` (as published), the
    compressed ones with `png`/`jpeg` (Image frames re-encoded into them), none with `none`."""
    if frames not in ("raw", "png", "jpeg", "none"):
        raise ValueError(f"frames {frames!r}: expected raw, png, jpeg or none")
    if frames == "raw":
        return CAMERA_IMAGES
    return () if frames == "none" else tuple(row for row in CAMERA_IMAGES if row.endswith("_compressed"))


def run_channels(keys: Keys, frames: str = "raw") -> list[ChannelSpec]:
    """Every channel of a servo run; `frames` is `raw` (Image), `png`/`jpeg` (CompressedImage) or `none`."""
    return ([ros_channel(keys, name) for name in (*frame_rows(frames), *ROS_KEYS)]
            + [json_channel(keys, name) for name in JSON_KEYS])
