"""The paper end to end (issue 8, part 1): its two experiments, each with the DVS (reduced error (13),
`v = λ ε'`, the service's `dvs_reduced`) and the decoupled DVS ((16), `c*' = m*'`, `v = Λ ε̄`), λ = 0.4, stop at an
error norm below 1e-3, the geometry estimated from rendered images only (no ground truth in the loop):

- "synthetic_<law>": section IV-A on the free-flying camera (`orchestration.experiment_synthetic.run_synthetic`): horse
  saddle 1 m ahead, f = 500 px, 550×418, 200×150 ROI, 30 ms sampling, t = [0.17, −0.11, 0.01] m,
  r = [−0.1, −0.31, 1.04] rad. Geometry source: "estimated" (general tracker of eq. (2)) when
  `GEOMETRY_SOURCES` offers it, else "exact" (ground truth; the report's geometry column then says so).
- "arm_<law>": section IV-B on the simulated UR5 through the real service (`orchestration.arm_run.run_arm`: sim,
  service and bridge as separate processes over Zenoh, lockstep clock): planar poster 0.7 m ahead, f = 420 px,
  320×240, 70×70 template on the control point, t = [0.13, −0.23, −0.08] m, r = [−20.3, 2.17, 14.59]°.

Measures, from the ground truth (evaluation only), the same for both plants:
- images to convergence (synthetic: images up to the first below the threshold; arm: `clients.analysis`, images
  while SERVOING before the first CONVERGED status), the first image below the threshold (`first_below`), final
  translation (mm) and rotation (deg) error;
- retreat (mm): largest increase of the camera centre's distance to the target centre over its initial value;
- coupling: the share of the translational command driven by the rotational error (`orchestration.experiment_synthetic`
  defines it; for the arm it is computed from the recorded control errors `Λ ε` and ground-truth rotations),
  over the whole run and where the remaining rotation is below 5°.

Each experiment writes `<out>/<name>/summary.json` and its figures (velocities and 3-D trajectory as the paper's
Figs. 3, 4, 6, 7, error norm, pose error); an experiment whose summary exists is skipped unless `force`. The
experiments are trials of `orchestration.trials` (run at once on Ray workers unless `--workers 1`): each writes into a
temporary directory of the host that runs it and gives its files back with its row (`run_experiment`).
`write_report` gathers them into `<out>/report.md` and `<out>/paper.json`.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.control.law import ControlConfig, ControlLaw, LawName
from ddvs_service.lie import pose_inv, so3_log
from orchestration.experiment_synthetic import (
    GEOMETRY_SOURCES,
    LAW_NAMES,
    PAPER_IMAGES,
    SyntheticSetup,
    _coupling,
    run_synthetic,
    save_plots,
)
from orchestration.trials import run_trials
from orchestration.workers import SEQUENTIAL, Workers

F64 = NDArray[np.float64]

EXPERIMENTS = ("synthetic_dvs", "synthetic_ddvs", "arm_dvs", "arm_ddvs")
PAPER_ARM_IMAGES = {"dvs": 417, "ddvs": 309}
ARM_TEMPLATE = (70, 70)
NEAR_EQUILIBRIUM_DEG = 5.0
SUMMARY = "summary.json"


@dataclass(frozen=True)
class PaperSettings:
    """`out_dir` of the report, the `experiments` to run (names of `EXPERIMENTS`), image budgets per run
    (`synthetic_max_images`, `arm_max_images`), the arm run's wall-time limit (s), and `force` (re-run experiments
    whose summary exists)."""

    out_dir: Path = Path("reports/paper")
    experiments: tuple[str, ...] = EXPERIMENTS
    synthetic_max_images: int = 3000
    arm_max_images: int = 2000
    arm_time_limit_s: float = 1800.0
    force: bool = False

    def __post_init__(self) -> None:
        unknown = [name for name in self.experiments if name not in EXPERIMENTS]
        if unknown or not self.experiments:
            raise ValueError(f"experiments {list(self.experiments)} invalid; expected a non-empty subset of "
                             f"{list(EXPERIMENTS)}")


def synthetic_geometry() -> str:
    """The synthetic experiment's geometry source: "estimated" when available, else "exact"."""
    return "estimated" if "estimated" in GEOMETRY_SOURCES else "exact"


def run_synthetic_experiment(law: str, out: Path, settings: PaperSettings) -> dict[str, Any]:
    """Section IV-A with `law` ("dvs" | "ddvs"); figures into `out`; returns the summary row."""
    setup = SyntheticSetup(max_images=settings.synthetic_max_images)
    result = run_synthetic(law, setup, synthetic_geometry())
    figures = save_plots(result, out, setup)
    # The reference camera frame is the world frame of the synthetic plant: positions/rotations are T_ref_cam.
    angles = np.degrees([np.linalg.norm(so3_log(R)) for R in result.rotations])
    figures.append(save_error_plot(result.error_norms, np.linalg.norm(result.positions, axis=1), angles,
                                   setup.threshold, out / f"{law}_errors.png"))
    return {
        "experiment": f"synthetic_{law}", "plant": "free-flying camera, saddle", "law": LAW_NAMES[law],
        "geometry": result.geometry, "converged": result.converged, "images": result.images,
        "first_below_threshold": first_below(result.error_norms, setup.threshold),
        "paper_images": PAPER_IMAGES[law], "translation_error_mm": 1e3 * result.translation_error_m,
        "rotation_error_deg": result.rotation_error_deg, "retreat_mm": 1e3 * result.retreat_m,
        "coupling": result.coupling, "coupling_near_equilibrium": result.coupling_near_equilibrium,
        "stopped": result.stopped, "figures": [str(p.relative_to(out)) for p in figures],
    }


def first_below(norms: F64, threshold: float) -> int | None:
    """Images up to and including the first whose error norm is below `threshold` (None: never). The service
    declares CONVERGED only after `converge_frames` consecutive such images, so with estimation noise near the
    threshold this comes earlier than its images to convergence."""
    below = np.flatnonzero(np.asarray(norms) < threshold)
    return int(below[0]) + 1 if below.size else None


def save_error_plot(norms: F64, translation_m: F64, rotation_deg: F64, threshold: float, path: Path) -> Path:
    """Error norm (log) and true pose error (translation mm, rotation deg; log) against the image index."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_e, ax_t, ax_r) = plt.subplots(3, 1, figsize=(7, 7), sharex=True)
    index = np.arange(len(norms))
    ax_e.semilogy(index, np.maximum(norms, 1e-12))
    ax_e.axhline(threshold, color="k", ls="--", lw=0.8, label=f"stop threshold {threshold:g}")
    ax_e.set_ylabel("control error norm")
    ax_e.legend()
    ax_t.semilogy(index, np.maximum(1e3 * translation_m, 1e-6))
    ax_t.set_ylabel("translation error (mm)")
    ax_r.semilogy(index, np.maximum(rotation_deg, 1e-6))
    ax_r.set_ylabel("rotation error (deg)")
    ax_r.set_xlabel("image")
    for ax in (ax_e, ax_t, ax_r):
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def run_arm_experiment(law: str, out: Path, settings: PaperSettings) -> dict[str, Any]:
    """Section IV-B with `law` ("dvs" | "ddvs") through the real service; recording and figures into `out`."""
    from clients.analysis import status_series, summarize
    from clients.plot import plot_recording
    from clients.recording import load_recording
    from orchestration.arm_run import ArmRunSettings, run_arm
    from sim.arm_scene import load_scene_config

    shutil.rmtree(out, ignore_errors=True)  # a recording directory must start empty
    run_settings = ArmRunSettings(out_dir=out, law=LAW_NAMES[law], template=ARM_TEMPLATE, clock="lockstep",
                                  max_images=settings.arm_max_images, time_limit=settings.arm_time_limit_s,
                                  robot=f"paper_{law}")
    result = run_arm(run_settings)
    recording = load_recording(result.recording_dir)
    summary = summarize(recording)
    scene = load_scene_config(run_settings.scene)
    assert scene.start is not None  # run_arm refuses a scene without a start
    centre = scene.targets[scene.start.target].T_world_target[:3, 3]
    measures = arm_measures(recording, LAW_NAMES[law], run_settings.gain, centre)
    title = f"arm, {'decoupled DVS' if law == 'ddvs' else 'DVS'}, {ARM_TEMPLATE[0]}×{ARM_TEMPLATE[1]} template"
    figures = plot_recording(recording, out / "plots", title)
    return {
        "experiment": f"arm_{law}", "plant": "SAPIEN UR5, planar poster", "law": LAW_NAMES[law],
        "geometry": "estimated (service: planar tracker + global init)", "converged": result.converged,
        "images": summary.images_to_convergence if result.converged else result.images,
        "first_below_threshold": first_below(status_series(recording).error_norm, run_settings.stop_threshold),
        "paper_images": PAPER_ARM_IMAGES[law], "translation_error_mm": summary.final_translation_error_mm,
        "rotation_error_deg": summary.final_rotation_error_deg, **measures, "stopped": result.reason,
        "figures": [str(p.relative_to(out)) for p in figures],
    }


def arm_measures(recording: Any, law: LawName, gain: float, target_centre: F64) -> dict[str, float]:
    """Retreat (mm) and coupling measures of an arm recording (module docstring). Uses the SERVOING frames up to
    the first CONVERGED one that have a ground-truth pose with the same stamp; the commanded linear velocity is
    `λ ε_v` from the recorded error (before the service's saturation, as in the synthetic experiment)."""
    from clients.analysis import reference_pose, status_series

    info = recording["camera_info"][0]
    intr = Intrinsics.from_matrix(np.asarray(info["k"], dtype=np.float64).reshape(3, 3), info["width"],
                                  info["height"])
    control = ControlLaw(ControlConfig(law=law, gains=gain), intr)
    T_world_ref = reference_pose(recording)
    if T_world_ref is None:
        raise ValueError("the recording has no reference_pose in its meta: cannot measure retreat and coupling")
    truth = {r["msg"]["stamp_ns"]: np.asarray(r["msg"]["camera_pose"], dtype=np.float64).reshape(4, 4)
             for r in recording["ground_truth"]}
    series = status_series(recording)
    errors = [r["msg"]["error"] for r in recording["status"]][-len(series.state):] if series.state else []
    v, v_rot, angles, distances = [], [], [], []
    for stamp, state, error in zip(series.stamp_ns, series.state, errors):
        if state == "CONVERGED":
            break
        T_world_cam = truth.get(int(stamp))
        if state != "SERVOING" or T_world_cam is None:
            continue
        R_cur_ref = (pose_inv(T_world_cam) @ T_world_ref)[:3, :3]
        v.append(control.gains[:3] * np.asarray(error[:3], dtype=np.float64))
        v_rot.append(control.gains[:3] * control.error(intr.K @ R_cur_ref @ intr.K_inv, np.zeros(3), 0.0)[:3])
        angles.append(np.degrees(np.linalg.norm(so3_log(R_cur_ref))))
        distances.append(float(np.linalg.norm(T_world_cam[:3, 3] - target_centre)))
    if not v:
        raise ValueError("no SERVOING frame with a ground-truth pose in the recording")
    va, vr, near = np.array(v), np.array(v_rot), np.array(angles) < NEAR_EQUILIBRIUM_DEG
    return {
        "retreat_mm": 1e3 * max(0.0, max(distances) - distances[0]),
        "coupling": _coupling(va, vr, np.ones(len(va), dtype=bool)),
        "coupling_near_equilibrium": _coupling(va, vr, near),
    }


@dataclass(frozen=True)
class ExperimentOutput:
    """What one experiment gives back to the process that runs the paper (`run_experiment`): its summary row and
    every file it wrote (path relative to its directory → bytes: figures, the arm's recording and logs), so that it
    may have run on another host."""

    row: dict[str, Any]
    files: dict[str, bytes]


def run_experiment(name: str, settings: PaperSettings) -> ExperimentOutput:
    """Experiment `name` (of `EXPERIMENTS`) in a fresh temporary directory on the host that runs it; returns its row
    and files."""
    plant, law = name.split("_")
    with tempfile.TemporaryDirectory(prefix=f"ddvs-{name}-") as tmp:
        out = Path(tmp)
        row = (run_synthetic_experiment if plant == "synthetic" else run_arm_experiment)(law, out, settings)
        files = {str(f.relative_to(out)): f.read_bytes() for f in sorted(out.rglob("*")) if f.is_file()}
    return ExperimentOutput(row, files)


def run_paper(settings: PaperSettings, log: bool = False, workers: Workers = SEQUENTIAL) -> dict[str, dict[str, Any]]:
    """Run (or resume) the selected experiments on `workers` (`orchestration.trials`) and write the report; returns
    the summary rows by name, in the order of `settings.experiments`. Each experiment's directory `<out>/<name>` is
    replaced by the files it gave back, then its summary written, as it ends. Raises
    `orchestration.trials.TrialsFailed` (after the report of the others) when some experiments failed."""
    rows: dict[str, dict[str, Any]] = {}
    todo = []
    for name in settings.experiments:
        summary_file = settings.out_dir / name / SUMMARY
        if summary_file.exists() and not settings.force:
            rows[name] = json.loads(summary_file.read_text())
            if log:
                print(f"{name}: summary exists, skipped (use --force to re-run)", flush=True)
        else:
            todo.append(name)

    def keep(name: str, output: ExperimentOutput) -> None:
        out = settings.out_dir / name
        shutil.rmtree(out, ignore_errors=True)
        for relative, data in output.files.items():
            (out / relative).parent.mkdir(parents=True, exist_ok=True)
            (out / relative).write_bytes(data)
        (out / SUMMARY).write_text(json.dumps(output.row, indent=2))
        rows[name] = output.row
        if log:
            print(json.dumps({k: v for k, v in output.row.items() if k != "figures"}), flush=True)

    try:
        run_trials(todo, partial(run_experiment, settings=settings), workers, keep)
    finally:
        rows = {name: rows[name] for name in settings.experiments if name in rows}
        write_report(rows, settings.out_dir)
    return rows


def _fmt(value: Any, spec: str) -> str:
    return "—" if value is None or (isinstance(value, float) and not np.isfinite(value)) else format(value, spec)


def markdown_table(rows: dict[str, dict[str, Any]]) -> str:
    """The report's table: one line per experiment."""
    head = ("| experiment | law | geometry | converged | images | first < threshold | paper | final ‖t‖ (mm) "
            "| final angle (°) | retreat (mm) | coupling | coupling, rotation < 5° |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    return head + "".join(
        f"| {r['experiment']} | {r['law']} | {r['geometry']} | {'yes' if r['converged'] else 'no'} | {r['images']} "
        f"| {_fmt(r['first_below_threshold'], 'd')} | {r['paper_images']} | {_fmt(r['translation_error_mm'], '.2f')} "
        f"| {_fmt(r['rotation_error_deg'], '.3f')} "
        f"| {_fmt(r['retreat_mm'], '.1f')} | {_fmt(r['coupling'], '.3f')} "
        f"| {_fmt(r['coupling_near_equilibrium'], '.3f')} |\n"
        for r in rows.values()
    )


def write_report(rows: dict[str, dict[str, Any]], out_dir: Path) -> Path:
    """`report.md` (table, how each run ended, figures) and `paper.json` (the rows) in `out_dir`."""
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "paper.json").write_text(json.dumps(rows, indent=2))
    lines = ["# The paper's experiments, reproduced", "",
             "Produced by `ddvs experiment paper` (`orchestration/experiment_paper.py`); see "
             "docs/results/servoing.md for the discussion.",
             "", markdown_table(rows), "## How each run ended", ""]
    lines += [f"- {name}: {row['stopped']}" for name, row in rows.items()]
    lines += ["", "## Figures", ""]
    for name, row in rows.items():
        lines.append(f"### {name}")
        lines += [f"![{name} {Path(f).stem}]({name}/{f})" for f in row["figures"]]
        lines.append("")
    path = out_dir / "report.md"
    path.write_text("\n".join(lines))
    return path


def run_paper_command(args: argparse.Namespace) -> int:
    """`ddvs experiment paper`: run or resume, print one JSON line per experiment and the report's path; exit 0
    only when every selected run converged."""
    budgets = {} if args.max_images is None else {"synthetic_max_images": args.max_images,
                                                   "arm_max_images": args.max_images}
    settings = PaperSettings(out_dir=args.out, experiments=tuple(args.only or EXPERIMENTS), force=args.force,
                             **budgets)
    rows = run_paper(settings, log=True, workers=Workers(args.workers, args.cluster))
    print(settings.out_dir / "report.md")
    return 0 if all(row["converged"] for row in rows.values()) else 1
