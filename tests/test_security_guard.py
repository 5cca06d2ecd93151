"""CommandGuard: commands are acted on only when from this robot's key, fresh, finite and within limits; every
rejection is logged as a structured line and counted."""

from __future__ import annotations

import json
import logging
import math
import struct
import time

import numpy as np
import pytest
import zenoh
from conftest import free_port

from ddvs_service.logs import JsonFormatter
from ddvs_service.protocol import Header, JointState, Keys, Time, TwistStamped
from ddvs_service.protocol.guard import REASONS, CommandGuard, CommandLimits
from ddvs_service.protocol.ros import encode_joint_state, encode_twist_stamped

KEYS = Keys("ddvs", "ur5")
NOW_NS = 1_700_000_000_000_000_000
JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint"]


def make_guard(**limits: object) -> CommandGuard:
    defaults: dict[str, object] = {"linear": 0.25, "angular": 0.8, "joint_velocity": 1.0}
    return CommandGuard(KEYS, deadman_s=0.1, limits=CommandLimits(**{**defaults, **limits}),  # type: ignore[arg-type]
                        future_tolerance_s=0.02, clock=lambda: NOW_NS)


def twist(v: list[float], w: list[float], age_s: float = 0.0) -> bytes:
    header = Header(Time.from_ns(NOW_NS - int(age_s * 1e9)), "camera")
    return encode_twist_stamped(TwistStamped(header, np.array(v), np.array(w)))


def joints(qd: list[float], names: list[str] | None = None, age_s: float = 0.0) -> bytes:
    names = JOINTS[: len(qd)] if names is None else names
    header = Header(Time.from_ns(NOW_NS - int(age_s * 1e9)), "world")
    return encode_joint_state(JointState(header, names, velocity=np.array(qd)))


def test_accepts_fresh_in_range_commands_of_its_robot() -> None:
    guard = make_guard()
    msg = guard.twist(KEYS.servo_twist, twist([0.1, 0.0, 0.2], [0.0, 0.5, 0.0], age_s=0.05))
    assert msg is not None and np.allclose(msg.vector, [0.1, 0.0, 0.2, 0.0, 0.5, 0.0])
    state = guard.joint_velocity(KEYS.arm_joint_velocity, joints([0.5, -1.0, 0.0]))
    assert state is not None and state.name == JOINTS
    assert guard.accepted == 2 and sum(guard.rejections.values()) == 0


@pytest.mark.parametrize(
    ("topic", "key", "payload", "reason"),
    [
        ("twist", "ddvs/other/servo/twist", twist([0.1, 0, 0], [0, 0, 0]), "foreign_key"),
        ("twist", KEYS.arm_joint_velocity, twist([0.1, 0, 0], [0, 0, 0]), "foreign_key"),
        ("joint_velocity", "ddvs/ur5/arm/joint_velocity/extra", joints([0.1]), "foreign_key"),
        ("twist", KEYS.servo_twist, twist([0.1, 0, 0], [0, 0, 0])[:-5], "malformed"),
        ("twist", KEYS.servo_twist, twist([0.1, 0, 0], [0, 0, 0])[:-8] + struct.pack("<d", math.nan), "malformed"),
        ("twist", KEYS.servo_twist, twist([0.1, 0, 0], [0, 0, 0], age_s=0.1001), "stale"),
        ("twist", KEYS.servo_twist, twist([0.1, 0, 0], [0, 0, 0], age_s=-0.03), "future"),
        ("twist", KEYS.servo_twist, twist([0.2, 0.2, 0], [0, 0, 0]), "out_of_range"),  # ‖v‖ = 0.283 > 0.25
        ("twist", KEYS.servo_twist, twist([0, 0, 0], [0, 0, -0.81]), "out_of_range"),
        ("joint_velocity", KEYS.arm_joint_velocity, b"\x00\x01\x00\x00garbage", "malformed"),
        ("joint_velocity", KEYS.arm_joint_velocity, joints([0.1, 0.2], age_s=5.0), "stale"),
        ("joint_velocity", KEYS.arm_joint_velocity, joints([0.1, math.nan]), "non_finite"),
        ("joint_velocity", KEYS.arm_joint_velocity, joints([0.1, math.inf]), "non_finite"),
        ("joint_velocity", KEYS.arm_joint_velocity, joints([0.1, -1.01]), "out_of_range"),
        ("joint_velocity", KEYS.arm_joint_velocity, joints([0.1, 0.1], names=["a", "a"]), "malformed"),
        ("joint_velocity", KEYS.arm_joint_velocity, joints([], names=JOINTS), "no_velocity"),
        ("joint_velocity", KEYS.arm_joint_velocity, joints([], names=[]), "no_velocity"),
    ],
)
def test_rejects_and_logs_each_bad_command(topic: str, key: str, payload: bytes, reason: str,
                                          caplog: pytest.LogCaptureFixture) -> None:
    guard = make_guard()
    with caplog.at_level(logging.WARNING, logger="ddvs.guard"):
        assert getattr(guard, topic)(key, payload) is None
    assert guard.rejections == {reason: 1} and guard.accepted == 0
    [record] = caplog.records
    line = json.loads(JsonFormatter().format(record))
    assert line["msg"] == "command rejected" and line["level"] == "WARNING"
    assert line["reason"] == reason and line["key"] == key and line["count"] == 1 and line["detail"]
    assert reason in REASONS


def test_per_joint_limits_and_unknown_joints() -> None:
    guard = make_guard(joint_velocity={"shoulder_pan_joint": 2.0, "shoulder_lift_joint": 0.5})
    assert guard.joint_velocity(KEYS.arm_joint_velocity, joints([1.9, 0.5])) is not None
    assert guard.joint_velocity(KEYS.arm_joint_velocity, joints([1.9, 0.51])) is None
    assert guard.joint_velocity(KEYS.arm_joint_velocity, joints([0.0, 0.0, 0.0])) is None  # elbow has no bound
    assert guard.rejections == {"out_of_range": 1, "unknown_joint": 1} and guard.accepted == 1


def test_counts_accumulate_per_reason() -> None:
    guard = make_guard()
    for _ in range(3):
        guard.twist(KEYS.servo_twist, twist([0, 0, 0], [0, 0, 0], age_s=1.0))
    guard.twist("ddvs/x/servo/twist", twist([0, 0, 0], [0, 0, 0]))
    assert guard.rejections == {"stale": 3, "foreign_key": 1}


def test_default_clock_is_the_wall_clock() -> None:
    guard = CommandGuard(KEYS, 0.5, CommandLimits())
    header = Header(Time.now(), "camera")
    fresh = encode_twist_stamped(TwistStamped(header, np.zeros(3), np.full(3, 1e6)))  # no limits: any finite value
    assert guard.twist(KEYS.servo_twist, fresh) is not None


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"deadman_s": 0.0}, "deadman_s = 0"),
        ({"deadman_s": -1.0}, "deadman_s = -1.0"),
        ({"deadman_s": math.nan}, "deadman_s = nan"),
        ({"future_tolerance_s": math.inf}, "future_tolerance_s = inf"),
    ],
)
def test_guard_settings_are_checked(kwargs: dict[str, float], message: str) -> None:
    args: dict[str, object] = {"deadman_s": 0.1, "limits": CommandLimits(), **kwargs}
    with pytest.raises(ValueError, match=message):
        CommandGuard(KEYS, **args)  # type: ignore[arg-type]


@pytest.mark.parametrize("limits", [{"linear": 0.0}, {"angular": -1.0}, {"joint_velocity": math.nan},
                                    {"joint_velocity": {"elbow_joint": 0.0}}])
def test_limits_must_be_positive(limits: dict[str, object]) -> None:
    with pytest.raises(ValueError, match="expected a positive number"):
        CommandLimits(**limits)  # type: ignore[arg-type]


def test_guard_behind_a_wildcard_subscription_acts_only_on_its_robot() -> None:
    """Real Zenoh sessions on loopback: a node subscribed to every robot's joint velocities (a misconfiguration)
    still acts only on its own robot's commands."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"

    def config(listen: bool) -> zenoh.Config:
        c = zenoh.Config()
        c.insert_json5("mode", '"peer"')
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("listen/endpoints" if listen else "connect/endpoints", json.dumps([endpoint]))
        return c

    guard = CommandGuard(KEYS, deadman_s=1.0, limits=CommandLimits(joint_velocity=1.0))
    accepted: list[JointState] = []
    samples: list[tuple[str, bytes]] = []
    with zenoh.open(config(True)) as node, zenoh.open(config(False)) as other:
        sub = node.declare_subscriber("ddvs/*/arm/joint_velocity", lambda s: samples.append(
            (str(s.key_expr), s.payload.to_bytes())))
        time.sleep(0.3)
        stamp = Header(Time.now(), "world")
        for robot in ("ur5", "panda"):
            other.put(Keys("ddvs", robot).arm_joint_velocity,
                      encode_joint_state(JointState(stamp, JOINTS[:1], velocity=np.array([0.3]))))
        deadline = time.monotonic() + 2.0
        while len(samples) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        sub.undeclare()
    for key, payload in samples:
        msg = guard.joint_velocity(key, payload)
        if msg is not None:
            accepted.append(msg)
    assert len(samples) == 2 and len(accepted) == 1
    assert guard.rejections == {"foreign_key": 1}


def test_a_stale_stop_command_is_still_honoured() -> None:
    guard = make_guard()
    assert guard.joint_velocity(KEYS.arm_joint_velocity, joints([0.0, 0.0, 0.0], age_s=5.0)) is not None
    assert guard.joint_velocity(KEYS.arm_joint_velocity, joints([0.0, 0.1, 0.0], age_s=5.0)) is None
    assert guard.rejections["stale"] == 1
