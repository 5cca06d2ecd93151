"""Convergence domain (issue 8, part 2): success rate of the DVS (reduced error (13), `v = λ ε'`) and of the
decoupled DVS ((16), `c*' = m*'`, `v = Λ ε̄`) over random initial displacements of growing size, on the free-flying
camera with estimation from rendered images only (no ground truth in the loop).

Set-up (both targets, the paper's synthetic camera): f = 500 px, 550×418, principal point at the centre; the target
centre 1 m in front of the reference camera, fronto-parallel, textured with `TEXTURE` over 1 m × 0.75 m; the scene
(`SCENES`): "finite" (default) — a poster of that size, a uniform grey (128) backdrop around it, like a real poster
and ViSP's `vpImageSimulator`; "distractors" — the same with the texture `DISTRACTOR_TEXTURE` as backdrop; "tiled" —
the texture repeated mirrored over the whole surface (a target filling any view; it has twin poses); the
paper's 200×150 ROI centred on the control point `m*' = [0, 0, 1]`; λ = 0.4 (1/s) on every axis; the service's
default twist saturation (`LawSettings`); stop when the error norm is below 1e-3.
- "planar": a plane. Geometry: the service's tracking session (`service.estimators.tracking_session`) of the planar
  model (planar tracker + direct global initialiser on the first frame and after a lost frame; `e = 0`, `ρ* = 0`).
- "saddle": the paper's horse saddle `Z = 1 + (X² − Y²)/a`, a = 1 m. Geometry: the same session of the general
  model (eq. (2): global initialisation and ρ* estimated on the first frame, then `G`, `e` tracked with ρ* fixed).

Displacement of size `s`: the initial camera pose in the reference frame has a translation of `s · UNIT_T_M`
metres along a uniformly random direction and a rotation of `s · UNIT_R_DEG` degrees about a uniformly random axis
(size 4 ≈ the paper's synthetic 0.2 m / 62°). Start rule: a draw is valid when at least `VISIBLE_FRACTION` of the
ROI patch — the part of the target the reference ROI sees, 0.4 m × 0.3 m, sampled at `PATCH_GRID` points through
the ROI pixels — projects in front of the initial camera and inside its image; other draws are rejected and
redrawn, and each trial records how many (`rejected_draws`). The rule uses the plane (the saddle's patch differs by
< 4 cm in depth), so the starts are the same for both targets. Trial `k` of size `s` uses the same start for every
law (paired comparison), drawn from `numpy.random.default_rng([seed, round(1000 · size), k])` (independent of the
other sizes swept).

Options: `illumination` varies the lighting over time (global gain 1 ± 0.25, a horizontal gain gradient ± 0.15
per unit of normalised x, bias ± 15 grey levels, periods 8 s, 5 s and 6 s); `noise` adds Gaussian sensor noise of
that standard deviation (grey levels, seeded per trial and frame); both quantise the frames to 8 bits.

Outcome of a trial, in this order:
- "lost": `LOST_AFTER` consecutive frames the estimator could not register (the camera holds still meanwhile);
- "diverged": the camera left the working volume (distance to the target centre outside [0.2, 3] m);
- "budget": no convergence within `max_images` images;
- "wrong_pose": converged, but the true final pose error exceeds `max_translation_m` or `max_rotation_deg`;
- "success": converged with a small true pose error (the ground truth is used only for this verdict).
Each trial also records, from the ground truth and only for diagnosis, the frames registered and the smallest
fraction of the ROI patch in view over the run (`min_in_view`): a "lost" trial with no frame registered failed at
the global initialiser, one whose patch left the view lost the target, the others lost the tracker.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass
from functools import cache
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.control.law import ControlConfig, ControlLaw
from ddvs_service.lie import pose, pose_inv, so3_exp, so3_log
from ddvs_service.service.config import RegistrationSettings
from ddvs_service.service.estimators import tracking_session
from orchestration.experiment_synthetic import LAW_NAMES, PAPER_ROI_SIZE, TEXTURE
from orchestration.journal import run_journalled
from orchestration.workers import SEQUENTIAL, Workers
from sim.freeflyer import Appearance, FreeFlyer, render_view
from sim.surfaces import Plane, Surface, paper_saddle
from sim.textures import load_texture

F64 = NDArray[np.float64]

TARGETS = ("planar", "saddle")
SCENES = ("finite", "distractors", "tiled")
DISTRACTOR_TEXTURE = "wall"
OUTCOMES = ("success", "lost", "diverged", "budget", "wrong_pose")
UNIT_T_M = 0.05
UNIT_R_DEG = 15.0
VISIBLE_FRACTION = 0.75
PATCH_GRID = (21, 16)
MAX_DRAWS = 100_000
LOST_AFTER = 5
TARGET_DEPTH_M = 1.0
TARGET_EXTENT_M = (1.0, 0.75)
WORKING_RANGE_M = (0.2, 3.0)
CAMERA = Intrinsics.centred(500.0, 550, 418)
ROI = (round(CAMERA.cx - 0.5 * (PAPER_ROI_SIZE[0] - 1)), round(CAMERA.cy - 0.5 * (PAPER_ROI_SIZE[1] - 1)),
       *PAPER_ROI_SIZE)


@dataclass(frozen=True)
class DomainSettings:
    """One sweep: targets and laws (keys of `TARGETS`, `LAW_NAMES`), `scene` (`SCENES`), displacement `sizes`
    (units of `UNIT_T_M` and `UNIT_R_DEG`), `trials` per size, `illumination`, sensor `noise` (grey levels), `seed`,
    sampling period `dt` (s), gain λ (1/s), stop `threshold` on the error norm, image budget `max_images` per trial,
    and the success bounds on the true final pose error (`max_translation_m`, `max_rotation_deg`)."""

    targets: tuple[str, ...] = TARGETS
    laws: tuple[str, ...] = ("dvs", "ddvs")
    scene: str = "finite"
    sizes: tuple[float, ...] = (1.0, 2.0, 3.0, 4.0, 5.0)
    trials: int = 10
    illumination: bool = False
    noise: float = 0.0
    seed: int = 0
    dt: float = 0.1
    gain: float = 0.4
    threshold: float = 1e-3
    max_images: int = 400
    max_translation_m: float = 0.01
    max_rotation_deg: float = 1.0

    def __post_init__(self) -> None:
        for name, values, known in (("target", self.targets, TARGETS), ("law", self.laws, tuple(LAW_NAMES))):
            unknown = [v for v in values if v not in known]
            if unknown or not values:
                raise ValueError(f"{name}s {list(values)} invalid; expected a non-empty subset of {list(known)}")
        if self.scene not in SCENES:
            raise ValueError(f"scene {self.scene!r} invalid; expected one of {list(SCENES)}")
        if not self.sizes or min(self.sizes) <= 0.0:
            raise ValueError(f"sizes must be positive displacement sizes, got {self.sizes}")
        if self.trials < 1 or self.max_images < 1:
            raise ValueError(f"trials ({self.trials}) and max_images ({self.max_images}) must be at least 1")
        if not (self.noise >= 0.0 and self.dt > 0.0):
            raise ValueError(f"noise must be >= 0 grey levels and dt > 0 s, got {self.noise}, {self.dt}")


@dataclass
class Trial:
    """One servo run: which target, law, size index and trial, the initial displacement (m, deg), the outcome
    (`OUTCOMES`), images processed, last error norm, true final pose error (m, deg), a note on why it ended, the
    draws the start rule rejected before this start, the frames registered and the smallest fraction of the ROI
    patch in view over the run (module docstring)."""

    target: str
    law: str
    size: float
    trial: int
    initial_translation_m: float
    initial_rotation_deg: float
    outcome: str
    images: int
    final_error_norm: float
    translation_error_m: float
    rotation_error_deg: float
    note: str
    rejected_draws: int
    registered: int
    min_in_view: float


def make_surface(target: str, scene: str = "finite") -> Surface:
    """The target surface in the reference camera frame (= world): centre `TARGET_DEPTH_M` ahead, fronto-parallel,
    finite unless `scene` is "tiled"."""
    tiled = scene == "tiled"
    if target == "saddle":
        return paper_saddle(TARGET_DEPTH_M, 1.0, TARGET_EXTENT_M, tiled=tiled)
    if target == "planar":
        return Plane(pose(np.eye(3), (0.0, 0.0, TARGET_DEPTH_M)), TARGET_EXTENT_M, tiled=tiled)
    raise ValueError(f"unknown target {target!r}; expected one of {TARGETS}")


def roi_patch(surface: Surface) -> F64:
    """World points (N×3, m) of the ROI patch: the surface seen through a `PATCH_GRID` of the reference ROI's pixels
    (corners included) from the reference pose (world = reference camera frame)."""
    x, y, w, h = ROI
    u, v = np.meshgrid(np.linspace(x, x + w - 1, PATCH_GRID[0]), np.linspace(y, y + h - 1, PATCH_GRID[1]))
    m = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1) @ CAMERA.K_inv.T
    return m * surface.intersect(np.eye(4), m)[:, None]


def in_view(points: F64, T_world_cam: F64) -> float:
    """Fraction of the world `points` (N×3) in front of the camera at `T_world_cam` and inside its image."""
    X = points @ T_world_cam[:3, :3] - T_world_cam[:3, :3].T @ T_world_cam[:3, 3]
    front = X[:, 2] > 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        p = X[:, :2] / X[:, 2:3] @ CAMERA.K[:2, :2].T + CAMERA.K[:2, 2]
    inside = front & (p[:, 0] >= -0.5) & (p[:, 0] <= CAMERA.width - 0.5) & (p[:, 1] >= -0.5) & (
        p[:, 1] <= CAMERA.height - 0.5)
    return float(np.mean(inside))


def initial_pose(size: float, rng: np.random.Generator) -> tuple[F64, int]:
    """`(T_ref_start, rejected)`: a displacement of `size` in random directions that passes the start rule, and the
    number of draws the rule rejected before it (module docstring)."""
    patch = roi_patch(make_surface("planar"))
    for rejected in range(MAX_DRAWS):
        t, axis = rng.normal(size=3), rng.normal(size=3)
        t *= size * UNIT_T_M / np.linalg.norm(t)
        axis *= np.radians(size * UNIT_R_DEG) / np.linalg.norm(axis)
        T = pose(so3_exp(axis), t)
        if in_view(patch, T) >= VISIBLE_FRACTION:
            return T, rejected
    raise RuntimeError(f"no start of size {size} sees {VISIBLE_FRACTION:.0%} of the ROI patch in {MAX_DRAWS} draws; "
                       "use smaller sizes")


def appearance(t: float, settings: DomainSettings, seed: int) -> Appearance:
    """The photometry at time `t` (s): the illumination variation and the sensor noise of the module docstring."""
    if not settings.illumination:
        return Appearance(noise=settings.noise, seed=seed, quantize=settings.noise > 0.0)
    gain = 1.0 + 0.25 * np.sin(2 * np.pi * t / 8.0)
    gradient = 0.15 * np.sin(2 * np.pi * t / 5.0)
    bias = 15.0 * np.sin(2 * np.pi * t / 6.0)
    return Appearance(gain=(gain, gradient, 0.0, 0.0, 0.0, 0.0), bias=bias, noise=settings.noise, seed=seed,
                      quantize=True)


@cache
def _texture(name: str) -> NDArray[np.float32]:
    return load_texture(name)


def trial_start(settings: DomainSettings, size: float, trial: int) -> tuple[F64, int, int]:
    """`(T_ref_start, rejected draws, noise seed)` of trial number `trial` of displacement `size`: the same for every
    target, law and scene."""
    T, rejected = initial_pose(size, np.random.default_rng([settings.seed, round(1000 * size), trial]))
    return T, rejected, settings.seed * 100_003 + round(1000 * size) * 1009 + trial


def run_trial(target: str, law: str, size: float, trial: int, settings: DomainSettings,
              start: F64 | None = None) -> Trial:
    """Servo with `law` on `target` from the start of trial number `trial` of displacement `size` to the reference
    pose (module docstring); `start` (4×4 `T_ref_start`) replaces the drawn start, keeping the trial's noise seed."""
    T_ref_start, rejected, seed = trial_start(settings, size, trial)
    if start is not None:
        T_ref_start, rejected = np.asarray(start, dtype=np.float64), 0
    surface = make_surface(target, settings.scene)
    patch = roi_patch(surface)
    control_px = (CAMERA.cx, CAMERA.cy)
    texture = _texture(TEXTURE)
    backdrop = _texture(DISTRACTOR_TEXTURE) if settings.scene == "distractors" else None
    reference = render_view(surface, texture, CAMERA, np.eye(4), appearance(0.0, settings, seed + 1),
                            backdrop=backdrop)[0]
    # the pyramid of the measured sweeps (the default is the engine's 8)
    registration = RegistrationSettings(levels=3, model="general" if target == "saddle" else "planar")
    estimator = tracking_session(reference, ROI, registration)
    control = ControlLaw(ControlConfig(law=LAW_NAMES[law], gains=settings.gain, stop_threshold=settings.threshold),
                         CAMERA)
    plant = FreeFlyer(surface, CAMERA, np.eye(4), T_ref_start, settings.dt, texture=texture, backdrop=backdrop)
    outcome, note, norm, untracked, images = "budget", f"not converged in {settings.max_images} images", np.nan, 0, 0
    registered, min_in_view = 0, 1.0
    for _ in range(settings.max_images):
        images += 1
        plant.appearance = appearance(plant.index * settings.dt, settings, seed)
        frame = plant.observe()
        assert frame.image is not None
        min_in_view = min(min_in_view, in_view(patch, frame.T_world_cam))
        est = estimator.estimate(frame.image, control_px)
        if not est.tracked:
            untracked += 1
            if untracked >= LOST_AFTER:
                outcome, note = "lost", f"{untracked} frames not registered up to image {images}: {est.message}"
                break
            plant.move(np.zeros(6))
            continue
        untracked = 0
        registered += 1
        out = control.compute(est.G, est.e, est.rho)
        norm = out.error_norm
        if out.converged:
            outcome, note = "converged", f"error norm {norm:.2e} below {settings.threshold:g}"
            break
        distance = float(np.linalg.norm(frame.T_world_cam[:3, 3] - surface.T_world_surface[:3, 3]))
        if not (WORKING_RANGE_M[0] <= distance <= WORKING_RANGE_M[1]):
            outcome, note = "diverged", f"camera {distance:.2f} m from the target centre"
            break
        plant.move(out.twist)
    T_cur_ref = pose_inv(plant.T_world_cam)
    t_err = float(np.linalg.norm(T_cur_ref[:3, 3]))
    r_err = float(np.degrees(np.linalg.norm(so3_log(T_cur_ref[:3, :3]))))
    if outcome == "converged":
        small = t_err <= settings.max_translation_m and r_err <= settings.max_rotation_deg
        outcome = "success" if small else "wrong_pose"
    return Trial(target, law, float(size), trial, float(np.linalg.norm(T_ref_start[:3, 3])),
                 float(np.degrees(np.linalg.norm(so3_log(T_ref_start[:3, :3])))), outcome, images, float(norm),
                 t_err, r_err, note, rejected, registered, min_in_view)


def run_domain(settings: DomainSettings, out_dir: Path | None = None, log: bool = False,
               workers: Workers = SEQUENTIAL) -> list[Trial]:
    """Every trial of the sweep, in the order trial → size → target → law (an interrupted sweep has covered every
    size about equally), run on `workers` (`orchestration.trials`). With `out_dir`, each trial is appended to
    `trials.jsonl` there as it ends, and trials already in that file are not run again (resume; the sizes, trials,
    targets and laws may change, every other setting must be the same); the journal ends in the sweep's order
    (`orchestration.journal`)."""
    journal = None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        journal = out_dir / "trials.jsonl"
        _check_resumable(settings, out_dir / "settings.json")
        (out_dir / "settings.json").write_text(json.dumps(asdict(settings), indent=2))
    keys = [(target, law, float(size), k) for k in range(settings.trials) for size in settings.sizes
            for target in settings.targets for law in settings.laws]
    return run_journalled(keys, lambda key: run_trial(*key, settings), Trial,
                          lambda t: (t.target, t.law, t.size, t.trial), journal, asdict if log else None, workers)


def _check_resumable(settings: DomainSettings, path: Path) -> None:
    """Raise `ValueError` when the sweep journalled beside `path` ran with other physics or success bounds."""
    if not path.exists():
        return
    free = ("sizes", "trials", "targets", "laws")
    old = {k: v for k, v in json.loads(path.read_text()).items() if k not in free}
    new = {k: v for k, v in json.loads(json.dumps(asdict(settings))).items() if k not in free}
    if old != new:
        changed = sorted(k for k in new if old.get(k) != new[k])
        raise ValueError(f"{path.parent} holds trials run with other settings ({', '.join(changed)}): choose another "
                         "--out directory or delete it")


def success_table(trials: list[Trial]) -> list[dict[str, float | int | str]]:
    """Per (target, law, size): trials, successes, rate and the count of each failure cause; mean images of the
    successes; draws the start rule rejected (over these trials' starts)."""
    rows: list[dict[str, float | int | str]] = []
    keys = sorted({(t.target, t.law, t.size) for t in trials})
    for target, law, size in keys:
        group = [t for t in trials if (t.target, t.law, t.size) == (target, law, size)]
        counts = {o: sum(t.outcome == o for t in group) for o in OUTCOMES}
        wins = [t.images for t in group if t.outcome == "success"]
        rows.append({"target": target, "law": law, "size": size, "translation_m": size * UNIT_T_M,
                     "rotation_deg": size * UNIT_R_DEG, "trials": len(group), **counts,
                     "rate": counts["success"] / len(group),
                     "mean_images": float(np.mean(wins)) if wins else float("nan"),
                     "rejected_draws": sum(t.rejected_draws for t in group)})
    return rows


def markdown_table(rows: list[dict[str, float | int | str]]) -> str:
    """The success table as markdown."""
    head = ("| target | law | size | ‖t‖ (m) | angle (°) | trials | success | rate | lost | diverged | budget "
            "| wrong pose | mean images (successes) | rejected draws |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    body = "".join(
        f"| {r['target']} | {r['law']} | {r['size']:g} | {r['translation_m']:.3f} | {r['rotation_deg']:.0f} "
        f"| {r['trials']} | {r['success']} | {r['rate']:.0%} | {r['lost']} | {r['diverged']} | {r['budget']} "
        f"| {r['wrong_pose']} | {r['mean_images']:.0f} | {r['rejected_draws']} |\n"
        for r in rows
    )
    return head + body


def save_plot(rows: list[dict[str, float | int | str]], path: Path) -> Path:
    """Success rate against displacement size, one line per (target, law)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for target, law in sorted({(r["target"], r["law"]) for r in rows}):
        mine = [r for r in rows if (r["target"], r["law"]) == (target, law)]
        ax.plot([r["size"] for r in mine], [100.0 * float(r["rate"]) for r in mine], marker="o",
                ls="-" if law == "ddvs" else "--", label=f"{target}, {'decoupled DVS' if law == 'ddvs' else 'DVS'}")
    ax.set_xlabel(f"displacement size (× {UNIT_T_M} m and × {UNIT_R_DEG:g}°)")
    ax.set_ylabel("success rate (%)")
    ax.set_ylim(-5, 105)
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_report(trials: list[Trial], settings: DomainSettings, out_dir: Path) -> dict[str, Path]:
    """`domain.md` (settings and table), `domain.json` (the table rows) and `domain.png` (the plot) in `out_dir`."""
    rows = success_table(trials)
    out_dir.mkdir(parents=True, exist_ok=True)
    plot = save_plot(rows, out_dir / "domain.png")
    (out_dir / "domain.json").write_text(json.dumps({"settings": asdict(settings), "rows": rows}, indent=2))
    text = (f"# Convergence domain\n\nSettings: {json.dumps(asdict(settings))}\n\n"
            f"Size s: ‖t‖ = s × {UNIT_T_M} m, rotation = s × {UNIT_R_DEG:g}° (random directions; start valid when ≥ "
            f"{VISIBLE_FRACTION:.0%} of the ROI patch is in view, rejected draws counted). Success: error norm < "
            f"{settings.threshold:g} within {settings.max_images} images and true final "
            f"error ≤ {settings.max_translation_m * 1e3:g} mm, ≤ {settings.max_rotation_deg:g}°.\n\n"
            f"{markdown_table(rows)}\n![success rate]({plot.name})\n")
    (out_dir / "domain.md").write_text(text)
    return {"markdown": out_dir / "domain.md", "json": out_dir / "domain.json", "plot": plot}


def run_domain_command(args: argparse.Namespace) -> int:
    """`ddvs experiment domain`: run or resume the sweep, one JSON line per trial, then the report's paths."""
    settings = DomainSettings(
        targets=(args.target,) if args.target else TARGETS,
        laws=(args.law,) if args.law else ("dvs", "ddvs"), scene=args.scene,
        sizes=tuple(args.sizes), trials=args.trials, illumination=args.illumination, noise=args.noise,
        seed=args.seed, dt=args.dt, max_images=args.max_images,
    )
    trials = run_domain(settings, args.out, log=True, workers=Workers(args.workers, args.cluster))
    for path in write_report(trials, settings, args.out).values():
        print(path)
    return 0
