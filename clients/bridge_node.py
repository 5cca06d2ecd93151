"""The twist bridge on Zenoh: servo twist + arm joint states → arm joint velocity commands.

Subscribes `servo_twist` (`TwistStamped`, camera frame) and `arm_joint_states`; publishes `arm_joint_velocity`
(`JointState` with the bridge's joint names and `velocity`, stamped with the stamp of the twist it realises, so a
lockstep plant can match it to its frame). In ROS 2 mode (docs/ros2.md) it is a ros2_control client instead: it
reads `sensor_msgs/JointState` from `/joint_states` and publishes `std_msgs/Float64MultiArray` velocities in the
configured joint order on `arm_velocity_commands` (`/forward_velocity_controller/commands` by default).

A command is published at once for every new twist (from the newest joint state) and again every `1/rate` seconds,
so a plant always has a fresh command; when the newest twist is older than the deadman (wall time since arrival) the
commands are zero velocities (still stamped with that twist's stamp, so a lockstep plant never mistakes them for the
answer to a newer frame).

Defence in depth (`ddvs_service.protocol.guard.CommandGuard`): a twist is acted on only when its key is exactly this
robot's twist key, it decodes, it is finite, within `BridgeLimits.max_linear`/`max_angular`, and its stamp is no
older than the deadman on the plant's clock (the newest joint-state stamp; the service stamps twists with the frame's
stamp, which the plant made). Every rejection is logged and counted (`guard.rejections`).
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import zenoh
from numpy.typing import NDArray

from clients.bridge import TwistBridge
from ddvs_service.protocol import (
    Header,
    JointState,
    Keys,
    Time,
    decode_joint_state,
    encode_joint_state,
)
from ddvs_service.protocol.endpoints import Endpoints
from ddvs_service.protocol.guard import CommandGuard, CommandLimits
from ddvs_service.protocol.ros import Float64MultiArray, encode_float64_multi_array
from ddvs_service.protocol.ros_graph import BRIDGE_NODE

log = logging.getLogger(__name__)


class BridgeNode:
    """Runs a `TwistBridge` on a Zenoh session (the caller opens and closes the session)."""

    def __init__(self, bridge: TwistBridge, session: zenoh.Session, keys: Keys, rate: float = 100.0) -> None:
        if not rate > 0:
            raise ValueError(f"rate must be > 0 Hz, got {rate}")
        self.bridge, self.period, self.ros = bridge, 1.0 / rate, keys.rmw
        self._endpoints = Endpoints(session, keys, BRIDGE_NODE)
        self._twists = self._endpoints.latest("servo_twist")
        self._joints = self._endpoints.latest("arm_joint_states")
        self._publisher = self._endpoints.publisher("arm_velocity_commands" if self.ros else "arm_joint_velocity")
        self._q: NDArray[np.float64] | None = None
        self._twist_stamp = Time(0, 0)
        self._plant_stamp_ns: int | None = None
        limits = bridge.limits
        self.guard = CommandGuard(keys, limits.deadman, CommandLimits(linear=limits.max_linear,
                                                                      angular=limits.max_angular),
                                  clock=self._plant_clock)
        self.published = 0

    def _plant_clock(self) -> int:
        """The plant's time: the newest joint-state stamp (ns), the wall clock before any arrived."""
        return self._plant_stamp_ns if self._plant_stamp_ns is not None else time.time_ns()

    def close(self) -> None:
        self._endpoints.close()

    def _take_joint_state(self) -> None:
        sample = self._joints.try_recv()
        if sample is None:
            return
        try:
            msg = decode_joint_state(sample.payload.to_bytes())
            by_name = dict(zip(msg.name, msg.position))
            missing = [n for n in self.bridge.joint_names if n not in by_name]
            if missing:
                raise ValueError(f"joint state lacks joints {missing} (has {msg.name})")
            self._q = np.array([by_name[n] for n in self.bridge.joint_names], dtype=np.float64)
            self._plant_stamp_ns = msg.header.stamp.to_ns()
        except ValueError as exc:
            log.warning("ignoring joint state: %s", exc)

    def _take_twist(self, timeout: float) -> bool:
        sample = self._twists.recv(timeout) if timeout > 0 else self._twists.try_recv()
        if sample is None:
            return False
        self._take_joint_state()
        msg = self.guard.twist(str(sample.key_expr), sample.payload.to_bytes())
        if msg is None:
            return False
        self.bridge.set_twist(np.r_[msg.linear, msg.angular], time.monotonic())
        self._twist_stamp = msg.header.stamp
        return True

    def publish_command(self) -> bool:
        """Publish the joint velocities for the newest twist and joint state; False while no joint state is known."""
        self._take_joint_state()
        if self._q is None:
            return False
        velocity = self.bridge.command(self._q, time.monotonic())
        if self.ros:
            self._publisher.put(encode_float64_multi_array(Float64MultiArray(velocity)))
        else:
            msg = JointState(Header(self._twist_stamp, ""), list(self.bridge.joint_names), velocity=velocity)
            self._publisher.put(encode_joint_state(msg))
        self.published += 1
        return True

    def run(self, stop: threading.Event) -> None:
        """Publish on every new twist and at least every period until `stop` is set."""
        next_tick = time.monotonic()
        while not stop.is_set():
            if self._take_twist(max(0.0, next_tick - time.monotonic())):
                self.publish_command()
            if time.monotonic() >= next_tick:
                self.publish_command()
                next_tick += self.period
                next_tick = max(next_tick, time.monotonic() - self.period)  # no burst after a stall
