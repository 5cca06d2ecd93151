"""`ddvs sim arm` and `ddvs bridge` as their own processes over real Zenoh sessions on loopback, real SAPIEN."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from conftest import free_port

from ddvs_service.lie import pose_inv, se3_exp, so3_log
from ddvs_service.protocol import (
    GroundTruth,
    Header,
    JointState,
    Keys,
    LatestSubscriber,
    SessionConfig,
    Time,
    TwistStamped,
    decode_camera_info,
    decode_image,
    decode_joint_state,
    encode_joint_state,
    encode_twist_stamped,
    open_session,
    parse_message,
)

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "configs" / "arm" / "ur5_poster.json"
KEYS = Keys("ddvs", "armtest")


@contextmanager
def _process(*args: str) -> Iterator[subprocess.Popen]:
    """A `ddvs` subcommand in its own process, stopped with SIGINT (then killed) at the end."""
    cmd = [sys.executable, "-m", "ddvs.cli", *args, "--prefix", KEYS.prefix, "--robot", KEYS.robot]
    proc = subprocess.Popen(cmd, cwd=ROOT, env={**os.environ, "PYTHONUNBUFFERED": "1"},
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        yield proc
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            out, _ = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
        proc.output = out  # type: ignore[attr-defined]
        print(out[-3000:])


def _session(*ports: int):
    return open_session(SessionConfig(connect=[f"tcp/127.0.0.1:{p}" for p in ports]))


def _recv(sub: LatestSubscriber, timeout: float, what: str):
    sample = sub.recv(timeout)
    assert sample is not None, f"no {what} within {timeout} s"
    return sample.payload.to_bytes()


def _command(names, velocity, stamp: Time) -> bytes:
    return encode_joint_state(JointState(Header(stamp, ""), list(names), velocity=np.asarray(velocity, float)))


def test_lockstep_publishes_frames_and_steps_on_command_k():
    port = free_port()
    args = ("sim", "arm", "--config", str(SCENE), "--clock", "lockstep", "--fps", "30", "--lockstep-timeout", "0.4",
            "--start", "reference", "--listen", f"tcp/127.0.0.1:{port}")
    with _process(*args), _session(port) as session:
        joints = LatestSubscriber(session, KEYS.arm_joint_states)
        image = LatestSubscriber(session, KEYS.camera_image)
        info = LatestSubscriber(session, KEYS.camera_info)
        truth = LatestSubscriber(session, KEYS.arm_ground_truth)
        commands = session.declare_publisher(KEYS.arm_joint_velocity)
        # Frames keep coming (each after the 0.4 s timeout) until we answer one.
        state0 = decode_joint_state(_recv(joints, 30.0, "joint state"))
        img = decode_image(_recv(image, 2.0, "image"))
        cam = decode_camera_info(_recv(info, 2.0, "camera info"))
        gt = parse_message(GroundTruth, _recv(truth, 2.0, "ground truth"))
        assert (img.height, img.width, img.encoding) == (240, 320, "mono8")
        np.testing.assert_allclose(cam.k, [420, 0, 159.5, 0, 420, 119.5, 0, 0, 1])
        T = np.array(gt.camera_pose).reshape(4, 4)
        assert T[2, 2] == pytest.approx(-1.0, abs=1e-5), "reference camera looks straight down at the poster"
        # Answer the newest frame: the next one shows the commanded motion over exactly one period.
        state = decode_joint_state(_recv(joints, 2.0, "joint state"))
        assert state.header.stamp.to_ns() > state0.header.stamp.to_ns()
        velocity = np.array([0.05, -0.04, 0.03, 0.02, -0.06, 0.1])
        sent = time.monotonic()
        commands.put(_command(state.name, velocity, state.header.stamp))
        after = decode_joint_state(_recv(joints, 2.0, "joint state after the command"))
        assert time.monotonic() - sent < 0.3, "lockstep must step as soon as command k arrives"
        assert after.header.stamp.to_ns() - state.header.stamp.to_ns() == pytest.approx(1e9 / 30, abs=2)
        np.testing.assert_allclose(after.position - state.position, velocity / 30, atol=1e-5)  # float32 qpos
        np.testing.assert_allclose(after.velocity, velocity, atol=1e-4)
        # A stale command (older stamp) does not release the next frame: it waits for the timeout, then holds still.
        commands.put(_command(after.name, velocity, state.header.stamp))
        sent = time.monotonic()
        held = decode_joint_state(_recv(joints, 2.0, "joint state after the timeout"))
        assert time.monotonic() - sent > 0.3
        np.testing.assert_allclose(held.position, after.position, atol=2e-6)
        for sub in (joints, image, info, truth):
            sub.close()
        commands.undeclare()


@pytest.mark.slow
def test_realtime_clock_keeps_rate_and_deadman_stops_the_arm():
    port = free_port()
    args = ("sim", "arm", "--config", str(SCENE), "--clock", "realtime", "--fps", "30", "--deadman", "0.1",
            "--start", "reference", "--listen", f"tcp/127.0.0.1:{port}")
    with _process(*args), _session(port) as session:
        received: list[JointState] = []
        sub = session.declare_subscriber(KEYS.arm_joint_states,
                                         lambda s: received.append(decode_joint_state(s.payload.to_bytes())))
        commands = session.declare_publisher(KEYS.arm_joint_velocity)
        deadline = time.monotonic() + 30.0
        while not received and time.monotonic() < deadline:
            time.sleep(0.05)
        assert received, "the sim published no joint states"
        names = received[-1].name
        velocity = np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0])
        t0 = time.monotonic()
        while time.monotonic() - t0 < 1.0:  # command at 50 Hz for 1 s, then go silent for 1 s
            commands.put(_command(names, velocity, Time.now()))
            time.sleep(0.02)
        time.sleep(1.0)
        sub.undeclare()
        commands.undeclare()
    stamps = np.array([m.header.stamp.to_ns() for m in received]) * 1e-9
    period = np.diff(stamps)
    assert np.median(period) == pytest.approx(1 / 30, abs=1e-6), "stamps advance by whole periods"
    assert len(received) / (stamps[-1] - stamps[0]) > 20.0, "frames published near 30 Hz"
    moving = [m for m in received if m.velocity[0] > 0.05]
    assert 0.8 < len(moving) / 30.0 < 1.3, "moved for about the 1 s of commands"
    last_move = max(m.header.stamp.to_ns() for m in moving) * 1e-9
    still_after = [m for m in received if m.header.stamp.to_ns() * 1e-9 > last_move]
    assert len(still_after) > 15 and all(abs(m.velocity[0]) < 1e-6 for m in still_after), "deadman stopped it"


@pytest.mark.slow
def test_sim_and_bridge_processes_reproduce_a_camera_twist():
    """Sim (lockstep) and bridge in their own processes; this test plays the servo: one twist per frame, stamped
    with the frame's stamp. After 15 frames (0.5 s) the true camera motion is exp(ξ · 0.5 s) to within 1 %."""
    sim_port, bridge_port = free_port(), free_port()
    twist = np.array([0.04, -0.03, 0.05, 0.15, -0.10, 0.20])
    sim_args = ("sim", "arm", "--config", str(SCENE), "--clock", "lockstep", "--fps", "30", "--start", "reference",
                "--lockstep-timeout", "2.0", "--listen", f"tcp/127.0.0.1:{sim_port}")
    bridge_args = ("bridge", "--config", str(ROOT / "configs" / "arm" / "ur5_bridge.json"),
                   "--listen", f"tcp/127.0.0.1:{bridge_port}", "--connect", f"tcp/127.0.0.1:{sim_port}")
    with _process(*sim_args), _process(*bridge_args), _session(sim_port, bridge_port) as session:
        truth = LatestSubscriber(session, KEYS.arm_ground_truth)
        twists = session.declare_publisher(KEYS.servo_twist)
        poses = []
        first = parse_message(GroundTruth, _recv(truth, 30.0, "ground truth"))
        time.sleep(1.0)  # let the bridge's sessions connect; the sim holds still meanwhile
        gt = parse_message(GroundTruth, _recv(truth, 5.0, "ground truth"))
        assert gt.stamp_ns >= first.stamp_ns
        for _ in range(15):
            poses.append(np.array(gt.camera_pose).reshape(4, 4))
            msg = TwistStamped(Header(Time.from_ns(gt.stamp_ns), "camera"), twist[:3], twist[3:])
            twists.put(encode_twist_stamped(msg))
            gt = parse_message(GroundTruth, _recv(truth, 5.0, "ground truth"))
            assert gt.stamp_ns - first.stamp_ns > 0
        poses.append(np.array(gt.camera_pose).reshape(4, 4))
        truth.close()
        twists.undeclare()
    moved = pose_inv(poses[0]) @ poses[-1]
    expected = se3_exp(twist * 0.5)
    t_err = np.linalg.norm(moved[:3, 3] - expected[:3, 3]) / np.linalg.norm(expected[:3, 3])
    r_err = np.linalg.norm(so3_log(expected[:3, :3].T @ moved[:3, :3])) / np.linalg.norm(twist[3:] * 0.5)
    print(f"over Zenoh at 30 Hz: translation error {100 * t_err:.3f} %, rotation error {100 * r_err:.3f} %")
    assert t_err < 0.01 and r_err < 0.01


def test_sim_refuses_foreign_and_out_of_range_commands():
    """Defence in depth: in lockstep, a command on another robot's key or beyond the URDF velocity limits does not
    move the arm (the sim holds still after its timeout) and the rejection is logged."""
    port = free_port()
    args = ("sim", "arm", "--config", str(SCENE), "--clock", "lockstep", "--fps", "30", "--lockstep-timeout", "0.4",
            "--start", "reference", "--listen", f"tcp/127.0.0.1:{port}")
    with _process(*args) as proc, _session(port) as session:
        joints = LatestSubscriber(session, KEYS.arm_joint_states)
        foreign = session.declare_publisher(Keys("ddvs", "intruder").arm_joint_velocity)
        commands = session.declare_publisher(KEYS.arm_joint_velocity)
        state = decode_joint_state(_recv(joints, 30.0, "joint state"))
        state = decode_joint_state(_recv(joints, 2.0, "joint state"))
        too_fast = np.array([0.05, -0.04, 0.03, 0.02, -0.06, 10.0])  # 10 rad/s > the UR5's 3.15 rad/s
        foreign.put(_command(state.name, np.full(6, 0.05), state.header.stamp))
        commands.put(_command(state.name, too_fast, state.header.stamp))
        held = decode_joint_state(_recv(joints, 2.0, "joint state after the timeout"))
        np.testing.assert_allclose(held.position, state.position, atol=2e-6)
        joints.close()
        foreign.undeclare()
        commands.undeclare()
    assert "command rejected" in proc.output and "out_of_range" in proc.output
