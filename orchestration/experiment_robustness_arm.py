"""Robustness matrix on the SAPIEN arm (issue 20): what SAPIEN renders physically — a light that dims, an occluding
plate moved into view — and coarse intrinsics told to the service, on the paper's arm experiment.

Plant: `sim.arm.ArmSim` with `configs/arm/ur5_poster.json` (UR5, camera on the flange, f = 420 px, 320×240, the
poster 0.7 m in front of the reference camera, procedural texture; `--scene configs/arm/ur5_poster_graf.json`: the
same poster with the free-flyer's "graf" texture, a path relative to the working directory), driven in process,
lockstep at 30 Hz: each frame is rendered by SAPIEN, the service's per-frame code (`ServoPipeline`, the shipped
`configs/serve/ur5_poster.json`: its template size on the control point, planar model) computes the twist, the
bridge's map (`clients.bridge.TwistBridge` with `configs/arm/ur5_bridge.json`: damped least squares, joint
velocity and position limits) turns it into joint velocities and SAPIEN integrates them for one period. The loop,
its measures and verdicts, the table and plots are `orchestration.experiment_robustness`'s (`servo`,
`summary_rows`, `write_report`); the journal is `orchestration.journal`'s. Ground truth: `sim.ground_truth` of the
poster (a `Plane`) from the reference and current camera poses SAPIEN reports.

Conditions (`ARM_CONDITIONS`, the free-flyer's names): told intrinsics as in `experiment_robustness.CONDITIONS`
(focal ×1.3, ×0.7, principal point 10 px off), twist latency and dropped frames as there, and two scene conditions
given as scene configuration (`sim.arm_scene`) instead of image transforms:
- "dimming_3x": a directional light perpendicular to the poster, its intensity falling linearly from 1 to 1/3
  over the first 10 s (`DIMMING_LIGHT`; linear camera response, so the frame dims 3× as the free-flyer's);
- "occluder_stays": a 0.5 m × 0.5 m plate textured with another image ("boat"), 0.15 m in front of the poster,
  sliding in from the left between frames 100 and 115 (3.33–3.83 s) and staying; at the reference pose it covers
  the left 30 % of the template's columns (`occluder_plate`; the share varies with the camera's pose: parallax).
"""

from __future__ import annotations

import argparse
import copy
import json
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from clients.bridge import TwistBridge, load_bridge
from ddvs_service.lie import pose_inv
from ddvs_service.service.config import ServiceConfig
from ddvs_service.service.pipeline import ServoPipeline
from orchestration.arm_run import BRIDGE, SCENE
from orchestration.experiment_robustness import (
    CONDITIONS,
    DT,
    SHIPPED_CONFIG,
    RobustnessCondition,
    RobustnessSettings,
    Run,
    Target,
    run_matrix,
    service_config,
    servo,
    start_pose,
    told_intrinsics,
    write_report,
)
from orchestration.experiment_synthetic import LAW_NAMES
from orchestration.workers import Workers
from sim.arm import ArmSim
from sim.arm_scene import ArmSceneConfig, StartPose, scene_config_from_dict
from sim.ground_truth import GroundTruth, ground_truth
from sim.surfaces import Plane, Surface
from sim.textures import texture_path

F64 = NDArray[np.float64]
OCCLUDER_DEPTH_M = 0.15  # in front of the poster
OCCLUDED_SHARE = 0.3  # of the template's columns, at the reference pose
OCCLUDER_FRAMES = (100, 115)  # enters between these frames (as the free-flyer's `Occluder`)
DIMMING_LIGHT = {"direction": [0.0, 0.0, -1.0], "ramp": {"gain": 1.0 / 3.0, "t_start": 0.0, "t_end": 10.0}}


def shipped_template() -> tuple[int, int]:
    """The template size (w, h) of the shipped service configuration (`configs/serve/ur5_poster.json`)."""
    w, h = ServiceConfig.from_file(SHIPPED_CONFIG).registration.template_size
    return w, h


def occluder_plate(scene: dict, template: tuple[int, int]) -> dict:
    """The occluding plate of "occluder_stays" for `scene` (a scene mapping with a `start`) and a `template` (w, h)
    centred on the principal point: its right edge, seen from the reference camera (fronto-parallel,
    `start.reference` = [0, 0, −d]), at the column `cx − w/2 + OCCLUDED_SHARE · w` of the template box;
    `OCCLUDER_DEPTH_M` in front of the target."""
    cam, start = scene["camera"], scene["start"]
    d = -float(start["reference"]["t"][2])
    z = d - OCCLUDER_DEPTH_M  # depth of the plate from the reference camera
    edge_px = (OCCLUDED_SHARE - 0.5) * template[0]  # right edge from the principal point, pixels
    edge_m = edge_px / float(cam["fx"]) * z
    size = 0.5
    t0, t1 = (k * DT for k in OCCLUDER_FRAMES)
    return {"target": int(start.get("target", 0)), "width": size, "height": size,
            "pose": {"t": [edge_m - size / 2.0, 0.0, -OCCLUDER_DEPTH_M]}, "offset": [-0.5, 0.0, 0.0],
            "t_start": t0, "t_end": t1, "texture": str(texture_path("boat"))}


@dataclass(frozen=True)
class ArmCondition:
    """Told intrinsics, latency and drops (`told`, no image transforms) and the scene keys it sets (`scene`:
    "light", or "occluders" when `occluder` is set)."""

    told: RobustnessCondition = field(default_factory=RobustnessCondition)
    light: bool = False
    occluder: bool = False

    def scene(self, base: dict, template: tuple[int, int]) -> dict:
        """`base` (a scene mapping) with this condition's light and occluder (sized against `template`)."""
        out = copy.deepcopy(base)
        if self.light:
            out["light"] = DIMMING_LIGHT
        if self.occluder:
            out["occluders"] = [*out.get("occluders", []), occluder_plate(base, template)]
        return out


ARM_CONDITIONS: dict[str, ArmCondition] = {
    "nominal": ArmCondition(),
    "focal_x1.3": ArmCondition(CONDITIONS["focal_x1.3"]),
    "focal_x0.7": ArmCondition(CONDITIONS["focal_x0.7"]),
    "principal_10px": ArmCondition(CONDITIONS["principal_10px"]),
    "dimming_3x": ArmCondition(light=True),
    "occluder_stays": ArmCondition(occluder=True),
    "latency_2": ArmCondition(CONDITIONS["latency_2"]),
    "drop_10pct": ArmCondition(CONDITIONS["drop_10pct"]),
}
DEFAULT_CONDITIONS = ("nominal", "dimming_3x", "occluder_stays", "focal_x1.3", "focal_x0.7", "principal_10px")


class ArmPlant:
    """`ArmSim` + the bridge's twist → joint velocity map as an `experiment_robustness.Plant`; the reference
    camera pose `T_world_ref` and the poster `surface` give the ground truth at control pixel `p_star`."""

    def __init__(self, sim: ArmSim, bridge: TwistBridge, T_world_ref: F64, surface: Surface,
                 p_star: tuple[float, float]) -> None:
        self.sim, self.bridge, self.T_world_ref, self.surface, self.p_star = sim, bridge, T_world_ref, surface, p_star
        self.index = 0

    def image(self) -> NDArray[np.float32]:
        return self.sim.render().astype(np.float32)

    def truth(self) -> GroundTruth:
        return ground_truth(self.surface, self.sim.intrinsics, self.T_world_ref, self.sim.camera_pose(), self.p_star)

    def T_cur_ref(self) -> F64:
        return pose_inv(self.sim.camera_pose()) @ self.T_world_ref

    def distance_m(self) -> float:
        return float(np.linalg.norm(self.sim.camera_pose()[:3, 3] - self.surface.T_world_surface[:3, 3]))

    def move(self, twist: F64) -> None:
        qd = self.bridge.joint_velocities(twist, self.sim.joint_state().position)
        self.sim.step(qd, DT)
        self.index += 1


def arm_scene(condition: str, start: str, scene_path: Path = SCENE,
              template: tuple[int, int] | None = None) -> tuple[ArmSceneConfig, Target]:
    """The scene of `condition` from `start` ("paper": the scene file's displacement, or a domain-sweep start
    "s<size>k<trial>") and the matrix's `Target` of it (camera, poster, `template` (default the shipped one),
    planar model, start)."""
    template = template or shipped_template()
    base = json.loads(Path(scene_path).read_text(encoding="utf-8"))
    config = scene_config_from_dict(ARM_CONDITIONS[condition].scene(base, template))
    if config.start is None:
        raise ValueError(f"{scene_path} has no 'start' section: no reference pose to servo to")
    poster = config.targets[config.start.target]
    target = Target(config.camera.intrinsics, Plane(poster.T_world_target, (poster.width, poster.height)), template,
                    "planar", config.start.T_ref_init)
    displacement = start_pose(target, start)
    return replace(config, start=StartPose(config.start.target, config.start.T_target_ref, displacement)), target


def run_arm_one(target: str, law: str, start: str, condition_name: str, settings: RobustnessSettings,
                scene_path: Path = SCENE) -> Run:
    """One closed-loop run on the arm (`experiment_robustness.servo` with an `ArmPlant`); `target` "planar" (the
    poster of the scene file `scene_path`)."""
    if target != "planar" or condition_name not in ARM_CONDITIONS:
        raise ValueError(f"the arm runs the planar target under {list(ARM_CONDITIONS)}; got {target!r}, "
                         f"{condition_name!r}")
    condition = ARM_CONDITIONS[condition_name]
    shipped = ServiceConfig.from_file(SHIPPED_CONFIG)
    w, h = (shipped.merged(settings.overrides) if settings.overrides else shipped).registration.template_size
    config, arm_target = arm_scene(condition_name, start, scene_path, (w, h))
    assert config.start is not None
    told = told_intrinsics(arm_target.camera, condition.told)
    control = {**settings.overrides.get("control", {}), "law": LAW_NAMES[law]}  # overrides' other control fields kept
    service = service_config(arm_target, told, {**settings.overrides, "control": control})
    sim = ArmSim(config)
    sim.place_camera(config.start.T_target_ref, config.start.target)
    T_world_ref = sim.camera_pose()
    pipeline = ServoPipeline(service, told, background_reacquisition=False)  # lockstep: the plant waits for it
    roi = pipeline.set_reference(sim.render())  # at t = 0: full light, the occluder out of view
    sim.place_start()
    plant = ArmPlant(sim, load_bridge(BRIDGE), T_world_ref, arm_target.surface, pipeline.control_px)
    return servo(Run(target, law, start, condition_name, "budget", 0, np.nan, np.nan, False, 0, 0, 0, ""),
                 plant, pipeline, roi, condition.told, settings)


def run_arm_robustness_command(args: argparse.Namespace) -> int:
    """`ddvs experiment robustness --plant arm [--scene FILE]`: run or resume the arm's matrix, then the report's
    paths."""
    if list(args.targets) != ["planar"]:
        raise ValueError(f"the arm's matrix has the planar poster only; got --targets {args.targets}")
    settings = RobustnessSettings(
        targets=("planar",), laws=tuple(args.laws), starts=tuple(args.starts),
        conditions=tuple(args.conditions) if args.conditions else DEFAULT_CONDITIONS, max_images=args.max_images,
        overrides=json.loads(args.overrides) if args.overrides else {},
    )
    unknown = [c for c in settings.conditions if c not in ARM_CONDITIONS]
    if unknown:
        raise ValueError(f"conditions {unknown} are not rendered on the arm; expected some of {list(ARM_CONDITIONS)}")
    scene = args.scene or SCENE
    runs = run_matrix(settings, args.out, log=True, one=partial(run_arm_one, scene_path=scene),
                      workers=Workers(args.workers, args.cluster))
    for path in write_report(runs, settings, args.out).values():
        print(path)
    return 0
