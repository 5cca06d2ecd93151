"""The residual image over the ROI (`registration.residual`): zero where the model explains the current image, the
engine's own residual after a real registration, and the misalignment before it."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ddvs_service.registration.config import RegistrationConfig
from ddvs_service.registration.planar import register
from ddvs_service.registration.residual import gain_surface, residual_image
from evaluation.pairs import load

ROI = (325, 265, 200, 150)


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    return cv2.GaussianBlur(load("boat", 1), (0, 0), 1.5)


def _scene(texture: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A current image = (I* − β)/S seen through H, S a 2×2 gain grid over the ROI, β = 12."""
    x, y, w, h = ROI
    H = np.array([[1.02, 0.03, -6.0], [-0.02, 1.01, 4.0], [1e-5, -2e-5, 1.0]])
    corners = np.array([[0.8, 1.1], [1.2, 0.9]])
    S = np.ones_like(texture)
    S[y:y + h, x:x + w] = gain_surface(corners, w, h)
    current = cv2.warpPerspective((texture - 12.0) / S, H, texture.shape[::-1], flags=cv2.INTER_LINEAR)
    return current, H, corners


def test_the_true_model_leaves_no_residual_and_identity_shows_the_motion(texture):
    current, H, corners = _scene(texture)
    r = residual_image(texture, current, ROI, H, corners, 12.0)
    assert r.shape == (150, 200) and r.dtype == np.float32
    inner = r[5:-5, 5:-5]
    assert np.sqrt(np.nanmean(inner**2)) < 2.5  # the scene's own warp: OpenCV's 1/32-pixel bilinear, resampled
    misaligned = residual_image(texture, current, ROI, np.eye(3), np.ones((1, 1)), 0.0)
    assert np.sqrt(np.nanmean(misaligned**2)) > 20.0


def test_after_a_registration_it_is_the_engines_residual(texture):
    current, _, _ = _scene(texture)
    result = register(texture, current, roi=ROI, config=RegistrationConfig(levels=3, gain_grid=(2, 2)))
    assert result.converged, result.reason
    r = residual_image(texture, current, ROI, result.G, result.S, result.beta)
    assert np.sqrt(np.nanmean(r**2)) == pytest.approx(result.residual_rms, rel=0.1, abs=0.2)


def test_gain_surface_is_bilinear_between_the_corner_nodes():
    S = gain_surface(np.array([[1.0, 2.0], [3.0, 5.0]]), width=5, height=3)
    assert S[0, 0] == 1.0 and S[0, -1] == 2.0 and S[-1, 0] == 3.0 and S[-1, -1] == 5.0
    assert S[1, 2] == pytest.approx((1 + 2 + 3 + 5) / 4)
    assert np.all(gain_surface(np.array([[1.5]]), 4, 4) == 1.5)


def test_points_outside_the_current_image_are_nan(texture):
    shifted = np.array([[1.0, 0.0, 400.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # the ROI's right part leaves the image
    r = residual_image(texture, texture, ROI, shifted, np.ones((1, 1)), 0.0)
    assert np.isnan(r[:, -1]).all() and np.isfinite(r[:, 0]).all()


def test_the_servo_pipeline_gives_the_residual_of_its_newest_estimate(texture):
    """Through the service's pipeline (planar model): after a step on a frame 3 px from the reference, the residual
    over the ROI is small; the same frame against an untracked pipeline (identity) is not."""
    from ddvs_service.camera import Intrinsics
    from ddvs_service.service.config import ServiceConfig
    from ddvs_service.service.pipeline import ServoPipeline

    reference = texture[200:440, 250:570]
    frame = cv2.warpAffine(reference, np.array([[1.0, 0.0, 3.0], [0.0, 1.0, -2.0]]), (320, 240))
    camera = {"fx": 420.0, "fy": 420.0, "cx": 159.5, "cy": 119.5, "width": 320, "height": 240}
    config = ServiceConfig.model_validate({"intrinsics": camera, "registration": {"template_size": [120, 90]}})
    pipeline = ServoPipeline(config, Intrinsics(**camera), background_reacquisition=False)  # the search in the step
    assert pipeline.residual(frame) is None  # no reference yet
    roi = pipeline.set_reference(reference)
    before = pipeline.residual(frame)
    pipeline.step(frame)
    after = pipeline.residual(frame)
    assert after.shape == before.shape == (roi[3], roi[2])
    assert np.sqrt(np.nanmean(after**2)) < 0.2 * np.sqrt(np.nanmean(before**2))


def test_the_general_model_residual_includes_the_parallax():
    """The general model's residual image (eq. (2)'s warp) on a saddle view 8 cm and 30° away: after the first
    frame's registration through the service's pipeline it is well below the residual of
    the same estimate's homography alone (`G`, no parallax) — the parallax the planar residual cannot explain."""
    from ddvs_service.lie import pose, so3_exp
    from ddvs_service.service.config import ServiceConfig
    from ddvs_service.service.pipeline import ServoPipeline
    from orchestration.experiment_domain import CAMERA, ROI, make_surface
    from orchestration.experiment_synthetic import TEXTURE
    from sim.freeflyer import render_view
    from sim.textures import load_texture

    saddle, tex = make_surface("saddle"), load_texture(TEXTURE)
    reference = render_view(saddle, tex, CAMERA, np.eye(4))[0]
    frame = render_view(saddle, tex, CAMERA, pose(so3_exp(np.radians([-5.0, -12.0, 25.0])), [0.06, -0.05, 0.0]))[0]
    camera = {"fx": CAMERA.fx, "fy": CAMERA.fy, "cx": CAMERA.cx, "cy": CAMERA.cy, "width": CAMERA.width,
              "height": CAMERA.height}
    config = ServiceConfig.model_validate({"intrinsics": camera,
                                           "registration": {"model": "general", "roi": list(ROI), "levels": 3}})
    pipeline = ServoPipeline(config, CAMERA, background_reacquisition=False)
    pipeline.set_reference(reference, ROI)
    pipeline.step(frame)
    general = pipeline.residual(frame)
    assert general is not None and general.shape == (ROI[3], ROI[2])
    assert pipeline.G is not None
    planar = residual_image(reference, frame, ROI, pipeline.G, np.ones((1, 1)), 0.0)
    assert np.sqrt(np.nanmean(general**2)) < 0.6 * np.sqrt(np.nanmean(planar**2))
