"""ArmSim: real SAPIEN rendering and physics of the UR5 scene (configs/arm/ur5_poster.json)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from ddvs_service.lie import pose, pose_inv, so3_exp, so3_log
from sim.arm import ArmSim
from sim.arm_scene import IlluminationRamp, TargetSpec, load_scene_config, surface_mesh

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "arm" / "ur5_poster.json"


@pytest.fixture(scope="module")
def config():
    return load_scene_config(CONFIG)


@pytest.fixture(scope="module")
def sim(config):
    return ArmSim(config)


@pytest.fixture(scope="module")
def point_sim(config):
    """The same scene with SAPIEN's point-sampled frames (one ray per pixel centre): the projection checks compare
    them with the texture sampled at projected points, which the shipped camera's pixel-area integration smooths."""
    return ArmSim(dataclasses.replace(config, camera=dataclasses.replace(config.camera, oversample=1, psf_sigma=0.0)))


def _bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Image values at pixel-centre coordinates (u, v)."""
    return cv2.remap(image.astype(np.float32), u.astype(np.float32)[None], v.astype(np.float32)[None],
                     cv2.INTER_LINEAR)[0]


def _surface_error(sim: ArmSim, target: TargetSpec, pixel_offset: float = 0.0) -> float:
    """Mean |rendered − texture| (grey levels) at random points of the analytic target surface projected with K
    and the SAPIEN camera pose (optionally shifted by `pixel_offset` px along u, to show the check's sensitivity)."""
    rng = np.random.default_rng(3)
    s, r = rng.uniform(0.05, 0.95, (2, 20000))  # texture coordinates (u, v) in [0, 1]
    x, y = (s - 0.5) * target.width, (r - 0.5) * target.height
    z = target.curvature * (x**2 - y**2)
    T_cam_target = pose_inv(sim.camera_pose()) @ target.T_world_target
    P = T_cam_target[:3, :3] @ np.stack([x, y, z]) + T_cam_target[:3, 3:4]
    p = sim.intrinsics.K @ (P / P[2])
    k = sim.intrinsics
    inside = (p[0] > 2) & (p[0] < k.width - 3) & (p[1] > 2) & (p[1] < k.height - 3)
    assert inside.sum() > 2000, "the target should fill much of the image"
    texture = target.texture_image()
    th, tw = texture.shape
    expected = _bilinear(texture, s * tw - 0.5, r * th - 0.5)
    rendered = _bilinear(sim.render(), p[0] + pixel_offset, p[1])
    return float(np.mean(np.abs(rendered - expected)[inside]))


def test_surface_mesh_faces_the_viewer_and_covers_the_texture():
    mesh = surface_mesh(0.4, 0.3, 1.0, 4)
    a, b, c = (mesh.vertices[mesh.triangles[:, i]].astype(np.float64) for i in range(3))
    geometric = np.cross(b - a, c - a)
    assert np.all(geometric[:, 2] < 0), "every triangle must face −z (the viewer side of a target)"
    assert np.all(mesh.normals[:, 2] < 0)
    assert mesh.uvs.min() == 0.0 and mesh.uvs.max() == 1.0
    corners = mesh.vertices[[0, 4, 20, 24]]
    np.testing.assert_allclose(corners[:, 2], 0.2**2 - 0.15**2, atol=1e-7)  # z = x² − y² at (±0.2, ±0.15)
    np.testing.assert_allclose(mesh.vertices[2, 2], -0.15**2, atol=1e-7)  # top edge middle (0, −0.15)


def test_reference_pose_is_reached_and_matches_sapien_camera(sim, config):
    start = config.start
    q = sim.place_camera(start.T_target_ref, start.target)
    T_target_cam = pose_inv(config.targets[0].T_world_target) @ sim.camera_pose()
    np.testing.assert_allclose(T_target_cam, start.T_target_ref, atol=1e-5)
    np.testing.assert_allclose(sim.kinematics.camera_pose(q), sim.camera_pose(), atol=1e-5)


@pytest.mark.parametrize("where", ["reference", "start"])
def test_poster_projects_with_opencv_intrinsics(point_sim, config, where):
    """The rendered poster equals the texture mapped through K and the camera pose: axes, UV orientation and the
    half-pixel principal point are right (a 0.5 px shift at least doubles the error)."""
    start = config.start
    if where == "reference":
        point_sim.place_camera(start.T_target_ref, start.target)
    else:
        point_sim.place_start()
    error = _surface_error(point_sim, config.targets[0])
    shifted = _surface_error(point_sim, config.targets[0], pixel_offset=0.5)
    assert error < 2.5, f"rendered vs projected texture: mean abs error {error:.2f} grey levels"
    assert shifted > 2.0 * error


def test_saddle_projects_with_opencv_intrinsics(config):
    T_world_target = config.targets[0].T_world_target
    saddle = TargetSpec("saddle", 0.8, 0.6, T_world_target, curvature=1.0, seed=11, cells=48)  # a = 1 m
    sim = ArmSim(dataclasses.replace(config, targets=(saddle,), show_robot=False))
    sim.place_camera(pose(so3_exp(np.deg2rad([8.0, -6.0, 5.0])), [0.03, -0.02, -0.55]))
    error = _surface_error(sim, saddle)
    flat = dataclasses.replace(saddle, curvature=0.0, kind="poster")
    assert error < 3.0, f"saddle: mean abs error {error:.2f} grey levels"
    assert _surface_error(sim, flat) > 2.0 * error, "the check must see the saddle's depth"


def test_illumination_ramp_scales_grey_levels(config):
    ramp = IlluminationRamp(gain=0.5, t_start=0.1, t_end=0.3)
    assert ramp.at(0.0) == 1.0 and ramp.at(0.2) == pytest.approx(0.75) and ramp.at(1.0) == 0.5
    sim = ArmSim(dataclasses.replace(config, illumination=ramp, show_robot=False))
    sim.place_camera(config.start.T_target_ref)
    before = sim.render().astype(np.float64)
    sim.step(np.zeros(len(sim.joint_names)), 0.5)
    after = sim.render().astype(np.float64)
    np.testing.assert_allclose(after, before * 0.5, atol=1.0)


def test_step_tracks_and_saturates_joint_velocities(sim, config):
    sim.place_camera(config.start.T_target_ref)
    q0 = sim.joint_state().position
    qd = np.array([0.1, -0.2, 0.15, 10.0, -10.0, 0.05])  # wrist joints beyond their 3.2 rad/s URDF limit
    sim.step(qd, 0.1)
    state = sim.joint_state()
    expected = np.clip(qd, -sim.kinematics.velocity_limit, sim.kinematics.velocity_limit)
    np.testing.assert_allclose(state.velocity, expected, atol=1e-3)  # 0.03 % of the limit
    np.testing.assert_allclose(state.position - q0, expected * 0.1, rtol=1e-3, atol=5e-5)
    with pytest.raises(ValueError, match="joint velocities"):
        sim.step(np.zeros(3), 0.1)


def test_start_pose_is_the_papers_displacement(sim, config):
    sim.place_start()
    T_target_cam = pose_inv(config.targets[0].T_world_target) @ sim.camera_pose()
    T_ref_init = pose_inv(config.start.T_target_ref) @ T_target_cam
    np.testing.assert_allclose(T_ref_init[:3, 3], [0.13, -0.23, -0.08], atol=1e-5)
    np.testing.assert_allclose(np.rad2deg(so3_log(T_ref_init[:3, :3])), [-20.3, 2.17, 14.59], atol=1e-3)


def test_antialiased_frames_keep_the_geometry_of_point_sampled_ones(sim, point_sim, config):
    """The shipped camera renders 2×2 sub-pixels per pixel with a 0.5 px optical blur: its frames are the
    point-sampled ones smoothed, not shifted (the sub-pixel grid keeps SAPIEN's edge-based principal point)."""
    assert (config.camera.oversample, config.camera.psf_sigma) == (2, 0.5)
    for plant in (sim, point_sim):
        plant.place_camera(config.start.T_target_ref, config.start.target)
    smooth, raw = sim.render().astype(np.float32), point_sim.render().astype(np.float32)
    (du, dv), _ = cv2.phaseCorrelate(raw, smooth)
    assert abs(du) < 0.02 and abs(dv) < 0.02, (du, dv)
    laplacian = [float(np.abs(cv2.Laplacian(image, cv2.CV_32F)).mean()) for image in (smooth, raw)]
    assert laplacian[0] < 0.9 * laplacian[1], laplacian  # the fine detail a pixel's area and the optics integrate
    with pytest.raises(ValueError, match="oversample"):
        dataclasses.replace(config.camera, oversample=0)
