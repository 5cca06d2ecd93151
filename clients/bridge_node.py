"""The twist bridge on Zenoh: servo twist + arm joint states → arm joint velocity commands.

Subscribes `servo_twist` (`TwistStamped`, camera frame) and `arm_joint_states`; publishes `arm_joint_velocity`
(`JointState` with the bridge's joint names and `velocity`, stamped with the stamp of the twist it realises, so a
lockstep plant can match it to its frame). A command is published at once for every new twist (from the newest
joint state) and again every `1/rate` seconds, so a plant always has a fresh command; when the newest twist is
older than the deadman (wall time since arrival) the commands are zero velocities.
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
    LatestSubscriber,
    Time,
    declare_publisher,
    decode_joint_state,
    decode_twist_stamped,
    encode_joint_state,
)

log = logging.getLogger(__name__)


class BridgeNode:
    """Runs a `TwistBridge` on a Zenoh session (the caller opens and closes the session)."""

    def __init__(self, bridge: TwistBridge, session: zenoh.Session, keys: Keys, rate: float = 100.0) -> None:
        if not rate > 0:
            raise ValueError(f"rate must be > 0 Hz, got {rate}")
        if keys.rmw:
            raise ValueError("the bridge node uses plain ddvs keys; rmw_zenoh mode (rmw_domain_id) is not supported")
        self.bridge, self.period = bridge, 1.0 / rate
        self._twists = LatestSubscriber(session, keys.servo_twist)
        self._joints = LatestSubscriber(session, keys.arm_joint_states)
        self._publisher = declare_publisher(session, keys, "arm_joint_velocity")
        self._q: NDArray[np.float64] | None = None
        self._twist_stamp = Time(0, 0)
        self.published = 0

    def close(self) -> None:
        self._twists.close()
        self._joints.close()
        self._publisher.undeclare()

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
        except ValueError as exc:
            log.warning("ignoring joint state: %s", exc)

    def _take_twist(self, timeout: float) -> bool:
        sample = self._twists.recv(timeout) if timeout > 0 else self._twists.try_recv()
        if sample is None:
            return False
        try:
            msg = decode_twist_stamped(sample.payload.to_bytes())
            twist = np.r_[msg.linear, msg.angular]
            if not np.all(np.isfinite(twist)):
                raise ValueError(f"twist must be finite, got {twist}")
        except ValueError as exc:
            log.warning("ignoring twist: %s", exc)
            return False
        self.bridge.set_twist(twist, time.monotonic())
        self._twist_stamp = msg.header.stamp
        return True

    def publish_command(self) -> bool:
        """Publish the joint velocities for the newest twist and joint state; False while no joint state is known."""
        self._take_joint_state()
        if self._q is None:
            return False
        velocity = self.bridge.command(self._q, time.monotonic())
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
