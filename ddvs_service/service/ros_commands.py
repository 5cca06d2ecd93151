"""The servo service's commands as ROS 2 services: `std_srvs/srv/Trigger` on `<node>/start`, `stop`, `reset` and
`set_reference` (the next camera frame becomes the reference, whole image or the configured ROI).

Why Trigger services and not a topic (docs/ros2.md): a command needs an answer (refused in this state, the reference
is pending, …) and Trigger's `success` + `message` carry the JSON reply's `ok` + error; `ros2 service call` and any
rclpy/rclcpp client call them with a standard type, without ddvs's messages. Each request is handed to the node's
command loop as the equivalent JSON command, so both planes share one code path and one order of execution.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from functools import partial
from typing import Any

import zenoh

from ddvs_service.logs import fields
from ddvs_service.protocol import PROTOCOL_VERSION, ProtocolError
from ddvs_service.protocol.endpoints import Endpoints, read_trigger_request, reply_trigger
from ddvs_service.protocol.rmw import RmwAttachment

log = logging.getLogger("ddvs.serve")

ROS_COMMANDS: dict[str, dict[str, Any]] = {
    "start": {"op": "start"},
    "stop": {"op": "stop"},
    "reset": {"op": "reset"},
    "set_reference": {"op": "set_reference", "source": "next_frame"},
}
"""Service name (under the node's name) → the JSON command it runs."""


class TriggerCommand:
    """A Trigger request presented to the command loop as a JSON command query (`payload`, `key_expr`, `reply`,
    `drop`); `reply` turns the JSON `Reply` into the Trigger response (success = ok, message = the error or state)."""

    def __init__(self, query: zenoh.Query, command: dict[str, Any], request: RmwAttachment) -> None:
        self._query, self._request = query, request
        self.op = command["op"]
        self.payload = zenoh.ZBytes(json.dumps({"protocol_version": PROTOCOL_VERSION, **command}).encode())

    @property
    def key_expr(self) -> zenoh.KeyExpr:
        return self._query.key_expr

    def reply(self, _key_expr: object, payload: bytes) -> None:
        reply = json.loads(payload)
        data = reply.get("data") or {}
        if reply["ok"]:
            message = data.get("pending") or f"{self.op}: done, state {data.get('state')}"
        else:
            message = reply.get("error") or f"{self.op} failed"
        reply_trigger(self._query, self._request, bool(reply["ok"]), message)

    def drop(self) -> None:
        self._query.drop()


def _on_trigger(command: dict[str, Any], on_query: Callable[[Any], None], query: zenoh.Query) -> None:
    try:
        request = read_trigger_request(query)
    except ProtocolError as exc:
        log.warning("ROS service request refused", extra=fields(key=str(query.key_expr), error=str(exc)))
        query.drop()
        return
    on_query(TriggerCommand(query, command, request))


def declare_command_services(endpoints: Endpoints, on_query: Callable[[Any], None]) -> list[str]:
    """Declare the Trigger services (ROS 2 mode); each request goes to `on_query` like a JSON command query.
    Returns the services' full names."""
    return [endpoints.trigger_service(name, partial(_on_trigger, command, on_query))
            for name, command in ROS_COMMANDS.items()]
