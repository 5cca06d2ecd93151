"""Defence in depth for the nodes that move a robot: check every command sample before acting on it.

Zenoh access control (`security.py`) decides who may publish; `CommandGuard` decides, in the receiving node, whether
a sample that arrived is a command to act on. A command is accepted only when all of these hold:

- its key is exactly this robot's key for that topic (`Keys.servo_twist` / `Keys.arm_joint_velocity` /
  `Keys.arm_velocity_commands` in ROS 2 mode, a `Float64MultiArray` in the configured joint order): a sample of
  another robot's namespace, or of a wildcard subscription that matched more, is refused (`foreign_key`);
- it decodes as the ROS message of `TOPICS` (`malformed` otherwise, e.g. truncated CDR; the twist decoder also
  refuses non-finite values);
- its header stamp is not older than `deadman_s` (`stale`) nor later than `future_tolerance_s` (`future`) on the
  receiver's clock (`clock`, nanoseconds since the Unix epoch: `time.time_ns` by default; a plant that stamps in
  simulated time passes its own stamp clock) — except a joint-velocity command of all zeros: stopping is always
  allowed, however old the stamp (a bridge whose own deadman fired keeps sending zeros with its last twist's stamp);
- its joint velocities are finite (`non_finite`) and its values within `CommandLimits` (`out_of_range`); a
  joint-velocity command must carry one velocity per named joint (`no_velocity`), name each joint once and, with
  per-joint limits, only known joints (`unknown_joint`).

Each rejection is logged (logger `ddvs.guard`, WARNING, structured fields `reason`, `topic`, `key`, `detail`,
`count`) and counted in `rejections[reason]`; accepted commands are counted in `accepted`.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from ddvs_service.protocol.errors import ProtocolError
from ddvs_service.protocol.keys import Keys
from ddvs_service.protocol.ros import (
    Header,
    JointState,
    Time,
    TwistStamped,
    decode_float64_multi_array,
    decode_joint_state,
    decode_twist_stamped,
)

log = logging.getLogger("ddvs.guard")

REASONS = ("foreign_key", "malformed", "stale", "future", "non_finite", "out_of_range", "no_velocity", "unknown_joint")


@dataclass(frozen=True)
class CommandLimits:
    """Largest commands a receiver acts on: `linear` ‖v‖ (m/s) and `angular` ‖ω‖ (rad/s) of a twist (norms, as the
    service's saturation), and `joint_velocity` |q̇ᵢ| (rad/s, or m/s for prismatic joints): one bound for every
    joint, or a bound per joint name. Infinite means unchecked."""

    linear: float = math.inf
    angular: float = math.inf
    joint_velocity: float | Mapping[str, float] = math.inf
    _per_joint: Mapping[str, float] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        bounds = {"linear": self.linear, "angular": self.angular}
        per_joint = dict(self.joint_velocity) if isinstance(self.joint_velocity, Mapping) else {}
        bounds.update({f"joint_velocity[{name}]": value for name, value in per_joint.items()})
        if not isinstance(self.joint_velocity, Mapping):
            bounds["joint_velocity"] = self.joint_velocity
        for what, value in bounds.items():
            if not (isinstance(value, int | float) and value > 0):  # NaN fails too
                raise ValueError(f"CommandLimits.{what} = {value!r}: expected a positive number (math.inf: no bound)")
        object.__setattr__(self, "_per_joint", per_joint)

    @property
    def joint_names(self) -> tuple[str, ...]:
        """The joints with their own bound (empty when one bound applies to every joint)."""
        return tuple(self._per_joint)

    def joint_bound(self, name: str) -> float | None:
        """The velocity bound of joint `name`; None when per-joint bounds are given and `name` has none."""
        if isinstance(self.joint_velocity, Mapping):
            return self._per_joint.get(name)
        return float(self.joint_velocity)


class CommandGuard:
    """Accepts or rejects command samples of robot `keys` (see the module docstring). `deadman_s` is the oldest
    command age acted on (seconds, > 0); `future_tolerance_s` the clock skew tolerated for stamps ahead of `clock`."""

    def __init__(
        self,
        keys: Keys,
        deadman_s: float,
        limits: CommandLimits,
        future_tolerance_s: float = 0.05,
        clock: Callable[[], int] = time.time_ns,
    ) -> None:
        for what, value in (("deadman_s", deadman_s), ("future_tolerance_s", future_tolerance_s)):
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"CommandGuard {what} = {value!r}: expected a finite number of seconds ≥ 0")
        if deadman_s == 0:
            raise ValueError("CommandGuard deadman_s = 0: expected a positive number of seconds")
        self.keys = keys
        self.limits = limits
        self.deadman_ns = int(deadman_s * 1e9)
        self.future_ns = int(future_tolerance_s * 1e9)
        self.clock = clock
        self.rejections: Counter[str] = Counter()
        self.accepted = 0

    def twist(self, key: str, payload: bytes | bytearray | memoryview) -> TwistStamped | None:
        """The twist command of sample (`key`, `payload`) if it is acceptable, else None (logged and counted)."""
        topic = "servo_twist"
        if not self._own_key(topic, key):
            return None
        try:
            msg = decode_twist_stamped(payload)
        except ProtocolError as exc:
            self._reject("malformed", topic, key, str(exc))
            return None
        if not self._fresh(topic, key, msg.header.stamp.to_ns()):
            return None
        v, w = float(np.linalg.norm(msg.linear)), float(np.linalg.norm(msg.angular))  # finite: the decoder checks
        if v > self.limits.linear or w > self.limits.angular:
            self._reject("out_of_range", topic, key, f"‖v‖ = {v:.6g} m/s, ‖ω‖ = {w:.6g} rad/s; expected at "
                         f"most {self.limits.linear} m/s and {self.limits.angular} rad/s")
            return None
        self.accepted += 1
        return msg

    def joint_velocity(self, key: str, payload: bytes | bytearray | memoryview) -> JointState | None:
        """The joint-velocity command of sample (`key`, `payload`) if acceptable, else None (logged and counted)."""
        topic = "arm_joint_velocity"
        if not self._own_key(topic, key):
            return None
        try:
            msg = decode_joint_state(payload)
        except ProtocolError as exc:
            self._reject("malformed", topic, key, str(exc))
            return None
        stop = msg.velocity.size > 0 and not np.any(msg.velocity)
        if not stop and not self._fresh(topic, key, msg.header.stamp.to_ns()):
            return None
        return self._joint_command(topic, key, msg)

    def velocity_array(self, key: str, payload: bytes | bytearray | memoryview,
                       joint_names: list[str]) -> JointState | None:
        """A ros2_control-style command (`std_msgs/Float64MultiArray` on `arm_velocity_commands`, one velocity per
        joint of `joint_names`, in that order) as a `JointState` stamped now on `clock`, if acceptable. It carries
        no stamp: freshness is the receiver's (time since arrival), so only the other checks apply."""
        topic = "arm_velocity_commands"
        if not self._own_key(topic, key):
            return None
        try:
            data = decode_float64_multi_array(payload).data
        except ProtocolError as exc:
            self._reject("malformed", topic, key, str(exc))
            return None
        if data.size != len(joint_names):
            self._reject("no_velocity", topic, key, f"{data.size} velocities; expected one per joint of "
                         f"{joint_names}, in that order")
            return None
        return self._joint_command(topic, key, JointState(Header(Time.from_ns(self.clock()), ""), joint_names,
                                                          velocity=data))

    def _joint_command(self, topic: str, key: str, msg: JointState) -> JointState | None:
        if not msg.name or msg.velocity.size != len(msg.name):
            self._reject("no_velocity", topic, key, f"{msg.velocity.size} velocities for joints {msg.name}; "
                         "expected one velocity per named joint")
            return None
        if len(set(msg.name)) != len(msg.name):
            self._reject("malformed", topic, key, f"joint names {msg.name} repeat; expected each once")
            return None
        if not np.all(np.isfinite(msg.velocity)):
            self._reject("non_finite", topic, key, f"velocities {msg.velocity.tolist()}")
            return None
        for name, qd in zip(msg.name, msg.velocity.tolist(), strict=True):
            bound = self.limits.joint_bound(name)
            if bound is None:
                self._reject("unknown_joint", topic, key, f"joint {name!r}; expected one of "
                             f"{list(self.limits.joint_names)}")
                return None
            if abs(qd) > bound:
                self._reject("out_of_range", topic, key, f"joint {name!r} at {qd:.6g}; expected |q̇| ≤ {bound}")
                return None
        self.accepted += 1
        return msg

    def _own_key(self, topic: str, key: str) -> bool:
        expected = self.keys.key(topic)
        if str(key) == expected:
            return True
        self._reject("foreign_key", topic, str(key), f"expected exactly {expected}")
        return False

    def _fresh(self, topic: str, key: str, stamp_ns: int) -> bool:
        age_ns = self.clock() - stamp_ns
        if age_ns > self.deadman_ns:
            self._reject("stale", topic, key, f"command is {age_ns / 1e9:.6g} s old; deadman {self.deadman_ns / 1e9} s")
            return False
        if -age_ns > self.future_ns:
            self._reject("future", topic, key, f"stamp {-age_ns / 1e9:.6g} s ahead of the receiver's clock; "
                         f"tolerance {self.future_ns / 1e9} s")
            return False
        return True

    def _reject(self, reason: str, topic: str, key: str, detail: str) -> None:
        self.rejections[reason] += 1
        log.warning("command rejected", extra={"fields": {"reason": reason, "topic": topic, "key": key,
                                                          "detail": detail, "count": self.rejections[reason]}})
        return None
