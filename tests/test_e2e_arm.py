"""End-to-end proof on the simulated UR5 (issue 7): `ddvs sim arm` (lockstep), `ddvs serve` and `ddvs bridge` as
separate processes over Zenoh on loopback, the paper's real-data set-up (planar poster 0.7 m in front of the
reference camera, displacement t = [0.13, −0.23, −0.08] m, r = [−20.3, 2.17, 14.59]°, 320×240, f = 420 px,
λ = 0.4, stop at ‖ε‖ < 1e-3). The reference image is rendered at the reference pose and uploaded.

Each case writes its recording (a bag, which `rosbags` and the `mcap` reader must read completely), plots and
summary to `reports/e2e_arm/<case>/` (images to convergence beside the paper's 417 for DVS and 309 for the
decoupled DVS).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from bag_checks import check_bag

from clients.channels import topic_name
from ddvs_service.protocol import Keys
from orchestration.arm_run import ArmRunSettings, run_arm
from orchestration.demo import write_report

ROOT = Path(__file__).resolve().parents[1]
REPORTS = ROOT / "reports" / "e2e_arm"
MAX_TRANSLATION_MM = 3.0
MAX_ROTATION_DEG = 0.3


# The paper's 70×70 template sees the poster through ±4.8°: a tilt of the estimate (h31, h32) moves its corners by
# 0.01 px per 3e-3 of the control error, so the estimate's tilt near the goal is off by a few 1e-3 (see
# orchestration/demo.py) and the servo settles where the biased estimate reads zero. A 3×3 gain surface over 70×70
# pixels takes more of that weak signal (measured in-process, lockstep, on both kinds of frames: the reduced DVS settles
# 4–6.6 mm away with 3×3, 1.5–1.8 mm with one gain; the decoupled law is less affected: its stop fell 2.5–3.2 mm away
# with 3×3 over four runs, 2.3 mm with one gain, and 3.15 mm in tests/test_security_e2e.py's lockstep run with 3×3):
# the 70×70 runs use one gain, the exact photometric model of the arm's uniform light; the 200×150 ROI keeps the
# service's default.
SINGLE_GAIN = (1, 1)


@pytest.mark.slow
@pytest.mark.parametrize(("law", "template", "gain_grid"), [
    ("ddvs", (70, 70), SINGLE_GAIN),
    ("dvs_reduced", (70, 70), SINGLE_GAIN),
    ("ddvs", (200, 150), None),
])
def test_both_laws_converge_to_the_reference_pose(law, template, gain_grid):
    out = REPORTS / f"{law}_{template[0]}x{template[1]}"
    shutil.rmtree(out, ignore_errors=True)
    settings = ArmRunSettings(out_dir=out, law=law, template=template, gain_grid=gain_grid, clock="lockstep",
                              max_images=1500, time_limit=240.0, robot=f"e2e_{law}_{template[0]}")
    result = run_arm(settings)
    summary = write_report(result, settings, out)
    print(json.dumps({k: summary[k] for k in ("law", "template", "images_to_convergence",
                                              "paper_images_to_convergence", "final_error_norm",
                                              "final_translation_error_mm", "final_rotation_error_deg")}))
    assert result.converged, f"{result.reason}; logs in {out / 'logs'}"
    # The stop rule judges the mean control error over the last `settle_frames` frames (issue 20): one frame's norm
    # still carries the estimation noise (1–2e-3 measured at the goal), so the last frame is held to a noise band and
    # the pose errors below are the physical check.
    assert summary["final_error_norm"] < 5e-3
    assert summary["final_translation_error_mm"] < MAX_TRANSLATION_MM, summary
    assert summary["final_rotation_error_deg"] < MAX_ROTATION_DEG, summary
    assert summary["initial_translation_error_mm"] > 250.0  # it really started at the paper's displacement
    for figure in summary["figures"]:
        assert (out / figure).stat().st_size > 10_000, figure
    counts = check_bag(result.recording_dir)  # rosbags decodes every ROS message; the mcap summaries agree
    assert counts == summary["recording"]["messages"]
    assert counts[topic_name(Keys(settings.prefix, settings.robot), "camera_image")] >= summary["frames"]


@pytest.mark.slow
def test_the_saddle_converges_with_the_general_model_and_records_its_residual():
    """`configs/arm/ur5_saddle.json` (a non-planar target under an illumination ramp, the scene `ddvs demo --scene`
    takes) with the decoupled law: the general model of eq. (2) estimates `G`, `e` and ρ* from the images alone, the
    arm converges to the reference pose, and the bag carries the general model's residual images."""
    from orchestration.demo import scene_model

    scene = ROOT / "configs" / "arm" / "ur5_saddle.json"
    out = REPORTS / "ddvs_saddle"
    shutil.rmtree(out, ignore_errors=True)
    settings = ArmRunSettings(out_dir=out, law="ddvs", template=(100, 100), clock="lockstep", max_images=1500,
                              time_limit=300.0, robot="e2e_saddle", scene=scene, model=scene_model(scene))
    assert settings.model == "general"
    result = run_arm(settings)
    summary = write_report(result, settings, out)
    assert result.converged, f"{result.reason}; logs in {out / 'logs'}"
    assert summary["final_translation_error_mm"] < 1.0, summary
    assert summary["final_rotation_error_deg"] < 0.1, summary
    counts = check_bag(result.recording_dir)
    assert counts[topic_name(Keys(settings.prefix, settings.robot), "servo_residual")] > 0, counts
