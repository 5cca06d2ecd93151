"""Which mode a node runs in — plain ddvs keys or ROS 2 over rmw_zenoh — and its ROS names (docs/ros2.md).

`RosSettings.domain_id = None` (the default) keeps the plain `<prefix>/<robot>/…` keys. A domain id switches the
ROS-typed topics to rmw_zenoh keys under ROS names: each row of `keys.TOPICS` with a ROS type has a default ROS name
(`ros_name`), relative names resolve in `namespace`, and `topics` remaps rows (`{"camera_image": "/cam/image_raw"}`).
Every node's CLI has `--ros-domain-id N`, `--ros-namespace NS` and `--ros-topic ROW:=NAME` (`protocol.ros_cli`).
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, field_validator

from ddvs_service.protocol.ros_graph import check_ros_name


class RosSettings(BaseModel):
    """ROS 2 mode of one node: `domain_id` (None: plain ddvs keys), `namespace`, node name override, remapping."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    domain_id: int | None = Field(default=None, ge=0, le=232, description=(
        "ROS 2 domain (0 to 232) of ROS 2 mode over rmw_zenoh; null: plain ddvs keys."))
    namespace: str = Field(default="/", description="ROS namespace of the node's relative names.")
    node_name: str | None = Field(default=None, description="The node's name instead of its default.")
    topics: dict[str, str] = Field(default_factory=dict, description="Remapping: {ddvs key name: ROS topic name}.")

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
