"""Robustness matrix (issue 20): the servo under a real camera's conditions, on the free-flying camera with the
service's per-frame code in the loop (`ServoPipeline`: estimator, law and state machine, exactly what `ddvs serve`
runs on each frame), lockstep at 30 Hz.

Targets (`TARGETS`):
- "planar": the arm's poster set-up without the arm: f = 420 px, 320×240, a 1.2 m × 0.9 m textured plane 0.7 m in
  front of the reference camera, the shipped service configuration `configs/serve/ur5_poster.json` (its template
  size on the control point, 140×140, planar model). Paper start: the real-data displacement t = [0.13, −0.23, −0.08] m,
  r = [−20.3, 2.17, 14.59]° (276 mm, 25°).
- "saddle": the synthetic experiment's set-up (f = 500 px, 550×418, horse saddle 1 m ahead), the same configuration
  with the general model and the paper's 200×150 ROI. Paper start: section IV-A's t, r.
Random starts: `experiment_domain.trial_start` of the domain sweep's sizes (3, 4: 0.15 m / 45°, 0.2 m / 60°).

Frames are rendered anti-aliased (`sim.freeflyer.render_camera`, 2×2 rays per pixel and a 0.5 px optical blur),
then pass through the condition's image transforms (`sim.conditions`) and are quantised to 8 bits. A condition
may also tell the service coarse intrinsics, delay the twist by whole frames (applied `latency_frames` periods
late) or drop frames (the service never sees a dropped frame; the plant keeps the last applied twist).

Outcome of a run (first applicable): "wrong_converged" (the service reported CONVERGED but the true pose is
farther than `max_translation_m` / `max_rotation_deg`: a confident wrong answer), "success" (CONVERGED within
the bounds), "lost" (LOST at the end of the budget, or `LOST_LIMIT_FRAMES` frames in a row), "budget" (no
CONVERGED within `max_images`), "diverged" (the camera left the working volume). Integrity measures:
`ever_lost`, `lost_frames`, and `wrong_fit_frames` / `wrong_fit_saturated`: frames where the service commanded a
twist (SERVOING) from an estimate whose control error is far from the one the same law computes from the ground
truth (`‖ε − ε_true‖ > WRONG_FIT_ABS + WRONG_FIT_REL ‖ε_true‖`), and among them those whose twist is saturated.
"""

from __future__ import annotations

import argparse
import json
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from functools import cache
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.control.law import ControlConfig, ControlLaw
from ddvs_service.lie import pose, pose_inv, so3_exp, so3_log
from ddvs_service.service.config import ServiceConfig
from ddvs_service.service.pipeline import ServoPipeline, StepResult
from ddvs_service.service.state import ServoState
from orchestration.experiment_domain import DomainSettings, trial_start
from orchestration.experiment_synthetic import LAW_NAMES, PAPER_R, PAPER_ROI_SIZE, PAPER_T
from orchestration.journal import run_journalled
from orchestration.workers import SEQUENTIAL, Workers
from sim.conditions import (
    Condition,
    Dimming,
    FrameContext,
    GainGradient,
    Jpeg,
    MotionBlur,
    Noise,
    Occluder,
    Roi,
    Specular,
    apply,
)
from sim.freeflyer import FreeFlyer, render_camera
from sim.ground_truth import GroundTruth
from sim.surfaces import Plane, Surface, paper_saddle
from sim.textures import load_texture

F64 = NDArray[np.float64]

ROOT = Path(__file__).resolve().parents[1]
SHIPPED_CONFIG = ROOT / "configs" / "serve" / "ur5_poster.json"
TARGETS = ("planar", "saddle")
OUTCOMES = ("success", "wrong_converged", "lost", "budget", "diverged")
DT = 1.0 / 30.0
OVERSAMPLE = 2
TEXTURE = "graf"
ARM_T = (0.13, -0.23, -0.08)
ARM_R_DEG = (-20.3, 2.17, 14.59)
WRONG_FIT_ABS = 0.02
WRONG_FIT_REL = 0.25
WORKING_RANGE_M = (0.15, 3.0)
LOST_LIMIT_FRAMES = 60  # a run LOST this many frames in a row (2 s) ends "lost" (each LOST frame re-initialises)


@dataclass(frozen=True)
class RobustnessCondition:
    """One condition of the matrix: image transforms applied to every frame, intrinsics told to the service
    (`focal_factor` × the true focal lengths, principal point shifted by `principal_offset_px` along u and v),
    twist latency in frames and the fraction of frames dropped (seeded)."""

    images: tuple[Condition, ...] = ()
    focal_factor: float = 1.0
    principal_offset_px: float = 0.0
    latency_frames: int = 0
    drop_fraction: float = 0.0


CONDITIONS: dict[str, RobustnessCondition] = {
    "nominal": RobustnessCondition(),
    "focal_x1.3": RobustnessCondition(focal_factor=1.3),
    "focal_x0.7": RobustnessCondition(focal_factor=0.7),
    "principal_10px": RobustnessCondition(principal_offset_px=10.0 / np.sqrt(2.0)),
    "dimming_3x": RobustnessCondition(images=(Dimming(),)),
    "gradient_turning": RobustnessCondition(images=(GainGradient(),)),
    "gradient_static": RobustnessCondition(images=(GainGradient(turn_period_s=0.0),)),
    "specular": RobustnessCondition(images=(Specular(),)),
    "occluder_stays": RobustnessCondition(images=(Occluder(),)),
    "occluder_comes_goes": RobustnessCondition(images=(Occluder(start_frame=60, leave_after=45),)),
    "noise_4": RobustnessCondition(images=(Noise(),)),
    "motion_blur": RobustnessCondition(images=(MotionBlur(),)),
    "jpeg_70": RobustnessCondition(images=(Jpeg(),)),
    "latency_2": RobustnessCondition(latency_frames=2),
    "drop_10pct": RobustnessCondition(drop_fraction=0.1),
    "hard_combination": RobustnessCondition(
        images=(Dimming(), GainGradient(), Occluder(), MotionBlur(), Noise(), Jpeg()),
        focal_factor=1.3, latency_frames=2, drop_fraction=0.1),
}


@dataclass(frozen=True)
class Target:
    """A target set-up: camera, surface, template size, service model and the paper's start `T_ref_start`."""

    camera: Intrinsics
    surface: Surface
    template: tuple[int, int]
    model: str
    paper_start: F64 = field(repr=False)


def make_target(name: str) -> Target:
    if name == "planar":
        return Target(Intrinsics(420.0, 420.0, 159.5, 119.5, 320, 240), Plane(pose(np.eye(3), (0.0, 0.0, 0.7)),
                      (1.2, 0.9)), ServiceConfig.from_file(SHIPPED_CONFIG).registration.template_size, "planar",
                      pose(so3_exp(np.radians(ARM_R_DEG)), ARM_T))
    if name == "saddle":
        return Target(Intrinsics.centred(500.0, 550, 418), paper_saddle(1.0, 1.0), PAPER_ROI_SIZE, "general",
                      pose(so3_exp(PAPER_R), PAPER_T))
    raise ValueError(f"unknown target {name!r}; expected one of {TARGETS}")


@dataclass(frozen=True)
class RobustnessSettings:
    """One matrix: targets, laws, starts ("paper" or "s<size>k<trial>", e.g. "s3k0"), conditions (keys of
    `CONDITIONS`), image budget, success bounds, and service configuration changes applied on top of the shipped
    file (`overrides`, a partial configuration as `ServiceConfig.merged` takes)."""

    targets: tuple[str, ...] = ("planar",)
    laws: tuple[str, ...] = ("ddvs",)
    starts: tuple[str, ...] = ("paper",)
    conditions: tuple[str, ...] = tuple(CONDITIONS)
    max_images: int = 1500
    max_translation_m: float = 0.005
    max_rotation_deg: float = 0.5
    overrides: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name, values, known in (("target", self.targets, TARGETS), ("law", self.laws, tuple(LAW_NAMES)),
                                    ("condition", self.conditions, tuple(CONDITIONS))):
            unknown = [v for v in values if v not in known]
            if unknown or not values:
                raise ValueError(f"{name}s {list(values)} invalid; expected a non-empty subset of {list(known)}")
        for start in self.starts:
            start_pose(make_target("planar"), start)


def start_pose(target: Target, start: str) -> F64:
    """`T_ref_start` of `start`: "paper", or "s<size>k<trial>" (the domain sweep's trial `trial` of that size)."""
    if start == "paper":
        return target.paper_start
    try:
        size, trial = start[1:].split("k")
        if start[0] != "s":
            raise ValueError
        return trial_start(DomainSettings(), float(size), int(trial))[0]
    except ValueError:
        raise ValueError(f"start {start!r}: expected 'paper' or 's<size>k<trial>', e.g. 's3k0'") from None


@dataclass
class Run:
    """One closed-loop run and its verdict (module docstring); traces per processed image."""

    target: str
    law: str
    start: str
    condition: str
    outcome: str
    images: int
    translation_error_mm: float
    rotation_error_deg: float
    ever_lost: bool
    lost_frames: int
    wrong_fit_frames: int
    wrong_fit_saturated: int
    note: str
    error_norms: list[float] = field(default_factory=list, repr=False)
    states: list[str] = field(default_factory=list, repr=False)
    pose_errors_mm: list[float] = field(default_factory=list, repr=False)


@cache
def _texture() -> NDArray[np.float32]:
    return load_texture(TEXTURE)


def service_config(target: Target, told: Intrinsics, overrides: dict) -> ServiceConfig:
    """The shipped configuration for `target` with the told intrinsics and `overrides`."""
    base = ServiceConfig.from_file(SHIPPED_CONFIG)
    patch = {"intrinsics": {"fx": told.fx, "fy": told.fy, "cx": told.cx, "cy": told.cy, "width": told.width,
                            "height": told.height},
             "registration": {"model": target.model, "template_size": list(target.template)}}
    config = base.merged(patch)
    return config.merged(overrides) if overrides else config


class Plant(Protocol):
    """A plant the matrix closes the loop on (`FreeFlyerPlant` here; the SAPIEN arm's in
    `orchestration.experiment_robustness_arm`): `index` the frame index (dropped frames included), `image()` the
    frame now before the condition's transforms (float grey levels), `truth()` the ground truth of the current pose
    (`sim.ground_truth`), `T_cur_ref()` the current camera pose in the reference camera frame, `distance_m()` from
    the camera to the target centre (m), `move(twist)` one period of the body twist [v; ω] (m/s, rad/s, camera
    frame)."""

    @property
    def index(self) -> int: ...

    def image(self) -> NDArray[np.float32]: ...

    def truth(self) -> GroundTruth: ...

    def T_cur_ref(self) -> F64: ...

    def distance_m(self) -> float: ...

    def move(self, twist: F64) -> None: ...


class FreeFlyerPlant:
    """The free-flying camera of `target` from `start`, frames rendered anti-aliased (module docstring)."""

    def __init__(self, target: Target, start: str, p_star: tuple[float, float]) -> None:
        self.target = target
        self.flyer = FreeFlyer(target.surface, target.camera, np.eye(4), start_pose(target, start), DT, p_star=p_star)

    @property
    def index(self) -> int:
        return self.flyer.index

    def image(self) -> NDArray[np.float32]:
        return render_camera(self.target.surface, _texture(), self.target.camera, self.flyer.T_world_cam,
                             oversample=OVERSAMPLE)

    def truth(self) -> GroundTruth:
        return self.flyer.observe(render=False).truth

    def T_cur_ref(self) -> F64:
        return pose_inv(self.flyer.T_world_cam)

    def distance_m(self) -> float:
        return float(np.linalg.norm(self.flyer.T_world_cam[:3, 3] - self.target.surface.T_world_surface[:3, 3]))

    def move(self, twist: F64) -> None:
        self.flyer.move(twist)


def told_intrinsics(camera: Intrinsics, condition: RobustnessCondition) -> Intrinsics:
    """The intrinsics the service is told under `condition` (focal lengths scaled, principal point shifted)."""
    return Intrinsics(camera.fx * condition.focal_factor, camera.fy * condition.focal_factor,
                      camera.cx + condition.principal_offset_px, camera.cy + condition.principal_offset_px,
                      camera.width, camera.height)


def run_one(target_name: str, law: str, start: str, condition_name: str, settings: RobustnessSettings) -> Run:
    """Servo from `start` under `condition_name` until CONVERGED, the budget or the camera leaves the volume."""
    target = make_target(target_name)
    condition = CONDITIONS[condition_name]
    told = told_intrinsics(target.camera, condition)
    config = service_config(target, told, {"control": {"law": LAW_NAMES[law]}, **settings.overrides})
    pipeline = ServoPipeline(config, told, background_reacquisition=False)  # lockstep: the plant waits for it
    reference = render_camera(target.surface, _texture(), target.camera, np.eye(4), oversample=OVERSAMPLE)
    roi = pipeline.set_reference(np.clip(np.rint(reference), 0, 255).astype(np.uint8))
    plant = FreeFlyerPlant(target, start, pipeline.control_px)
    return servo(Run(target_name, law, start, condition_name, "budget", 0, np.nan, np.nan, False, 0, 0, 0, ""),
                 plant, pipeline, roi, condition, settings)


def servo(run: Run, plant: Plant, pipeline: ServoPipeline, roi: Roi, condition: RobustnessCondition,
          settings: RobustnessSettings, observe: Callable[[GroundTruth, StepResult], None] | None = None) -> Run:
    """Close the loop on `plant` through `pipeline` (its reference set, template box `roi`) under `condition`
    until CONVERGED, the budget, `LOST_LIMIT_FRAMES` LOST frames in a row or the camera leaves the volume; fills
    `run` (traces, integrity measures, verdict) and returns it. `observe(truth, step)`: called with each processed
    frame's ground truth and the pipeline's answer (dropped frames are not processed)."""
    config, told = pipeline.config, pipeline.intrinsics
    assert told is not None, "the pipeline needs the told intrinsics"
    pipeline.machine.start()
    p_star = pipeline.control_px
    truth_law = ControlLaw(ControlConfig(law=config.control.law, gains=config.control.gains, stop_threshold=0.0), told)
    rng = np.random.default_rng([7, condition.latency_frames, round(1000 * condition.drop_fraction)])
    pending: deque[F64] = deque([np.zeros(6)] * condition.latency_frames)
    applied = np.zeros(6)
    run.outcome, run.note = "budget", f"no CONVERGED in {settings.max_images} images"
    limits = np.array([config.control.max_linear, config.control.max_angular])
    previous_px: F64 | None = None
    lost_run = 0
    for _ in range(settings.max_images):
        truth = plant.truth()
        px = _project(truth.G, truth.e, truth.rho, p_star)
        motion = (0.0, 0.0) if previous_px is None else (float(px[0] - previous_px[0]), float(px[1] - previous_px[1]))
        previous_px = px
        if condition.drop_fraction > 0.0 and rng.random() < condition.drop_fraction:
            plant.move(applied)  # the service never sees this frame; the robot keeps its last command
            continue
        image = apply(condition.images, plant.image(), FrameContext(plant.index, plant.index * DT, roi, motion))
        step = pipeline.step(image.astype(np.uint8))
        if observe is not None:
            observe(truth, step)
        run.images += 1
        run.error_norms.append(step.error_norm)
        run.states.append(step.state.value)
        run.pose_errors_mm.append(1e3 * float(np.linalg.norm(plant.T_cur_ref()[:3, 3])))
        if step.state == ServoState.LOST:
            run.ever_lost, run.lost_frames, lost_run = True, run.lost_frames + 1, lost_run + 1
            if lost_run >= LOST_LIMIT_FRAMES:
                run.outcome, run.note = "lost", f"LOST {lost_run} frames in a row: {step.message[:200]}"
                break
        else:
            lost_run = 0
        if np.any(step.twist):
            true_error = truth_law.error(truth.G, truth.e, truth.rho)
            if np.linalg.norm(step.error - true_error) > WRONG_FIT_ABS + WRONG_FIT_REL * np.linalg.norm(true_error):
                run.wrong_fit_frames += 1
                norms = np.array([np.linalg.norm(step.twist[:3]), np.linalg.norm(step.twist[3:])])
                run.wrong_fit_saturated += int(np.any(norms >= limits * (1.0 - 1e-6)))
        if step.state == ServoState.CONVERGED:
            run.outcome, run.note = "converged", f"CONVERGED at error norm {step.error_norm:.2e}"
            break
        distance = plant.distance_m()
        if not WORKING_RANGE_M[0] <= distance <= WORKING_RANGE_M[1]:
            run.outcome, run.note = "diverged", f"camera {distance:.2f} m from the target centre"
            break
        pending.append(step.twist)
        applied = pending.popleft()
        plant.move(applied)
    T_cur_ref = plant.T_cur_ref()
    run.translation_error_mm = 1e3 * float(np.linalg.norm(T_cur_ref[:3, 3]))
    run.rotation_error_deg = float(np.degrees(np.linalg.norm(so3_log(T_cur_ref[:3, :3]))))
    if run.outcome == "converged":
        close = (run.translation_error_mm <= 1e3 * settings.max_translation_m
                 and run.rotation_error_deg <= settings.max_rotation_deg)
        run.outcome = "success" if close else "wrong_converged"
    elif run.outcome == "budget" and run.states and run.states[-1] == ServoState.LOST.value:
        run.outcome, run.note = "lost", f"LOST at the end of the budget ({run.lost_frames} LOST frames)"
    return run


def _project(G: F64, e: F64, rho: float, p: tuple[float, float]) -> F64:
    q = G @ np.array([p[0], p[1], 1.0]) + rho * np.asarray(e)
    return q[:2] / q[2]


def run_matrix(settings: RobustnessSettings, out_dir: Path | None = None, log: bool = False,
               one: Callable[[str, str, str, str, RobustnessSettings], Run] = run_one,
               workers: Workers = SEQUENTIAL) -> list[Run]:
    """Every run of the matrix (condition → start → target → law), each `one(target, law, start, condition,
    settings)` (default the free-flyer's `run_one`) on `workers` (`orchestration.trials`); with `out_dir`, each run
    is appended to `runs.jsonl` there (traces included) and runs already journalled are not run again."""
    journal = None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        journal = out_dir / "runs.jsonl"
    keys = [(target, law, start, condition) for condition in settings.conditions for start in settings.starts
            for target in settings.targets for law in settings.laws]
    return run_journalled(keys, lambda key: one(*key, settings), Run,
                          lambda r: (r.target, r.law, r.start, r.condition), journal, _summary if log else None,
                          workers)


def _summary(run: Run) -> dict[str, object]:
    """A run's fields without its per-frame traces (one log line)."""
    return {k: v for k, v in asdict(run).items() if not isinstance(v, list)}


def summary_rows(runs: list[Run]) -> list[dict[str, object]]:
    """Per condition (and target, law): runs, success rate, median images of the successes, median final pose
    error, runs that ever went LOST, wrong CONVERGED runs and frames servoed on a wrong fit (saturated)."""
    rows = []
    for key in sorted({(r.condition, r.target, r.law) for r in runs}, key=lambda k: (list(CONDITIONS).index(k[0]),
                                                                                   k[1], k[2])):
        group = [r for r in runs if (r.condition, r.target, r.law) == key]
        wins = [r for r in group if r.outcome == "success"]
        rows.append({
            "condition": key[0], "target": key[1], "law": key[2], "runs": len(group),
            "success": len(wins), "rate": len(wins) / len(group),
            "images": float(np.median([r.images for r in wins])) if wins else float("nan"),
            "translation_mm": float(np.median([r.translation_error_mm for r in group])),
            "rotation_deg": float(np.median([r.rotation_error_deg for r in group])),
            "ever_lost": sum(r.ever_lost for r in group),
            "wrong_converged": sum(r.outcome == "wrong_converged" for r in group),
            "wrong_fit_frames": sum(r.wrong_fit_frames for r in group),
            "wrong_fit_saturated": sum(r.wrong_fit_saturated for r in group),
            "outcomes": ",".join(r.outcome for r in group),
        })
    return rows


def markdown_table(rows: list[dict[str, object]]) -> str:
    head = ("| condition | target | law | runs | success | images (median of successes) | final error (median) "
            "| ever LOST | wrong CONVERGED | frames servoed on a wrong fit (saturated) | outcomes |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|\n")
    return head + "".join(
        f"| {r['condition']} | {r['target']} | {r['law']} | {r['runs']} | {r['success']}/{r['runs']} "
        f"| {r['images']:.0f} | {r['translation_mm']:.1f} mm / {r['rotation_deg']:.2f}° | {r['ever_lost']} "
        f"| {r['wrong_converged']} | {r['wrong_fit_frames']} ({r['wrong_fit_saturated']}) | {r['outcomes']} |\n"
        for r in rows)


def save_plots(runs: list[Run], out_dir: Path) -> list[Path]:
    """Error norm and true translation error against images, one panel per condition (every run of it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [c for c in CONDITIONS if any(r.condition == c for r in runs)]
    cols = 4
    rows = -(-len(names) // cols)
    paths = []
    for quantity, label, log_scale in (("error_norms", "error norm", True), ("pose_errors_mm", "‖t‖ (mm)", True)):
        fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 2.6 * rows), squeeze=False, sharex=True)
        for ax, name in zip(axes.ravel(), names):
            for r in (r for r in runs if r.condition == name):
                y = np.maximum(np.asarray(getattr(r, quantity), dtype=float), 1e-6)
                ax.plot(y, lw=0.8, label=f"{r.target} {r.law} {r.start}: {r.outcome}")
            ax.set_title(name, fontsize=9)
            if log_scale:
                ax.set_yscale("log")
            ax.tick_params(labelsize=7)
            ax.legend(fontsize=5)
        for ax in axes.ravel()[len(names):]:
            ax.axis("off")
        fig.supxlabel("images")
        fig.supylabel(label)
        fig.tight_layout()
        path = out_dir / f"{quantity}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)
    return paths


def write_report(runs: list[Run], settings: RobustnessSettings, out_dir: Path) -> dict[str, Path]:
    """`robustness.md` (settings, table, plots) and `robustness.json` (rows) in `out_dir`."""
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = summary_rows(runs)
    plots = save_plots(runs, out_dir)
    (out_dir / "robustness.json").write_text(json.dumps({"settings": asdict(settings), "rows": rows}, indent=2,
                                                        default=str))
    text = (f"# Robustness matrix\n\nSettings: {json.dumps(asdict(settings), default=str)}\n\n"
            f"Success: CONVERGED within {settings.max_images} images and within "
            f"{settings.max_translation_m * 1e3:g} mm / {settings.max_rotation_deg:g}° of the reference pose.\n\n"
            f"{markdown_table(rows)}\n" + "".join(f"![{p.stem}]({p.name})\n" for p in plots))
    (out_dir / "robustness.md").write_text(text)
    return {"markdown": out_dir / "robustness.md", "json": out_dir / "robustness.json",
            **{p.stem: p for p in plots}}


def run_robustness_command(args: argparse.Namespace) -> int:
    """`ddvs experiment robustness`: run or resume the matrix, one JSON line per run, then the report's paths."""
    settings = RobustnessSettings(
        targets=tuple(args.targets), laws=tuple(args.laws), starts=tuple(args.starts),
        conditions=tuple(args.conditions) if args.conditions else tuple(CONDITIONS), max_images=args.max_images,
        overrides=json.loads(args.overrides) if args.overrides else {},
    )
    runs = run_matrix(settings, args.out, log=True, workers=Workers(args.workers, args.cluster))
    for path in write_report(runs, settings, args.out).values():
        print(path)
    return 0
