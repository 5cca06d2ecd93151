"""Clipped pixels take no part in the fit (issue 20): a current sample on the 8-bit ceiling (`kernels.planar_step.
SATURATED`) is invalid in both step kernels, since eq. (4) `S · I + β` does not hold where the sensor clipped.
Real Taichi kernels, a real texture, the saddle's rendered first frame."""

from __future__ import annotations

import cv2
import numpy as np
from test_kernels_planar_step import G_TEST, IMG, make_params, run_kernel


def test_planar_step_counts_a_clipped_block_as_invalid() -> None:
    """A 30×40 block at 255 in the current image: its pixels (and their 1-pixel border, whose central differences
    use them) leave the valid count, the oracle agreeing."""
    from evaluation.numpy_iteration import numpy_step

    grid = (1, 1)
    cur = cv2.warpPerspective(IMG, G_TEST, (IMG.shape[1], IMG.shape[0])) * 0.9 + 7.0
    params = make_params(grid)
    _, _, clean = run_kernel(IMG, cur, params, grid)
    cur[300:330, 380:420] = 255.0
    _, _, clipped = run_kernel(IMG, cur, params, grid)
    lost = clean[0] - clipped[0]
    assert 30 * 40 <= lost <= 34 * 44, lost
    assert clipped[0] == numpy_step(IMG, cur, params, grid).n_valid


def test_saddle_parallax_from_a_partly_saturated_first_frame() -> None:
    """The robustness matrix's saddle hard combination: on the first frame (paper's start) the turning gain ramp
    (0.6–1.4) clips 2 % of the pixels and, with noise σ 4 and JPEG q70, the parallax field ρ* — estimated on that
    frame and then held — came out as a different field (coefficients (0.0081, −0.0042, 0, −0.0095) against
    (0.0068, −0.0001, 0, −0.0122) in nominal light, up to the sign of (e, ρ*)), which biased θμ of the DVS error by
    0.11 for the run. With the clipped samples out, the same field as in nominal light."""
    from ddvs_service.registration.general import GeneralRegistration
    from ddvs_service.service.pipeline import template_roi
    from orchestration import experiment_robustness as er
    from sim.conditions import FrameContext, apply
    from sim.freeflyer import render_camera
    from sim.textures import load_texture

    target = er.make_target("saddle")
    condition = er.CONDITIONS["hard_combination"]
    told = er.told_intrinsics(target.camera, condition)
    config = er.service_config(target, told, {})
    roi = template_roi(config, told)
    reference = render_camera(target.surface, load_texture(er.TEXTURE), target.camera, np.eye(4),
                              oversample=er.OVERSAMPLE)
    engine = GeneralRegistration.prepare(np.clip(np.rint(reference), 0, 255).astype(np.float32), roi,
                                         config=config.registration.general_config())
    plant = er.FreeFlyerPlant(target, "paper", (told.cx, told.cy))
    frame = plant.image()

    def rho(images) -> np.ndarray:
        image = apply(images, frame, FrameContext(0, 0.0, roi, (0.0, 0.0)))
        result = engine.estimate(np.clip(np.rint(image), 0, 255).astype(np.float32), plant.truth().G)
        assert result.converged, result.reason
        c = result.rho_coeffs
        return c * np.sign(c[np.argmax(np.abs(c))])  # the gauge (e, ρ*) ~ (−e, −ρ*)

    hard = apply(condition.images, frame, FrameContext(0, 0.0, roi, (0.0, 0.0)))
    assert np.mean(hard >= 255.0) > 0.01  # the premise: part of the frame is clipped
    nominal = rho(())
    assert np.max(np.abs(rho(condition.images) - nominal)) < 5e-4
