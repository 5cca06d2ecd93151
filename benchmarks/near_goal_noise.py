"""How noisy the saddle's estimated control error is near the goal under a robustness condition, and why: the
free-flying camera servoes (decoupled law, the robustness matrix's saddle set-up, `orchestration.experiment_robustness`)
from a start a few millimetres from the goal, or from one of the matrix's starts, with the stop disabled so that the
camera keeps servoing, and the estimated error ε̄ is compared with the one the same law computes from the ground
truth. Printed over the servoed images after the first `--skip` (the dimming and the occluder have set in by then):
the standard deviation of that gap per component (units of ε̄), the integrated autocorrelation time τ of
components 0 and 4 (the tilt that keeps the control point still: the direction the stop rule's scatter is made of),
the estimate's scatter s as the stop rule computes it, s/√N (the long window's standard error, N =
`control.noise_frames`, against the stop threshold 1e-3) and s·√(τ/N) (that standard error with the correlation
counted), and the camera's distance from the goal.

`--rho-from START`: the general model's ρ* coefficients are those its first frame estimates from START (as a run from
START has them), instead of those of the probe's own first frame (near the goal: no parallax to see, ρ* = 0).

Run: `.venv/bin/python benchmarks/near_goal_noise.py [--condition hard_combination] [--start near|s4k1]
[--rho-from s4k1] [--images 700] [--skip 400]`
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from numpy.typing import NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.control.law import ControlConfig, ControlLaw
from ddvs_service.lie import pose, so3_exp
from ddvs_service.service.config import ServiceConfig
from ddvs_service.service.pipeline import ServoPipeline, StepResult
from orchestration import experiment_robustness as rob
from sim.freeflyer import FreeFlyer
from sim.ground_truth import GroundTruth

NEAR_T = (0.002, -0.001, 0.001)  # m
NEAR_R_DEG = (0.1, -0.1, 0.05)


def autocorrelation_time(x: NDArray[np.float64], cutoff: float = 0.05) -> float:
    """1 + 2 Σ_k c_k over the lags k ≥ 1 before the normalised autocorrelation c_k first drops below `cutoff`."""
    x = x - x.mean()
    c = np.correlate(x, x, "full")[len(x) - 1:] / float(x @ x)
    tau = 1.0
    for k in range(1, min(len(c), 100)):
        if c[k] < cutoff:
            break
        tau += 2.0 * c[k]
    return tau


def first_frame_rho(config: ServiceConfig, told: Intrinsics, reference: NDArray[np.uint8],
                    target: rob.Target, start: str) -> list[float]:
    """The ρ* coefficients the general model estimates on the first (clean) frame from `start`."""
    pipeline = ServoPipeline(config, told, background_reacquisition=False)
    pipeline.set_reference(reference)
    pipeline.machine.start()
    plant = rob.FreeFlyerPlant(target, start, pipeline.control_px)
    pipeline.step(np.clip(np.rint(plant.image()), 0, 255).astype(np.uint8))
    return list(pipeline.rho_coeffs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--condition", default="hard_combination", choices=list(rob.CONDITIONS))
    parser.add_argument("--start", default="near", help="'near' or a matrix start ('paper', 's4k1', ...)")
    parser.add_argument("--rho-from", default=None, help="a matrix start whose first frame's ρ* the run uses")
    parser.add_argument("--images", type=int, default=700)
    parser.add_argument("--skip", type=int, default=400)
    parser.add_argument("--overrides", default="{}", help="service configuration changes (JSON)")
    args = parser.parse_args()
    target = rob.make_target("saddle")
    condition = rob.CONDITIONS[args.condition]
    told = rob.told_intrinsics(target.camera, condition)
    config = rob.service_config(target, told, {"control": {"law": "ddvs", "stop_threshold": 0.0},
                                               **json.loads(args.overrides)})
    reference = np.clip(np.rint(rob.render_camera(target.surface, rob._texture(), target.camera, np.eye(4),
                                                  oversample=rob.OVERSAMPLE)), 0, 255).astype(np.uint8)
    rho = first_frame_rho(config, told, reference, target, args.rho_from) if args.rho_from else None
    pipeline = ServoPipeline(config, told, background_reacquisition=False)
    roi = pipeline.set_reference(reference, rho_coeffs=rho)
    plant = rob.FreeFlyerPlant(target, "paper" if args.start == "near" else args.start, pipeline.control_px)
    if args.start == "near":
        plant.flyer = FreeFlyer(target.surface, target.camera, np.eye(4),
                                pose(so3_exp(np.radians(NEAR_R_DEG)), NEAR_T), rob.DT, p_star=pipeline.control_px)
    law = ControlLaw(ControlConfig(law="ddvs", gains=config.control.gains, stop_threshold=0.0), told)
    gaps: list[NDArray[np.float64]] = []
    estimates: list[NDArray[np.float64]] = []

    def observe(truth: GroundTruth, step: StepResult) -> None:
        if step.state.value == "SERVOING":
            estimates.append(step.error)
            gaps.append(step.error - law.error(truth.G, truth.e, truth.rho))

    run = rob.Run("saddle", "ddvs", args.start, args.condition, "budget", 0, np.nan, np.nan, False, 0, 0, 0, "")
    rob.servo(run, plant, pipeline, roi, condition,
              rob.RobustnessSettings(targets=("saddle",), max_images=args.images), observe)
    window = config.control.noise_frames
    gap, estimate = np.array(gaps[args.skip:]), np.array(estimates[args.skip:])
    if len(gap) < 2 * window:
        raise SystemExit(f"only {len(gap)} servoed images after --skip {args.skip}; expected ≥ {2 * window}")
    s = float(np.sqrt(((estimate - estimate.mean(0)) ** 2).sum(1).mean()))
    tau = max(autocorrelation_time(gap[:, 0]), autocorrelation_time(gap[:, 4]))
    print(f"condition {args.condition}, start {args.start}, ρ* {'from ' + args.rho_from if rho else 'own'} "
          f"{np.round(pipeline.rho_coeffs, 4).tolist()}; {len(gap)} servoed images after {args.skip}")
    print(f"gap std per component {np.array2string(gap.std(0), precision=5)}; τ {tau:.1f} images")
    print(f"estimate scatter s {s:.2e}, s/√{window} {s / np.sqrt(window):.2e}, s·√(τ/{window}) "
          f"{s * np.sqrt(tau / window):.2e}; camera {np.median(run.pose_errors_mm[args.skip:]):.2f} mm from the goal "
          f"(median)")


if __name__ == "__main__":
    main()
