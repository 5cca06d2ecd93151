"""`ArmSim`: a SAPIEN 3 arm (default UR5) with a camera on its flange, looking at textured targets. No I/O.

Frames (see sim/arm_scene.py): world = robot base frame (URDF root link). Camera poses use OpenCV axes
(x right, y down, z forward); `camera_pose()` is `T_world_cam`. Joint vectors follow `joint_names` (SAPIEN's active
joints, the URDF order). Velocities in rad/s (m/s for prismatic joints), times in seconds of simulated time.

Plant facts this relies on (PLATFORM-NOTES.md): gravity off on every link and force-mode velocity drives with
damping 1e4 make each joint track its velocity target to ~1e-6 rad/s; SAPIEN does not apply the URDF velocity limit,
so `step` saturates each joint at it. SAPIEN's camera has x forward, y left, z up and counts its principal point from
pixel edges: the component is mounted at `T_link_cam · R_cv_sapien` with `cx_sapien = cx + 0.5`, `cy_sapien = cy + 0.5`.
Rendering uses the `trivial` shader (unlit albedo, textures loaded linear with srgb=False), ambient light only, so
grey levels are the texture's and independent of the viewpoint; the scripted illumination change is a gain on them.
A scene with a `light` (`LightSpec`) renders with the `minimal` shader instead, lit by that directional light only
(no ambient), its intensity set at each frame from the simulated time, with a linear camera response (SAPIEN's
1/2.2 encoding undone on the float picture); `occluders` (`OccluderSpec`) are render-only plates posed at each frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import sapien
from numpy.typing import ArrayLike, NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.kinematics import ArmKinematics, resolve_urdf
from ddvs_service.lie import pose
from sim.arm_scene import ArmSceneConfig, LightSpec, TargetSpec

F64 = NDArray[np.float64]

# Rotation of the SAPIEN camera axes (x forward, y left, z up) in the OpenCV camera frame: quaternion (wxyz)
# [0.5, 0.5, −0.5, 0.5].
R_CV_SAPIEN: F64 = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
DRIVE_DAMPING = 1e4
DRIVE_FORCE_LIMIT = 1e6


@dataclass(frozen=True)
class ArmJointState:
    """Joint names, positions (rad or m) and velocities (rad/s or m/s) at simulated time `time` (s)."""

    names: tuple[str, ...]
    position: F64
    velocity: F64
    time: float


class ArmSim:
    """The arm plant: `step(qd, dt)` integrates joint velocities, `render()` takes the camera image."""

    def __init__(self, config: ArmSceneConfig) -> None:
        self.config = config
        sapien.render.set_camera_shader_dir("trivial" if config.light is None else "minimal")  # global; before cameras
        scene = sapien.Scene()
        scene.set_timestep(1.0 / config.physics_hz)
        scene.render_system.set_ambient_light([1.0, 1.0, 1.0] if config.light is None else [0.0, 0.0, 0.0])
        loader = scene.create_urdf_loader()
        loader.fix_root_link = True
        robot = loader.load(str(resolve_urdf(config.urdf)))
        if robot is None:
            raise RuntimeError(f"SAPIEN could not load the URDF {config.urdf}")
        for link in robot.links:
            link.disable_gravity = True
            if not config.show_robot:
                for body in link.entity.components:
                    if isinstance(body, sapien.render.RenderBodyComponent):
                        body.disable()
        self._joints = robot.active_joints
        for joint in self._joints:
            joint.set_drive_properties(
                stiffness=0.0, damping=DRIVE_DAMPING, force_limit=DRIVE_FORCE_LIMIT, mode="force"
            )
        self.joint_names: tuple[str, ...] = tuple(j.name for j in self._joints)
        self.kinematics = ArmKinematics(config.urdf, config.camera.link, config.camera.T_link_cam, self.joint_names)
        links = {link.name: link for link in robot.links}
        if config.camera.link not in links:
            raise ValueError(f"camera link {config.camera.link!r} not in the robot; links: {sorted(links)}")
        self._camera_link = links[config.camera.link]
        self._camera = self._mount_camera(config)
        for target in config.targets:
            scene.add_entity(self._target_entity(target))
        self._light = None if config.light is None else self._light_component(scene, config.light)
        for occluder in config.occluders:
            if not 0 <= occluder.target < len(config.targets):
                raise ValueError(f"occluder target index {occluder.target} out of range: the scene has "
                                 f"{len(config.targets)} targets")
        self._occluders = [(spec, self._target_entity(spec.plate())) for spec in config.occluders]
        for _, entity in self._occluders:
            scene.add_entity(entity)
        self.scene = scene
        self.robot = robot
        self.time = 0.0
        if len(config.home) != len(self.joint_names):
            raise ValueError(f"home has {len(config.home)} values, the robot has joints {self.joint_names}")
        self.set_joint_positions(config.home)

    @property
    def intrinsics(self) -> Intrinsics:
        return self.config.camera.intrinsics

    def _mount_camera(self, config: ArmSceneConfig) -> sapien.render.RenderCameraComponent:
        """SAPIEN camera of the sub-pixel grid: `oversample` (s) times the resolution and the focal lengths; with the
        principal point counted from pixel edges, output pixel u covers [u, u + 1] and its sub-pixels s·u … s·u + s − 1,
        so the edge-based principal point scales by s too."""
        k, spec = config.camera.intrinsics, config.camera
        s = spec.oversample
        camera = sapien.render.RenderCameraComponent(s * k.width, s * k.height)
        camera.set_perspective_parameters(spec.near, spec.far, s * k.fx, s * k.fy, s * (k.cx + 0.5), s * (k.cy + 0.5),
                                          s * k.skew)
        T = spec.T_link_cam @ pose(R_CV_SAPIEN, np.zeros(3))
        camera.set_local_pose(sapien.Pose(T.astype(np.float32)))
        self._camera_link.entity.add_component(camera)
        return camera

    @staticmethod
    def _target_entity(target: TargetSpec) -> sapien.Entity:
        grey = target.texture_image()
        rgba = np.dstack([grey, grey, grey, np.full_like(grey, 255)])
        material = sapien.render.RenderMaterial(base_color=[1.0, 1.0, 1.0, 1.0])
        material.base_color_texture = sapien.render.RenderTexture2D(rgba, "R8G8B8A8Unorm", srgb=False)
        mesh = target.mesh()
        body = sapien.render.RenderBodyComponent()
        shape = sapien.render.RenderShapeTriangleMesh(mesh.vertices, mesh.triangles, mesh.normals, mesh.uvs, material)
        body.attach(shape)
        entity = sapien.Entity()
        entity.add_component(body)
        entity.set_pose(sapien.Pose(target.T_world_target.astype(np.float32)))
        return entity

    @staticmethod
    def _light_component(scene: sapien.Scene, light: LightSpec) -> sapien.render.RenderDirectionalLightComponent:
        """A directional light entity shining along `light.direction` (SAPIEN's lights shine along their x axis)."""
        x = np.asarray(light.direction, dtype=np.float64)
        helper = np.array([0.0, 0.0, 1.0]) if abs(x[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        y = np.cross(helper, x)
        y /= np.linalg.norm(y)
        component = sapien.render.RenderDirectionalLightComponent()
        entity = sapien.Entity()
        entity.add_component(component)
        entity.set_pose(sapien.Pose(pose(np.stack([x, y, np.cross(x, y)], axis=1), np.zeros(3)).astype(np.float32)))
        scene.add_entity(entity)
        return component

    def _set_scene_time(self) -> None:
        """Light intensity and occluder poses at the current simulated time."""
        if self._light is not None and self.config.light is not None:
            self._light.set_color([math.pi * self.config.light.intensity(self.time)] * 3)
        for spec, entity in self._occluders:
            T = self.config.targets[spec.target].T_world_target @ spec.T_target_plate_at(self.time)
            entity.set_pose(sapien.Pose(T.astype(np.float32)))

    def set_joint_positions(self, q: ArrayLike) -> None:
        """Teleport the arm to `q` (joint_names order) at rest; raises outside the URDF position limits."""
        q = np.asarray(q, dtype=np.float64).reshape(-1)
        kin = self.kinematics
        if q.shape != (len(self.joint_names),):
            raise ValueError(f"expected {len(self.joint_names)} joint positions {self.joint_names}, got {q.shape[0]}")
        if np.any(q < kin.lower - 1e-9) or np.any(q > kin.upper + 1e-9):
            raise ValueError(f"joint positions {q.round(4).tolist()} outside limits [{kin.lower}, {kin.upper}]")
        self.robot.set_qpos(q.astype(np.float32))
        self.robot.set_qvel(np.zeros(len(q), np.float32))
        for joint in self._joints:
            joint.set_drive_velocity_target(0.0)

    def step(self, qd: ArrayLike, dt: float) -> None:
        """Hold joint velocities `qd` (each saturated at its URDF velocity limit) for `dt` seconds of physics,
        in ⌈dt · physics_hz⌉ equal sub-steps (an ideal velocity-controlled arm: joint velocities switch at once)."""
        cmd = np.asarray(qd, dtype=np.float64).reshape(-1)
        if cmd.shape != (len(self.joint_names),) or not np.all(np.isfinite(cmd)):
            raise ValueError(f"expected {len(self.joint_names)} finite joint velocities {self.joint_names}, got {cmd}")
        if dt <= 0:
            raise ValueError(f"dt must be > 0 seconds, got {dt}")
        vmax = self.kinematics.velocity_limit
        velocity = np.clip(cmd, -vmax, vmax)
        for joint, v in zip(self._joints, velocity):
            joint.set_drive_velocity_target(float(v))
        # Start the step at the commanded velocity: the drive alone loses ~15 % of the first sub-step after a change.
        self.robot.set_qvel(velocity.astype(np.float32))
        n = max(1, math.ceil(dt * self.config.physics_hz - 1e-9))
        self.scene.set_timestep(dt / n)
        for _ in range(n):
            self.scene.step()
        self.time += dt

    def joint_state(self) -> ArmJointState:
        return ArmJointState(
            self.joint_names, self.robot.get_qpos().astype(np.float64), self.robot.get_qvel().astype(np.float64),
            self.time,
        )

    def camera_pose(self) -> F64:
        """`T_world_cam` (OpenCV camera axes) from SAPIEN's link pose and the mount."""
        T_world_link = self._camera_link.entity_pose.to_transformation_matrix().astype(np.float64)
        return T_world_link @ self.config.camera.T_link_cam

    def illumination_gain(self) -> float:
        ramp = self.config.illumination
        return 1.0 if ramp is None else ramp.at(self.time)

    def render(self) -> NDArray[np.uint8]:
        """Grey uint8 image [row, col] (height × width of the intrinsics) seen by the camera now, gain applied.

        Image formation of `CameraSpec`: the sub-pixel render, blurred by the optical Gaussian (`psf_sigma` output
        pixels, mirrored border), averaged over each pixel's `oversample × oversample` sub-pixels (`cv2.INTER_AREA`
        at an integer factor is the block mean), then the illumination gain, rounded and saturated to 8 bits."""
        self._set_scene_time()
        self.scene.update_render()
        self._camera.take_picture()
        grey = np.ascontiguousarray(self._camera.get_picture("Color")[..., 0])
        if self._light is not None:
            grey = np.power(grey, np.float32(2.2))  # linear response: undo the minimal shader's 1/2.2 encoding
        spec = self.config.camera
        if spec.psf_sigma > 0.0:
            sigma = spec.psf_sigma * spec.oversample
            grey = cv2.GaussianBlur(grey, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        if spec.oversample > 1:
            k = spec.intrinsics
            grey = cv2.resize(grey, (k.width, k.height), interpolation=cv2.INTER_AREA)
        return np.asarray(cv2.convertScaleAbs(grey, alpha=255.0 * self.illumination_gain()), dtype=np.uint8)

    def place_camera(self, T_target_cam: ArrayLike, target: int = 0, seed: ArrayLike | None = None) -> F64:
        """Move the arm so that the camera is at `T_target_cam` in the frame of target `target` (IK seeded with
        `seed`, default `home`: the solution is the IK branch nearest the seed); returns the joint positions."""
        if not 0 <= target < len(self.config.targets):
            raise ValueError(f"target index {target} out of range: the scene has {len(self.config.targets)} targets")
        T_world_cam = self.config.targets[target].T_world_target @ np.asarray(T_target_cam, dtype=np.float64)
        q = self.kinematics.inverse_kinematics(T_world_cam, self.config.home if seed is None else seed)
        self.set_joint_positions(q)
        return q

    def place_start(self) -> F64:
        """Place the camera at the configured start pose `T_target_ref · T_ref_init` (paper convention), IK seeded
        with the reference configuration so that both poses lie on the same IK branch."""
        start = self.config.start
        if start is None:
            raise ValueError("the scene configuration has no 'start' section")
        q_ref = self.place_camera(start.T_target_ref, start.target)
        return self.place_camera(start.T_target_ref @ start.T_ref_init, start.target, seed=q_ref)
