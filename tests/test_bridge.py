"""TwistBridge: Pinocchio camera Jacobian, damped least squares, limits and deadman; twist reproduction in SAPIEN."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from clients.bridge import BridgeLimits, TwistBridge, bridge_from_config, load_bridge
from ddvs_service.kinematics import ArmKinematics
from ddvs_service.lie import pose_inv, se3_exp, so3_log
from sim.arm import ArmSim
from sim.arm_scene import load_scene_config

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "arm"
UR5_URDF = "package://example-robot-data/robots/ur_description/urdf/ur5_robot.urdf"
UR5_READY = np.array([0.0, -1.2, 1.5, -1.9, -1.5708, 0.3])
TWIST = np.array([0.04, -0.03, 0.05, 0.15, -0.10, 0.20])  # m/s, rad/s in the camera frame


@pytest.fixture(scope="module")
def ur5() -> TwistBridge:
    return load_bridge(CONFIGS / "ur5_bridge.json")


def _body_increment(T0: np.ndarray, T1: np.ndarray) -> np.ndarray:
    D = pose_inv(T0) @ T1
    return np.r_[D[:3, 3], so3_log(D[:3, :3])]


def test_jacobian_matches_finite_differences_of_the_camera_pose(ur5):
    kin = ur5.kinematics
    J = kin.jacobian(UR5_READY)
    eps = 1e-6
    for i in range(kin.dof):
        dq = np.zeros(kin.dof)
        dq[i] = eps
        numeric = _body_increment(kin.camera_pose(UR5_READY), kin.camera_pose(UR5_READY + dq)) / eps
        np.testing.assert_allclose(J[:, i], numeric, atol=1e-5)


def test_regular_configuration_inverts_the_twist_exactly(ur5):
    qd = ur5.joint_velocities(TWIST, UR5_READY)
    np.testing.assert_allclose(ur5.kinematics.jacobian(UR5_READY) @ qd, TWIST, atol=1e-12)


def test_damped_least_squares_bounds_velocities_at_a_wrist_singularity():
    bridge = TwistBridge(ArmKinematics(UR5_URDF, "tool0", np.eye(4)), BridgeLimits(velocity_scale=1.0))
    q = UR5_READY.copy()
    q[4] = 1e-5  # wrist_2 ≈ 0: wrist_1, wrist_3 axes aligned
    J = bridge.kinematics.jacobian(q)
    plain = np.linalg.pinv(J) @ TWIST
    damped = bridge.damped_inverse(J) @ TWIST
    assert np.abs(plain).max() > 1e3, "the plain pseudo-inverse explodes here"
    assert np.abs(damped).max() < 50.0
    # Away from the singular direction the damped solution still does what was asked.
    U = np.linalg.svd(J)[0]
    regular = U[:, :5] @ U[:, :5].T
    np.testing.assert_allclose(regular @ (J @ damped), regular @ TWIST, atol=1e-3)


def test_velocity_limit_scales_the_whole_vector(ur5):
    big = 50.0 * TWIST
    raw = ur5.damped_inverse(ur5.kinematics.jacobian(UR5_READY)) @ big
    qd = ur5.joint_velocities(big, UR5_READY)
    assert np.max(np.abs(qd) / ur5.max_velocity) == pytest.approx(1.0)
    np.testing.assert_allclose(qd / np.linalg.norm(qd), raw / np.linalg.norm(raw), atol=1e-12)


def test_position_limits_are_never_crossed():
    """Panda joint 4 has its upper limit at −0.0698 rad: push towards it and integrate."""
    bridge = load_bridge(CONFIGS / "panda_bridge.json")
    kin = bridge.kinematics
    q = np.array([0.0, -0.3, 0.0, -0.3, 0.0, 1.2, 0.785])
    J = kin.jacobian(q)
    twist = J @ np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])  # the camera motion of opening joint 4
    limit = kin.upper[3] - bridge.limits.position_margin
    for _ in range(300):
        q = q + bridge.joint_velocities(twist, q) * 0.01
        assert np.all(q <= kin.upper - bridge.limits.position_margin + 1e-9)
        assert np.all(q >= kin.lower + bridge.limits.position_margin - 1e-9)
    assert q[3] == pytest.approx(limit, abs=2e-3), "it should approach the margin, not stop far from it"


def test_deadman_zeroes_stale_twists(ur5):
    ur5.set_twist(TWIST, t=10.0)
    assert np.any(ur5.command(UR5_READY, t=10.05) != 0.0)
    np.testing.assert_array_equal(ur5.command(UR5_READY, t=10.0 + ur5.limits.deadman + 1e-3), 0.0)


def test_configuration_errors_say_what_is_wrong():
    with pytest.raises(ValueError, match="not in"):
        ArmKinematics(UR5_URDF, "tool0", np.eye(4), ["elbow_joint", "no_such_joint"])
    with pytest.raises(ValueError, match="camera link"):
        ArmKinematics(UR5_URDF, "no_link", np.eye(4))
    with pytest.raises(FileNotFoundError, match="ur9"):
        ArmKinematics("package://example-robot-data/robots/ur_description/urdf/ur9.urdf", "tool0", np.eye(4))
    with pytest.raises(ValueError, match="understood"):
        bridge_from_config({"urdf": UR5_URDF, "camera_link": "tool0", "gain": 3})
    with pytest.raises(ValueError, match="velocity_scale"):
        BridgeLimits(velocity_scale=2.0)


def test_inverse_kinematics_reaches_a_pose_and_reports_unreachable_ones(ur5):
    kin = ur5.kinematics
    target = kin.camera_pose(UR5_READY + np.array([0.2, -0.1, 0.15, 0.1, 0.2, -0.3]))
    q = kin.inverse_kinematics(target, UR5_READY)
    np.testing.assert_allclose(kin.camera_pose(q), target, atol=1e-8)
    far = target.copy()
    far[:3, 3] += [3.0, 0.0, 0.0]
    with pytest.raises(RuntimeError, match="out of reach"):
        kin.inverse_kinematics(far, UR5_READY)


def _reproduce(scene: str, bridge_file: str, rate: float, duration: float = 0.5) -> tuple[float, float]:
    """Relative translation and rotation errors of the SAPIEN camera motion under a constant commanded twist."""
    config = load_scene_config(CONFIGS / scene)
    sim = ArmSim(config)
    bridge = load_bridge(CONFIGS / bridge_file)
    sim.place_camera(config.start.T_target_ref)
    columns = [sim.joint_names.index(n) for n in bridge.joint_names]
    np.testing.assert_allclose(bridge.kinematics.camera_pose(sim.joint_state().position[columns]), sim.camera_pose(),
                               atol=1e-5, err_msg="bridge and sim configurations must describe the same camera")
    T0 = sim.camera_pose()
    for _ in range(round(duration * rate)):
        qd = np.zeros(len(sim.joint_names))
        qd[columns] = bridge.joint_velocities(TWIST, sim.joint_state().position[columns])
        sim.step(qd, 1.0 / rate)
    expected = se3_exp(TWIST * duration)
    actual = pose_inv(T0) @ sim.camera_pose()
    t_err = np.linalg.norm(actual[:3, 3] - expected[:3, 3]) / np.linalg.norm(expected[:3, 3])
    r_err = np.linalg.norm(so3_log(expected[:3, :3].T @ actual[:3, :3])) / np.linalg.norm(TWIST[3:] * duration)
    return float(t_err), float(r_err)


@pytest.mark.slow
@pytest.mark.parametrize("scene, bridge_file", [("ur5_poster.json", "ur5_bridge.json"),
                                                ("panda_poster.json", "panda_bridge.json")])
@pytest.mark.parametrize("rate", [30.0, 240.0])
def test_commanded_twist_is_reproduced_by_the_simulated_camera(scene, bridge_file, rate):
    t_err, r_err = _reproduce(scene, bridge_file, rate)
    print(f"{scene} at {rate:.0f} Hz: translation error {100 * t_err:.3f} %, rotation error {100 * r_err:.3f} %")
    assert t_err < 0.01 and r_err < 0.01


@pytest.mark.parametrize("scene, bridge_file", [("ur5_poster.json", "ur5_bridge.json"),
                                                ("ur5_saddle.json", "ur5_bridge.json"),
                                                ("panda_poster.json", "panda_bridge.json")])
def test_shipped_configurations_load_and_describe_the_same_camera(scene, bridge_file):
    config = load_scene_config(CONFIGS / scene)
    bridge = load_bridge(CONFIGS / bridge_file)
    plant = ArmKinematics(config.urdf, config.camera.link, config.camera.T_link_cam)
    q = np.array(config.home)[: plant.dof]
    columns = [plant.joint_names.index(n) for n in bridge.joint_names]
    np.testing.assert_allclose(bridge.kinematics.camera_pose(q[columns]), plant.camera_pose(q), atol=1e-12)
