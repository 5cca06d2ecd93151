"""One robot of a `ddvs serve` process: its keys, pipeline, state machine, persistence, watchdog, status, counters.

`RobotServo` holds everything that belongs to one robot; the process (`service.process`) owns the Zenoh session and
the loop thread and calls in: `listen(session)` subscribes it to its camera (before the warm-up), `open(session)`
declares its queryable, publishers and liveliness token, `handle_inputs()` runs its oldest pending command, adopts
its newest camera info and reports rejected inputs, `handle_frame(arrival)` serves one frame, `watchdog()` zeroes a
standing twist when no valid frame *arrived* within `frame_timeout_s` (a slow frame while valid frames keep arriving
is no timeout), `close(reason)` publishes a zero twist and undeclares everything. Zenoh callbacks only hand samples
to the robot's `Inbox` and wake the loop; the camera's callback first decodes the frame and checks its size.

Per frame: decode (in the camera's callback: the message, with the frame's size checked against the camera's; in the
loop its grey levels, of any supported encoding, a view of the payload for mono8; JPEG/PNG with `camera.transport`
compressed: `ddvs_service.grey`) → rectify (raw frames of a camera whose info has distortion, maps computed once per
camera info: `ddvs_service.rectification`; `camera.images` says whether frames are raw or rectified) → register →
control → publish `servo/twist` (stamped with the frame's stamp, camera frame) and `servo/status`. Bad frames are
rejected and counted; the robot keeps running, and so do the other robots of the process. A rejected frame carries
no image to servo on, so it changes nothing: no twist (the last valid frame's twist stands until a newer valid frame
replaces it or the watchdog zeroes it, `frame_timeout_s` after the last valid frame), no per-frame status;
rejections are reported at most once per `REJECTION_REPORT_S` (one WARNING and one Status naming how many and the
newest reason), so a flood of bad frames costs the loop nothing and cannot interleave zero twists with the servo's.
Never stale: the twist of frame k is withheld (and counted `stale`) when it would go out more than `frame_timeout_s`
after the frame arrived and frames k+1 and k+2 arrived meanwhile — a newer frame's twist is about to follow. (Newer
frames alone are no reason: a camera faster than the loop always has newer frames waiting, and its surplus frames
are superseded in the inbox, so each twist answers the newest frame the loop could take.) Twist stamps on the topic
never decrease: a zero twist that answers no frame (watchdog, `stop`, `reset`, shutdown) carries the newest stamp
published (the camera's clock; 0 before any), and a frame older than that stamp gets no twist (counted `stale`).
Frames in IDLE (no reference, none pending) are not answered. State (reference, servo state, intrinsics, run-time
configuration changes) is persisted atomically in the robot's own state directory by a background writer
(`BackgroundWriter`: no fsync on the loop thread); a restarted robot resumes from it.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh
from numpy.typing import NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.grey import checked_frame, frame_pixels
from ddvs_service.logs import fields
from ddvs_service.protocol import (
    Command,
    CompressedImage,
    Counters,
    Header,
    Image,
    InvalidMessage,
    Keys,
    Latency,
    ProtocolError,
    Reply,
    Roi,
    StateSnapshot,
    Status,
    Time,
    TwistStamped,
    decode_camera_info,
    dump,
    encode_image,
    encode_twist_stamped,
    image_from_array,
    parse_command,
)
from ddvs_service.protocol.control import PROCESS_OPS
from ddvs_service.protocol.endpoints import Endpoints
from ddvs_service.protocol.ros_graph import SERVO_NODE
from ddvs_service.rectification import CameraGeometry, camera_geometry
from ddvs_service.registration.images import to_grey
from ddvs_service.service.config import IntrinsicsConfig, ServiceConfig, deep_merge
from ddvs_service.service.inbox import Arrival, Inbox, Wakeup
from ddvs_service.service.persistence import BackgroundWriter, StateStore
from ddvs_service.service.pipeline import ServoPipeline, StepResult
from ddvs_service.service.residual_publisher import ResidualPublisher
from ddvs_service.service.ros_commands import declare_command_services
from ddvs_service.service.state import ServoState, TransitionError
from kernels.backend import current as current_backend

log = logging.getLogger("ddvs.serve")
ZERO6 = np.zeros(6)
RESUMING_STATES = (ServoState.SERVOING, ServoState.CONVERGED, ServoState.LOST)
STALE_AFTER = 2  # a late frame's twist is stale once this many newer frames have arrived
REJECTION_REPORT_S = 1.0  # rejected inputs are logged and reported in a Status at most this often (seconds)
NOT_PERSISTED = ("zenoh", "state_dir")  # configuration that comes from the command line, never from the state

# a persisted state's reference, ROI, ρ* and last good estimate, adopted once the camera intrinsics are known
_Restored = tuple[NDArray, tuple[int, int, int, int] | None, list[float], NDArray | None]

class RobotServo:
    """One robot's servo. `wakeup`: the loop's shared wake-up (a new one when this robot has the loop to itself)."""

    def __init__(self, config: ServiceConfig, wakeup: Wakeup | None = None) -> None:
        self.store = StateStore(config.state_dir)
        state = self.store.load_json("state.json") or {}
        self._config_changes: dict[str, Any] = state.get("config_changes") or {}
        self.config = self._with_persisted_changes(config)
        self.keys = Keys(self.config.prefix, self.config.robot, self.config.ros)
        self.pipeline = ServoPipeline(self.config, self._known_intrinsics(state))
        self.counters = {"frames": 0, "stale": 0, "idle": 0}
        self._pending_reference: tuple[str, tuple[int, int, int, int] | None] | None = None
        self._resume_state: ServoState | None = None
        self._reference_stamp_ns: int | None = None
        self._geometry: CameraGeometry | None = None  # of the newest camera info: intrinsics, rectification
        self._info_key: tuple[Any, ...] | None = None  # what of that camera info the geometry depends on
        self._frame_id = "camera"  # the camera's frame (header.frame_id of its newest frame)
        self._zero_sent = True
        self._twist_stamp = Time(0, 0)  # the newest stamp published on servo/twist
        self._rejections_reported = (0, -math.inf)  # rejected count at the last report, and its time (monotonic s)
        self._seq = 0
        self._last_status: Status | None = None
        self._persisted_rho: list[float] = []
        self.inbox: Inbox[CheckedFrame] = Inbox(wakeup=wakeup)
        self._ends: Endpoints | None = None  # the robot's subscriptions and publishers (`listen`, `open`)
        self._zenoh: _Declared | None = None
        self._restored_reference: _Restored | None = None
        self.writer = BackgroundWriter(self.store)
        self._restore(state)
        self._persist_config()

    # --- persistence --------------------------------------------------------------------------------------------
    def _with_persisted_changes(self, given: ServiceConfig) -> ServiceConfig:
        """The given configuration (file and command line) with the changes made at run time applied again."""
        if not self._config_changes:
            return given
        try:
            config = given.merged(self._config_changes)
        except ValueError as exc:
            log.error("persisted configuration changes no longer apply to the given configuration; dropped",
                      extra=fields(changes=self._config_changes, error=str(exc)))
            self._config_changes = {}
            return given
        log.info("applied the configuration changes made at run time",
                 extra=fields(changes=self._config_changes, path=str(self.store.dir)))
        return config

    def _known_intrinsics(self, state: dict[str, Any]) -> Intrinsics | None:
        """Configured intrinsics, else those of the last camera info (persisted), else None (wait for one)."""
        if self.config.intrinsics is not None:
            return self.config.intrinsics.to_intrinsics()
        if state.get("intrinsics"):
            return IntrinsicsConfig.model_validate(state["intrinsics"]).to_intrinsics()
        return None

    def _restore(self, state: dict[str, Any]) -> None:
        reference = self.store.load_reference()
        if reference is None:
            return
        roi = tuple(state["roi"]) if state.get("roi") else None
        self._reference_stamp_ns = state.get("reference_stamp_ns")
        self._resume_state = ServoState(state.get("state", "READY"))
        self._restored_reference = (reference, roi, state.get("rho_coeffs") or [], _last_good(state))
        self._try_adopt_restored()

    def _try_adopt_restored(self) -> None:
        restored = self._restored_reference
        if restored is None or self.pipeline.intrinsics is None:
            return
        reference, roi, rho_coeffs, last_good = restored
        self._restored_reference = None
        try:
            self.pipeline.set_reference(reference, roi, rho_coeffs=rho_coeffs, last_good=last_good)
        except ValueError as exc:
            log.error("persisted reference not usable", extra=fields(error=str(exc)))
            return
        if self._resume_state in RESUMING_STATES:
            self.pipeline.machine.resume()
        elif self._resume_state == ServoState.STOPPED:
            self.pipeline.machine.stop()
        log.info("resumed persisted reference", extra=fields(state=self.pipeline.machine.state.value, roi=roi))

    def _persist_state(self) -> None:
        intr = self.pipeline.intrinsics
        self.writer.put_json("state.json", {
            "state": self.pipeline.machine.state.value,
            "roi": list(self.pipeline.roi) if self.pipeline.roi else None,
            "reference_stamp_ns": self._reference_stamp_ns,
            "rho_coeffs": self.pipeline.rho_coeffs,
            "last_good_G": None if self.pipeline.last_good is None else self.pipeline.last_good.ravel().tolist(),
            "intrinsics": None if intr is None else {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy,
                                                     "width": intr.width, "height": intr.height},
            "config_changes": self._config_changes,
        })

    def _persist_config(self) -> None:
        self.writer.put_json("config.json", self.config.model_dump(mode="json", exclude=set(NOT_PERSISTED)))

    # --- the robot on the process's session --------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self.config.robot

    def listen(self, session: zenoh.Session) -> None:
        """Subscribe this robot's inbox to its camera (image and info) on `session`, nothing else: declared before
        the warm-up, the subscription reaches the camera meanwhile and the newest frame waits in the inbox when the
        loop starts (`Inbox` keeps the newest one only; no frame is answered before `open`)."""
        if self._ends is not None:
            return
        ends = Endpoints(session, self.keys, SERVO_NODE)  # in ROS 2 mode: graph tokens, attachments (docs/ros2.md)
        ends.subscriber(self.config.camera.topic, self._on_frame)  # held until `ends.close()`
        ends.subscriber("camera_info", self.inbox.on_info)
        self._ends = ends

    def open(self, session: zenoh.Session) -> None:
        """Declare this robot's endpoints on `session` (from the loop thread; the camera's already if `listen`ed)
        and announce it."""
        k = self.keys
        inbox = self.inbox
        self.listen(session)
        ends = self._ends
        assert ends is not None
        commands = session.declare_queryable(k.key("servo_command"), inbox.on_query)
        if k.rmw:
            declare_command_services(ends, inbox.on_query)
        self._pub = {name: ends.publisher(name)
                     for name in ("servo_twist", "servo_status", "servo_state", "servo_config", "servo_reference")}
        self._residual = ResidualPublisher(ends.publisher("servo_residual"))
        token = session.liveliness().declare_token(k.key("liveliness"))
        self._zenoh = _Declared(commands, token)
        log.info("serving", extra=fields(robot=self.config.robot, prefix=self.config.prefix,
                                          state=self.pipeline.machine.state.value, state_dir=str(self.store.dir)))
        self._publish_config()
        self._publish_state("started")

    def close(self, reason: str) -> None:
        """Zero twist, a last state naming `reason`, every endpoint undeclared, pending writes flushed, the
        background re-acquisition ended."""
        try:
            if self._zenoh is not None:
                self._publish_zero_twist()
                self._publish_state(f"stopped: {reason}")
                self._zenoh.token.undeclare()
                self._residual.close()
                self._zenoh.commands.undeclare()
                self._zenoh = None
                log.info("robot stopped", extra=fields(robot=self.config.robot, reason=reason,
                                                        **self.current_counters().model_dump(),
                                                        received=self.inbox.frames_received))
            if self._ends is not None:
                self._ends.close()
                self._ends = None
        finally:
            self._persist_state()  # with the last good estimate, where a restart re-acquires from first
            self.writer.close()
            self.pipeline.close()

    def wait_timeout(self, longest_s: float) -> float:
        """Seconds the loop may sleep for this robot: until its watchdog is due while a non-zero twist stands,
        `longest_s` at most."""
        if self._zero_sent:
            return longest_s
        due = self.inbox.last_arrival_t + self.config.frame_timeout_s - time.monotonic()
        return min(max(due, 0.0), longest_s)

    def handle_inputs(self) -> None:
        """The oldest pending command, then the newest camera info, then the report of rejected inputs when due."""
        self._handle_query(self.inbox.take_query())
        self._handle_info(self.inbox.take_info())
        self._report_rejections()

    # --- inputs -------------------------------------------------------------------------------------------------
    def _handle_info(self, sample: zenoh.Sample | None) -> None:
        if sample is None or self.config.intrinsics is not None:
            return  # configured intrinsics take precedence over camera info
        try:
            info = decode_camera_info(sample.payload.to_bytes())
            key = (info.width, info.height, info.distortion_model, info.d.tobytes(), info.k.tobytes(),
                   info.r.tobytes(), info.p.tobytes(), info.binning_x, info.binning_y, info.roi)
            if key == self._info_key:
                return  # a camera sends its info with every frame: the maps are computed once per calibration
            geometry = camera_geometry(info, rectified=self.config.camera.images == "rect")
            if geometry.intrinsics != self.pipeline.intrinsics:
                self.pipeline.set_intrinsics(geometry.intrinsics)
                self._try_adopt_restored()
                self._persist_state()
            self._geometry, self._info_key = geometry, key
        except (ProtocolError, ValueError) as exc:
            self.inbox.reject(f"camera info rejected: {exc}")

    def _on_frame(self, sample: zenoh.Sample) -> None:
        """Zenoh's thread: decode the frame and check its size against the camera's; the inbox keeps it, or counts
        it rejected."""
        t = time.monotonic()
        try:
            msg, size = checked_frame(sample.payload.to_bytes(), self.config.camera.transport == "compressed",
                                      self.config.max_frame_bytes)
            intrinsics = self.pipeline.intrinsics
            if intrinsics is not None and size != (intrinsics.width, intrinsics.height):
                raise ValueError(f"frame is {size[0]}×{size[1]}; the camera is "
                                 f"{intrinsics.width}×{intrinsics.height}")
        except (ProtocolError, ValueError) as exc:
            self.inbox.reject(f"frame rejected: {exc}")
            return
        self.inbox.on_frame(CheckedFrame(msg, time.monotonic() - t), t)

    def handle_frame(self, arrival: Arrival[CheckedFrame]) -> None:
        """Serve one frame taken from this robot's inbox, with the newest camera info that arrived before it (a
        camera's info and image come on two topics, possibly over two links, in either order)."""
        self._handle_info(self.inbox.take_info())
        if self.pipeline.machine.state == ServoState.IDLE and self._pending_reference is None:
            self.counters["idle"] += 1  # nothing to servo to: no twist, no status
            return
        t_taken, cpu_taken = time.monotonic(), time.process_time()
        msg = arrival.sample.msg
        header = msg.header
        try:
            pixels = frame_pixels(msg, self.config.max_frame_bytes)
            image = pixels if self._geometry is None else self._geometry.frame(pixels)
        except (ProtocolError, ValueError) as exc:
            self.inbox.reject(f"frame rejected: {exc}")
            return
        self._frame_id = header.frame_id
        t_decoded = time.monotonic()
        if self._pending_reference is not None:
            self._adopt_next_frame(image, header)
        try:
            step = self.pipeline.step(image)
        except ValueError as exc:
            self.inbox.reject(f"frame rejected: {exc}")
            return
        self.counters["frames"] += 1
        t_publish = time.monotonic()
        newer = self.inbox.frames_received - arrival.index
        late = t_publish - arrival.t > self.config.frame_timeout_s and newer >= STALE_AFTER
        stale = late or header.stamp.to_ns() < self._twist_stamp.to_ns()
        if stale:
            self.counters["stale"] += 1
            step.message = (f"stale: twist withheld, {newer} newer frames arrived in the "
                            f"{t_publish - arrival.t:.3f} s since the frame did" if late else "stale: twist "
                            "withheld, its frame is older than the newest twist published (stamps never decrease)")
        else:
            self._publish_twist(step.twist, header.stamp, header.frame_id)
        t_done = time.monotonic()
        latency = {
            "decode": (arrival.sample.decode_s + t_decoded - t_taken) * 1e3,
            "registration": step.timings_ms.get("registration", 0.0),
            "control": step.timings_ms.get("control", 0.0),
            "publish": (t_done - t_publish) * 1e3,
            "total": (t_done - arrival.t) * 1e3,
            "cpu": (time.process_time() - cpu_taken) * 1e3,
        }
        self._publish_status(step, header.stamp.to_ns(), latency, stale)
        self._residual.offer(header, lambda: self.pipeline.residual(image))

    def _report_rejections(self) -> None:
        """One WARNING and one Status for the inputs rejected since the last report, at most once per
        `REJECTION_REPORT_S` (the first one at once)."""
        rejected, reason = self.inbox.rejections
        reported, t_reported = self._rejections_reported
        now = time.monotonic()
        if rejected == reported or now - t_reported < REJECTION_REPORT_S:
            return
        self._rejections_reported = (rejected, now)
        since = "" if math.isinf(t_reported) else f" in the last {now - t_reported:.1f} s"
        message = f"{rejected - reported} input(s) rejected{since} ({rejected} in all), the newest: {reason}"
        log.warning(message, extra=fields(robot=self.config.robot, rejected=rejected, newest=reason))
        state = self.pipeline.machine.state
        self._emit_status(Status(robot=self.config.robot, state=state.value, frame_stamp_ns=0, seq=self._next_seq(),
                                 error=[0.0] * 6, error_norm=0.0, iterations=0, residual_rms=0.0, inlier_ratio=0.0,
                                 twist=[0.0] * 6, latency_ms=Latency(decode=0, registration=0, control=0, publish=0,
                                                                     total=0),
                                 counters=self.current_counters(), message=message[:500],
                                 backend=current_backend()))

    def _adopt_next_frame(self, image: NDArray, header: Header) -> None:
        assert self._pending_reference is not None
        if self.pipeline.intrinsics is None:
            log.warning("reference from the next frame waits for a camera info",
                        extra=fields(hint="configure 'intrinsics' or publish camera info"))
            return  # kept pending: the camera's info for this frame may still be on its way
        _, roi = self._pending_reference
        self._pending_reference = None
        try:
            self._set_reference(image, roi, header, G0=np.eye(3))
        except ValueError as exc:
            log.error("reference from the next frame refused", extra=fields(error=str(exc)))

    def watchdog(self) -> None:
        """A zero twist when no valid frame arrived within `frame_timeout_s` while a non-zero twist stands."""
        if self._zero_sent or time.monotonic() - self.inbox.last_arrival_t < self.config.frame_timeout_s:
            return
        log.warning("no frame within the timeout: zero twist", extra=fields(timeout_s=self.config.frame_timeout_s))
        self._publish_zero_twist()

    # --- commands -----------------------------------------------------------------------------------------------
    def _handle_query(self, query: zenoh.Query | None) -> None:
        if query is None:
            return
        try:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            reply = self.handle_command(payload)
            query.reply(query.key_expr, dump(reply))
        finally:
            query.drop()

    def handle_command(self, payload: bytes) -> Reply:
        """Execute one JSON command; any failure is a `Reply.failure` naming the problem, with state unchanged."""
        try:
            command = parse_command(payload)
        except (InvalidMessage, ProtocolError) as exc:
            log.warning("command rejected", extra=fields(robot=self.config.robot, error=str(exc)))
            return Reply.failure(str(exc))
        if command.op in PROCESS_OPS:
            return Reply.failure(f"{command.op} is a command of the serving process: send it to the process's key "
                                 "<prefix>/serve/<process>/command, not to a robot's servo/command")
        try:
            data = self._execute(command)
        except (TransitionError, ValueError, ProtocolError) as exc:
            log.warning("command refused", extra=fields(op=command.op, id=command.id, error=str(exc)))
            return Reply.failure(f"{command.op}: {exc}")
        log.info("command executed", extra=fields(op=command.op, id=command.id,
                                                    state=self.pipeline.machine.state.value))
        return Reply.success(data)

    def _execute(self, command: Command) -> dict[str, Any] | None:
        machine = self.pipeline.machine
        op = command.op
        if op == "get_state":
            return self._snapshot().model_dump(mode="json")
        if op == "get_config":
            return self.config.model_dump(mode="json", exclude={"zenoh"})
        if op == "set_config":
            assert command.config is not None
            new = self.config.merged(command.config, self.pipeline.intrinsics)
            start_only = self.config.start_only_changes(new)
            if start_only:
                raise ValueError(f"{', '.join(start_only)} cannot change while it is served: read when the robot "
                                 "starts (prefix and robot name its keys: remove_robot, then add_robot under the new "
                                 "name; the others: restart the service with the new configuration)")
            self.pipeline.apply_config(new)
            self.config = new
            changes = {key: value for key, value in command.config.items() if key not in NOT_PERSISTED}
            self._config_changes = deep_merge(self._config_changes, changes)
            self._persist_state()
            self._persist_config()
            self._publish_config()
            return new.model_dump(mode="json", exclude={"zenoh"})
        if op == "set_reference":
            roi = _roi_tuple(command.roi)
            if command.source == "upload":
                assert command.image is not None
                self._set_reference(self._uploaded(command.image.to_array(self.config.max_frame_bytes)), roi,
                                    Header(Time.now(), self._frame_id), G0=None)
                return self._snapshot().model_dump(mode="json")
            self._pending_reference = ("next_frame", roi)
            return {"pending": "the next camera frame becomes the reference"}
        if op == "start":
            machine.start()
        elif op == "stop":
            machine.stop()
            self._publish_zero_twist()
        elif op == "reset":
            self.pipeline.clear_reference()
            self.writer.remove_reference()
            self._reference_stamp_ns = None
            self._publish_zero_twist()
        self._persist_state()
        self._publish_state(f"{op} command")
        return self._snapshot().model_dump(mode="json")

    def _uploaded(self, image: NDArray) -> NDArray:
        """An uploaded reference as the live frames are registered: a raw frame of the camera's size goes through
        the same rectification (the camera's raw frames and an upload saved from them match)."""
        rectifier = None if self._geometry is None else self._geometry.rectifier
        if rectifier is None or image.shape[:2] != rectifier.map_x.shape:
            return image
        return rectifier(image if image.ndim == 2 else to_grey(image))

    def _set_reference(self, image: NDArray, roi: tuple[int, int, int, int] | None, header: Header,
                       G0: NDArray | None) -> None:
        """Adopt `image` (grey, as registered) as the reference and publish it on `servo/reference` with `header`:
        the camera frame's own (frame_id and stamp of the frame it came from), or for an upload the camera's
        frame_id stamped at the upload."""
        roi_used = self.pipeline.set_reference(image, roi, G0=G0)
        self._reference_stamp_ns = header.stamp.to_ns()
        reference = np.ascontiguousarray(image)
        self.writer.put_reference(reference.copy())
        self._persist_state()
        self._pub["servo_reference"].put(encode_image(reference_image(reference, header)))
        self._publish_state(f"reference set, roi {list(roi_used)}")

    # --- outputs ------------------------------------------------------------------------------------------------
    def _publish_twist(self, twist: NDArray[np.float64], stamp: Time, frame_id: str) -> None:
        values = twist.tolist()  # plain floats: the checks below run on every frame
        if not all(map(math.isfinite, values)):
            log.error("non-finite twist replaced by zero", extra=fields(twist=values))
            values = [0.0] * 6
        msg = TwistStamped(Header(stamp, frame_id), np.array(values[:3]), np.array(values[3:]))
        self._pub["servo_twist"].put(encode_twist_stamped(msg))
        self._zero_sent = not any(values)
        self._twist_stamp = stamp

    def _publish_zero_twist(self) -> None:
        """A zero twist that answers no frame, stamped with the newest stamp published (never earlier: a later
        frame's twist would otherwise carry an older stamp than this one)."""
        self._publish_twist(ZERO6, self._twist_stamp, self._frame_id)

    def _publish_status(self, step: StepResult, stamp_ns: int, latency: dict[str, float], stale: bool) -> None:
        """The frame's `Status`: every frame with `status_every_frame`, else on a state change or a stale twist."""
        previous = self._last_status.state if self._last_status else None
        changed = previous != step.state.value
        if self.config.status_every_frame or changed or stale:
            # one validation of the whole message, the nested latency and counters given as plain dicts
            self._emit_status(Status.model_validate({
                "robot": self.config.robot, "state": step.state.value, "frame_stamp_ns": stamp_ns,
                "seq": self._next_seq(), "error": step.error.tolist(), "error_norm": step.error_norm,
                "iterations": step.iterations, "residual_rms": step.residual_rms,
                "inlier_ratio": min(max(step.inlier_ratio, 0.0), 1.0), "twist": step.twist.tolist(),
                "latency_ms": latency, "counters": self._counts(), "message": step.message[:500],
                "backend": current_backend(),
            }))
        if changed or self.pipeline.rho_coeffs != self._persisted_rho:
            self._persisted_rho = list(self.pipeline.rho_coeffs)
            self._persist_state()
            self._publish_state(step.message or "frame")

    def _emit_status(self, status: Status) -> None:
        self._last_status = status
        self._pub["servo_status"].put(dump(status))

    def _publish_state(self, message: str) -> None:
        self._pub["servo_state"].put(dump(self._snapshot(message)))

    def _publish_config(self) -> None:
        self._pub["servo_config"].put(dump_json(self.config.model_dump(mode="json", exclude={"zenoh"})))

    def _snapshot(self, message: str = "") -> StateSnapshot:
        G = self.pipeline.G
        roi = self.pipeline.roi
        return StateSnapshot(
            robot=self.config.robot, state=self.pipeline.machine.state.value,
            has_reference=self.pipeline.reference is not None, reference_stamp_ns=self._reference_stamp_ns,
            roi=None if roi is None else Roi(x=roi[0], y=roi[1], width=roi[2], height=roi[3]),
            homography=None if G is None else [float(x) for x in (G / G[2, 2]).reshape(-1)],
            last_status=self._last_status, message=message[:500],
        )

    def current_counters(self) -> Counters:
        """The counters of `Status.counters` now."""
        return Counters.model_validate(self._counts())

    def _counts(self) -> dict[str, int]:
        return {"dropped": self.inbox.frames_superseded, "rejected": self.inbox.rejections[0], **self.counters}

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq


@dataclass(frozen=True)
class CheckedFrame:
    """A camera frame as the subscriber accepted it: the decoded message (its pixels a view of the payload) and the
    seconds its decoding and checks took."""

    msg: Image | CompressedImage
    decode_s: float


@dataclass(frozen=True)
class _Declared:
    """What `open` declared on the session besides the robot's `Endpoints` (undeclared by `close`)."""

    commands: zenoh.Queryable[None]
    token: zenoh.LivelinessToken


def dump_json(obj: dict[str, Any]) -> bytes:
    return json.dumps(obj).encode()


def _roi_tuple(roi: Roi | None) -> tuple[int, int, int, int] | None:
    return None if roi is None else (roi.x, roi.y, roi.width, roi.height)


def reference_image(reference: NDArray, header: Header) -> Image:
    """The reference as published: grey levels as the engine registers them, mono8 when they are bytes, else 32FC1
    (16-bit and float frames, grey levels 0–255); a colour upload as its BT.601 grey."""
    grey = reference if reference.ndim == 2 else to_grey(reference)
    if grey.dtype == np.uint8:
        return image_from_array(np.ascontiguousarray(grey), "mono8", header)
    return image_from_array(np.ascontiguousarray(grey, dtype=np.float32), "32FC1", header)


def _last_good(state: dict[str, Any]) -> NDArray | None:
    """The persisted last good estimate `G` (3×3, finite, positive determinant), None when absent or unusable."""
    values = state.get("last_good_G")
    if values is None:
        return None
    try:
        G = np.asarray(values, dtype=np.float64).reshape(3, 3)
        usable = bool(np.all(np.isfinite(G)) and np.linalg.det(G) > 0.0)
    except (TypeError, ValueError):  # not 9 numbers
        usable = False
    if not usable:
        log.error("persisted last good estimate not usable; the first frame is initialised globally",
                  extra=fields(last_good_G=values))
        return None
    return G
