"""The arm plant on Zenoh: publishes frames, camera info, joint states and ground truth; consumes joint velocities.

Keys (`ddvs_service.protocol.Keys`): publishes `camera_image` (mono8), `camera_info`, `arm_joint_states`
(position + velocity) and `arm_ground_truth` (evaluation only: `T_world_cam`, OpenCV axes); subscribes
`arm_joint_velocity` (`JointState` whose `velocity` gives rad/s per named joint; unnamed joints get 0). In ROS 2
mode (docs/ros2.md) it stands for a robot under ros2_control: `/image_raw`, `/camera_info`, `/joint_states`, and
velocity commands as `std_msgs/Float64MultiArray` in the arm's joint order on `arm_velocity_commands`
(`/forward_velocity_controller/commands`); those carry no stamp, so ROS 2 mode runs the realtime clock only.
Every message of frame k carries the same stamp: node start wall time + simulated time of frame k.

Clocks:
- `realtime`: ticks at `fps` on the wall clock; the physics always advances with the wall clock and, when a frame
  takes longer than a period, the missed frames are dropped (the plant is never slowed). A command older than
  `deadman` seconds (wall time) is replaced by zero velocities.
- `lockstep`: publish frame k, then wait for a command stamped ≥ frame k's stamp (the servo and the bridge pass the
  frame stamp along) or `lockstep_timeout` seconds (then zero velocities), and step one period. Deterministic.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
import zenoh
from numpy.typing import NDArray

from ddvs_service.protocol import (
    CameraInfo,
    GroundTruth,
    Header,
    JointState,
    Keys,
    Time,
    dump,
    encode_camera_info,
    encode_image,
    encode_joint_state,
    image_from_array,
)
from ddvs_service.protocol.endpoints import Endpoints
from ddvs_service.protocol.guard import CommandGuard, CommandLimits
from ddvs_service.protocol.ros_graph import ARM_SIM_NODE
from sim.arm import ArmSim

log = logging.getLogger(__name__)
CAMERA_FRAME_ID = "camera"
WORLD_FRAME_ID = "world"


@dataclass(frozen=True)
class ArmNodeSettings:
    """`clock` "realtime" or "lockstep"; `fps` frames (and control periods) per second; `deadman` seconds a command
    stays valid (realtime); `lockstep_timeout` seconds to wait for command k (lockstep); `max_frames` stop after
    that many published frames (None: run until stopped)."""

    clock: Literal["realtime", "lockstep"] = "realtime"
    fps: float = 30.0
    deadman: float = 0.1
    lockstep_timeout: float = 1.0
    max_frames: int | None = None

    def __post_init__(self) -> None:
        if self.clock not in ("realtime", "lockstep"):
            raise ValueError(f"clock {self.clock!r} unknown; expected 'realtime' or 'lockstep'")
        for name in ("fps", "deadman", "lockstep_timeout"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")


@dataclass
class _Command:
    velocity: NDArray[np.float64]
    stamp_ns: int
    received: float  # time.monotonic() at arrival


class ArmNode:
    """Runs an `ArmSim` on a Zenoh session (the caller opens and closes the session)."""

    def __init__(self, sim: ArmSim, session: zenoh.Session, keys: Keys, settings: ArmNodeSettings) -> None:
        if keys.rmw and settings.clock == "lockstep":
            raise ValueError("lockstep needs the plain ddvs protocol: ROS 2 velocity commands (Float64MultiArray) "
                             "carry no stamp to match a frame; use the realtime clock in ROS 2 mode")
        self.sim, self.keys, self.settings = sim, keys, settings
        self._endpoints = Endpoints(session, keys, ARM_SIM_NODE)
        self._pub = {name: self._endpoints.publisher(name) for name in (
            "camera_image", "camera_info", "arm_joint_states", "arm_ground_truth")}
        self._commands = self._endpoints.latest("arm_velocity_commands" if keys.rmw else "arm_joint_velocity")
        self._command: _Command | None = None
        self._epoch_ns = time.time_ns()
        # Defence in depth: only this robot's key, stamps within the deadman on the simulated clock, known joints,
        # finite velocities within the URDF limits (plus rounding slack); every rejection logged and counted.
        bounds = {n: float(v) * (1 + 1e-6) + 1e-9 for n, v in zip(sim.joint_names, sim.kinematics.velocity_limit)}
        self.guard = CommandGuard(keys, settings.deadman, CommandLimits(joint_velocity=bounds), clock=self.stamp_ns)
        self.frames = 0
        self.dropped = 0
        self.render_seconds = 0.0  # total time spent in `ArmSim.render` (mean = render_seconds / frames)

    def close(self) -> None:
        self._endpoints.close()

    def stamp_ns(self) -> int:
        """Stamp of the current simulated instant (ns since the Unix epoch)."""
        return self._epoch_ns + round(self.sim.time * 1e9)

    def publish(self) -> int:
        """Publish joint states, camera info, image and ground truth of the current instant; returns the stamp."""
        stamp_ns = self.stamp_ns()
        stamp = Time.from_ns(stamp_ns)
        state = self.sim.joint_state()
        started = time.perf_counter()
        image = self.sim.render()
        self.render_seconds += time.perf_counter() - started
        joints = JointState(Header(stamp, WORLD_FRAME_ID), list(state.names), state.position, state.velocity)
        self._pub["arm_joint_states"].put(encode_joint_state(joints))
        info = CameraInfo.from_intrinsics(self.sim.intrinsics, Header(stamp, CAMERA_FRAME_ID))
        self._pub["camera_info"].put(encode_camera_info(info))
        self._pub["camera_image"].put(encode_image(image_from_array(image, "mono8", Header(stamp, CAMERA_FRAME_ID))))
        truth = GroundTruth(stamp_ns=stamp_ns, frame_id=WORLD_FRAME_ID,
                            camera_pose=self.sim.camera_pose().reshape(-1).tolist(),
                            joint_positions=state.position.tolist())
        self._pub["arm_ground_truth"].put(dump(truth))
        self.frames += 1
        return stamp_ns

    def _poll_command(self, timeout: float = 0.0) -> bool:
        """Take the newest command (waiting up to `timeout` s); True when one arrived."""
        sample = self._commands.recv(timeout) if timeout > 0 else self._commands.try_recv()
        if sample is None:
            return False
        key, payload = str(sample.key_expr), sample.payload.to_bytes()
        if self.keys.rmw:
            msg = self.guard.velocity_array(key, payload, list(self.sim.joint_names))
        else:
            msg = self.guard.joint_velocity(key, payload)
        if msg is None:
            return False
        velocity = self._velocity_by_name(msg)
        self._command = _Command(velocity, msg.header.stamp.to_ns(), time.monotonic())
        return True

    def _velocity_by_name(self, msg: JointState) -> NDArray[np.float64]:
        """Velocities in this arm's joint order (the guard checked names, count, finiteness and bounds)."""
        velocity = np.zeros(len(self.sim.joint_names))
        for name, v in zip(msg.name, msg.velocity):
            velocity[self.sim.joint_names.index(name)] = v
        return velocity

    def _zero(self) -> NDArray[np.float64]:
        return np.zeros(len(self.sim.joint_names))

    def _done(self, stop: threading.Event) -> bool:
        limit = self.settings.max_frames
        return stop.is_set() or (limit is not None and self.frames >= limit)

    def run(self, stop: threading.Event | None = None) -> None:
        """Loop with the configured clock until `stop` is set or `max_frames` frames were published."""
        stop = stop or threading.Event()
        if self.settings.clock == "lockstep":
            self._run_lockstep(stop)
        else:
            self._run_realtime(stop)

    def _run_lockstep(self, stop: threading.Event) -> None:
        period = 1.0 / self.settings.fps
        while not self._done(stop):
            stamp_ns = self.publish()
            deadline = time.monotonic() + self.settings.lockstep_timeout
            velocity = self._zero()
            while not stop.is_set():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    log.info("lockstep: no command for frame stamped %d within %.3f s; holding still",
                             stamp_ns, self.settings.lockstep_timeout)
                    break
                command = self._command if self._poll_command(min(remaining, 0.05)) else None
                if command is not None and command.stamp_ns >= stamp_ns:
                    velocity = command.velocity
                    break
            self.sim.step(velocity, period)

    def _run_realtime(self, stop: threading.Event) -> None:
        period = 1.0 / self.settings.fps
        start = time.monotonic()
        ticks = 0
        while not self._done(stop):
            wait = start + (ticks + 1) * period - time.monotonic()
            if wait > 0:
                stop.wait(wait)
            due = math.floor((time.monotonic() - start) / period)
            if due <= ticks:  # woken early (stop requested)
                continue
            self._poll_command()
            command = self._command
            if command is None or time.monotonic() - command.received > self.settings.deadman:
                velocity = self._zero()
            else:
                velocity = command.velocity
            self.sim.step(velocity, (due - ticks) * period)
            self.dropped += due - ticks - 1
            ticks = due
            self.publish()
