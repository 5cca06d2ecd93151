"""Never a confident wrong answer (issue 20): the servo acts only on fits it has reasons to trust.

State machine and error guard (pure logic) here; the engine-level integrity (anchored robust scale, implausible
fits) and the service pipeline on real frames below them."""

from __future__ import annotations

import numpy as np
import pytest

from ddvs_service.service.guard import ErrorGuard
from ddvs_service.service.state import FrameOutcome, ServoState, StateMachine


def test_lost_servo_resumes_only_after_confirmed_frames() -> None:
    sm = StateMachine(stop_threshold=1e-3, resume_threshold=5e-3, confirm_frames=3)
    sm.reference_set()
    sm.start()
    assert sm.on_frame(FrameOutcome(True, 0.3)) == ServoState.SERVOING
    assert sm.on_frame(FrameOutcome(False, np.nan)) == ServoState.LOST
    # one re-acquired frame, then a failure: the confirmation restarts
    assert sm.on_frame(FrameOutcome(True, 0.3)) == ServoState.LOST and not sm.moves
    assert sm.on_frame(FrameOutcome(False, np.nan)) == ServoState.LOST
    assert sm.on_frame(FrameOutcome(True, 0.3)) == ServoState.LOST
    assert sm.on_frame(FrameOutcome(True, 0.3)) == ServoState.LOST
    assert sm.on_frame(FrameOutcome(True, 0.3)) == ServoState.SERVOING and sm.moves
    with pytest.raises(ValueError, match="confirm_frames"):
        StateMachine(stop_threshold=1e-3, resume_threshold=5e-3, confirm_frames=0)


def test_error_guard_flags_a_jump_and_adopts_only_a_consistent_run() -> None:
    guard = ErrorGuard(jump_abs=0.1, jump_rel=0.25, rebase_frames=4)
    e = np.array([0.1, 0.0, 0.05, 0.0, 0.02, 0.0])
    assert guard.check(e) == ""  # the first tracked error is trusted
    assert guard.check(e * 0.98) == ""  # a servo step
    wrong = np.array([3.0, -1.0, 2.0, 0.5, 0.1, 1.0])  # the occluder fit of issue 20: norm 0.12 → 4.3
    assert "jumped" in guard.check(wrong)
    assert guard.check(e * 0.97) == ""  # back on the trusted track
    # a wrong fit wandering with the noise never builds a consistent run
    rng = np.random.default_rng(0)
    for _ in range(20):
        assert "jumped" in guard.check(wrong + rng.normal(scale=0.5, size=6))
    # a genuine displacement (the camera moved by hand while LOST) is adopted after rebase_frames agreeing frames
    moved = np.array([0.6, 0.2, 0.1, 0.0, 0.3, 0.1])
    assert "jumped" in guard.check(moved)
    moved = moved + 0.01
    for k in range(1, 3):
        assert f"{k + 1}/4" in guard.check(moved)
    assert guard.check(moved) == ""
    assert guard.check(moved * 0.99) == ""


# --- the service pipeline on rendered frames -------------------------------------------------------------------
CAMERA = {"fx": 420.0, "fy": 420.0, "cx": 159.5, "cy": 119.5, "width": 320, "height": 240}


def _render(T: np.ndarray) -> np.ndarray:
    """Anti-aliased 8-bit render of the graf poster 0.7 m ahead of the reference camera, from camera pose `T` (in
    the reference camera's frame)."""
    from ddvs_service.camera import Intrinsics
    from ddvs_service.lie import pose
    from sim.freeflyer import render_camera
    from sim.surfaces import Plane
    from sim.textures import load_texture

    cam = Intrinsics(**{k: CAMERA[k] for k in ("fx", "fy", "cx", "cy")}, width=320, height=240)
    plane = Plane(pose(np.eye(3), (0.0, 0.0, 0.7)), (1.2, 0.9))
    return np.clip(np.rint(render_camera(plane, load_texture("graf"), cam, T, oversample=2)), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def frames():
    """The camera, the reference render and a view 11 mm / 1.3° away."""
    from ddvs_service.camera import Intrinsics
    from ddvs_service.lie import pose, so3_exp

    cam = Intrinsics(**{k: CAMERA[k] for k in ("fx", "fy", "cx", "cy")}, width=320, height=240)
    return cam, _render(np.eye(4)), _render(pose(so3_exp([0.0, 0.02, 0.01]), (0.01, -0.005, 0.0)))


def _servo(frames, **registration):
    from ddvs_service.service.config import ServiceConfig
    from ddvs_service.service.pipeline import ServoPipeline

    cam, reference, _ = frames
    config = ServiceConfig.model_validate({"intrinsics": CAMERA, "registration": {
        "template_size": [70, 70], "levels": 3, **registration}})
    pipeline = ServoPipeline(config, cam, background_reacquisition=False)  # frame by frame: the search within
    roi = pipeline.set_reference(reference)
    pipeline.machine.start()
    return pipeline, roi


def _condition(image: np.ndarray, roi, *conditions) -> np.ndarray:
    from sim.conditions import FrameContext, apply

    return apply(conditions, image.astype(np.float32), FrameContext(5, 0.2, roi)).astype(np.uint8)


def test_after_lost_an_occluded_view_is_reacquired_from_the_last_good_estimate_and_right(frames) -> None:
    """Issue 20: LOST (a textureless frame), then the view comes back with 30 % of the template occluded, where the
    global initialiser's cost is above its threshold: the frame is re-acquired by tracking from the last good
    estimate, and that estimate is the unoccluded view's (within 0.5 px RMS over the ROI: a wrong fit lies pixels
    away). Nothing moves on it unless it is trusted: here the occluder, appearing at once, shifts the control error
    by more than the guard allows between frames, so the servo stays LOST with zero twists. (Before, such a frame
    was refused: the service stayed LOST under an occluder for good, even one that entered gradually.)"""
    from ddvs_service.registration.warp_distance import warp_rms
    from sim.conditions import Occluder

    pipeline, roi = _servo(frames, robust="tukey")
    _, _, view = frames
    assert pipeline.step(view).state == ServoState.SERVOING
    assert pipeline.G is not None
    clean = pipeline.G
    assert pipeline.step(np.full_like(view, 128)).state == ServoState.LOST  # textureless: untracked
    occluded = _condition(view, roi, Occluder(fraction=0.3, start_frame=0, enter_frames=1))
    step = pipeline.step(occluded)
    assert step.message.startswith("re-acquired by tracking from the last good estimate"), step.message
    assert warp_rms(pipeline.G, clean, roi) < 0.5  # the same optimum (the occluder biases it a little)
    for _ in range(5):
        assert step.state == ServoState.LOST and not np.any(step.twist), step
        step = pipeline.step(occluded)


def test_a_fit_whose_error_jumps_moves_nothing(frames) -> None:
    """Issue 20: a light ramp the single gain cannot represent biases the fit (error 0.035 → 0.25 at the same
    pose, inliers 100 % under the re-estimated scale): the service must not servo on it."""
    from sim.conditions import GainGradient

    pipeline, roi = _servo(frames, gain_grid=[1, 1])
    _, _, view = frames
    for _ in range(2):
        step = pipeline.step(view)
        assert step.state == ServoState.SERVOING and step.error_norm < 0.05
    step = pipeline.step(_condition(view, roi, GainGradient(0.3, 1.7, turn_period_s=0.0)))
    assert step.state == ServoState.LOST and not np.any(step.twist)
    assert "suspect fit" in step.message
    for _ in range(pipeline.machine.confirm_frames - 1):  # the light is back: held until confirmed
        assert pipeline.step(view).state == ServoState.LOST
    assert pipeline.step(view).state == ServoState.SERVOING


# --- the tracker: anchored scale and implausible fits ----------------------------------------------------------
def _shifted_frames(occluded_from: int, n: int, fraction: float, enter_frames: int = 1, roi=(125, 85, 70, 70)):
    """A 320×240 view of the graf texture shifted by (0.3 k, 0.15 k) px in frame k, and from frame `occluded_from`
    on the left of the image up to `fraction` of the template box `roi` covered by another scene (boat), reached
    over `enter_frames` frames (sliding in from the left, as `sim.conditions.Occluder`)."""
    import cv2

    from sim.textures import load_texture

    h, w = 240, 320
    reference = cv2.resize(load_texture("graf"), (2 * w, 2 * h), interpolation=cv2.INTER_AREA)[h // 2 : h // 2 + h,
                                                                                                w // 2 : w // 2 + w]
    reference = np.ascontiguousarray(reference)
    other = cv2.resize(load_texture("boat"), (w, h), interpolation=cv2.INTER_AREA)
    frames = []
    for k in range(n):
        shift = np.array([[1.0, 0.0, 0.3 * k], [0.0, 1.0, 0.15 * k]])
        frame = cv2.warpAffine(reference, shift, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        if k >= occluded_from:
            cols = int(roi[0] + fraction * min(1.0, (k - occluded_from + 1) / enter_frames) * roi[2])
            frame[:, :cols] = other[:, w - cols :]
        frames.append((np.rint(frame).astype(np.float32), (0.3 * k, 0.15 * k)))
    return reference, roi, frames


def test_tracker_inlier_ratio_measures_a_sudden_occluder() -> None:
    """Issue 20: 43 % of the template covered at once. With σ re-estimated from every iteration's median the
    occluder's residuals inflated σ (20 grey levels) and 91 % of the pixels counted as inliers; with σ capped at
    the last good frames' scale the inlier ratio measures the occlusion. Tukey weights (the service default) keep
    the fit on the visible part: every frame within 0.5 px at the template's corners (Huber: 1.8 px)."""
    from ddvs_service.registration.config import RegistrationConfig
    from ddvs_service.registration.tracker import Tracker

    reference, roi, frames = _shifted_frames(occluded_from=6, n=10, fraction=0.43)
    x, y, w, h = roi
    corners = np.array([[x, x + w - 1, x + w - 1, x], [y, y, y + h - 1, y + h - 1], [1.0, 1.0, 1.0, 1.0]])
    for robust in ("huber", "tukey"):
        tracker = Tracker.prepare(reference, roi, RegistrationConfig(levels=3, robust=robust))
        for k, (frame, (tx, ty)) in enumerate(frames):
            result = tracker.track(frame)
            q = result.G @ corners
            error = float(np.max(np.abs(q[:2] / q[2] - corners[:2] - np.array([[tx], [ty]]))))
            assert result.converged, (robust, k, result.reason)
            if k >= 6:
                assert result.inlier_ratio < 0.8, (robust, k, result.inlier_ratio)
            if robust == "tukey":
                assert error < 0.5, (k, error)


def test_tracker_follows_an_occluder_sliding_over_more_than_half_the_template() -> None:
    """Issue 20 (the planar hard combination from s4k0 went LOST at image 115, 52 mm from the goal): an occluder
    sliding in covered 57 % of the template there, the fit 0.08 px from the truth with 46 % of the pixels inliers,
    and the engine refused it (fewer than `min_inlier_ratio` 0.5), then the integrity check (the frame's scale, the
    median of a majority of occluder residuals, 28 grey levels > 4 × the anchor's 4.1). Here 60 % of the shipped
    140×140 template covered over 10 frames: tracked to the end within 0.6 px at the corners (two of them hidden),
    at a support under half the pixels; the same occluder at once (a support lost in one frame, as a wrong
    optimum's) is still refused."""
    from ddvs_service.registration.config import RegistrationConfig
    from ddvs_service.registration.tracker import Tracker

    config = RegistrationConfig(levels=3, robust="tukey", gain_grid=(1, 1))  # one gain, as measured
    roi = (90, 50, 140, 140)
    x, y, w, h = roi
    corners = np.array([[x, x + w - 1, x + w - 1, x], [y, y, y + h - 1, y + h - 1], [1.0, 1.0, 1.0, 1.0]])
    for enter_frames in (10, 1):
        reference, _, frames = _shifted_frames(6, 20, 0.6, enter_frames, roi)
        tracker = Tracker.prepare(reference, roi, config)
        for k, (frame, (tx, ty)) in enumerate(frames):
            result = tracker.track(frame)
            q = result.G @ corners
            error = float(np.max(np.abs(q[:2] / q[2] - corners[:2] - np.array([[tx], [ty]]))))
            if enter_frames == 1 and k == 6:
                assert not result.converged, (k, result.inlier_ratio)
                break
            assert result.converged, (enter_frames, k, result.reason)
            assert error < 0.6, (k, error)
        if enter_frames == 10:
            assert result.inlier_ratio < 0.5  # the last frames: fewer than half the pixels support the fit


def test_stop_decision_averages_the_estimation_noise_out() -> None:
    """Near the goal a 70×70 template's error norm jitters at ~2e-3 from frame to frame while the camera is 0.5 mm
    away: the stop compares the mean error over `settle_frames` tracked frames and their scatter (RMS deviation from
    the mean, inf until the window is full); an untracked frame empties the window."""
    from ddvs_service.service.settling import SettleWindow

    window = SettleWindow(settle_frames=4, noise_frames=90, threshold=1e-3)
    rng = np.random.default_rng(3)
    bias = np.full(6, 1e-4)
    settled = [window.add(bias + rng.normal(scale=1e-3, size=6))[:2] for _ in range(12)]
    norms, scatters = np.array(settled).T
    assert np.median(norms[4:]) < 0.6 * 2.4e-3  # one frame's norm: about 1e-3 · √6
    assert np.all(np.isinf(scatters[:3]))  # fewer than settle_frames tracked frames back the mean
    assert np.all((scatters[3:] > 1e-3) & (scatters[3:] < 4e-3))  # ≈ 1e-3 · √(6 · 3/4)
    norm, scatter = window.add(None)[:2]
    assert np.isnan(norm) and np.isinf(scatter)
    first = bias + 2e-3
    assert window.add(first)[:2] == (pytest.approx(float(np.linalg.norm(first))), np.inf)


def test_a_noisy_unbiased_estimate_converges_on_the_long_window() -> None:
    """Issue 20 ("every condition converges"): control errors drawn about zero from the covariance the
    registration predicts, scattering by 6e-3 as the free-flyer's hard combination's do at the goal: the short
    window's scatter stays above 2 × the threshold (the scatter bound alone kept such a servo SERVOING for good);
    once the long window (90 frames) is full its mean is known to within the threshold and its scatter is what
    the noise predicts: CONVERGED. The same errors with a covariance that predicts a quarter of their scatter (a fit
    that wanders by more than its noise explains) are not."""
    from ddvs_service.camera import Intrinsics
    from ddvs_service.control.law import ControlLaw
    from ddvs_service.service.config import ServiceConfig
    from ddvs_service.service.settling import SettleWindow, error_jacobian

    cam = Intrinsics(**{k: CAMERA[k] for k in ("fx", "fy", "cx", "cy")}, width=320, height=240)
    A = error_jacobian(ControlLaw(ServiceConfig().control.law_config(), cam), np.eye(3), np.zeros(3), 0.0)
    rng = np.random.default_rng(4)
    B = rng.normal(size=(12, 12))
    covariance = B @ B.T
    covariance *= 6e-3**2 / np.trace(A @ covariance @ A.T)  # the predicted scatter: 6e-3
    errors = rng.multivariate_normal(np.zeros(6), A @ covariance @ A.T, size=150)
    for scale, converges in ((1.0, True), (1.0 / 16.0, False)):
        sm = StateMachine(stop_threshold=1e-3, resume_threshold=5e-3, converge_frames=3, scatter_threshold=2e-3)
        sm.reference_set()
        sm.start()
        window = SettleWindow(settle_frames=10, noise_frames=90, threshold=1e-3)
        states, scatters = [], []
        for error in errors:
            figures = window.add(error, scale * covariance, lambda: A)
            scatters.append(figures[1])
            states.append(sm.on_frame(FrameOutcome(True, float(np.linalg.norm(error)), *figures)))
        assert min(scatters) > 2e-3
        if converges:
            assert states.index(ServoState.CONVERGED) >= 91, states  # the long window full, then 3 frames
        else:
            assert ServoState.CONVERGED not in states


def test_the_registration_covariance_predicts_the_scatter_of_its_estimate(frames) -> None:
    """The stop rule's long window compares the control error's scatter with the one the registration's
    Gauss-Newton covariance predicts (`RegistrationResult.covariance` through the law's Jacobian): on frames at
    the reference with independent noise σ 12 on each pixel (140×140 template, the service's 3×3 gains and Tukey
    weights) the two agree within 25 %."""
    from ddvs_service.control.law import ControlLaw
    from ddvs_service.registration.planar import register
    from ddvs_service.service.config import ServiceConfig
    from ddvs_service.service.pipeline import template_roi
    from ddvs_service.service.settling import error_jacobian

    cam, reference, _ = frames
    config = ServiceConfig.model_validate({"intrinsics": CAMERA, "registration": {"template_size": [140, 140]}})
    law = ControlLaw(config.control.law_config(), cam)
    roi = template_roi(config, cam)
    rng = np.random.default_rng(6)
    errors, predicted = [], []
    for _ in range(40):
        noisy = np.clip(np.rint(reference + rng.normal(scale=12.0, size=reference.shape)), 0, 255).astype(np.uint8)
        result = register(reference, noisy, roi, G0=np.eye(3), config=config.registration.engine_config())
        assert result.converged and result.covariance is not None, result.reason
        A = error_jacobian(law, result.G, np.zeros(3), 0.0)
        errors.append(law.error(result.G, np.zeros(3), 0.0))
        predicted.append(np.trace(A @ result.covariance @ A.T))
    E = np.asarray(errors)
    measured = np.sqrt(np.mean(np.sum((E - E.mean(axis=0)) ** 2, axis=1)))
    assert measured > 2e-3  # noisy: above the short window's scatter bound
    assert measured / np.sqrt(np.mean(predicted)) == pytest.approx(1.0, abs=0.25)


@pytest.mark.slow
def test_the_general_registration_covariance_predicts_the_scatter_of_its_estimate() -> None:
    """The same for the general model (eq. (2): the saddle, 200×150 ROI, ρ* estimated once 5 cm / 3° from the
    reference, then held): the covariance of [vec(G), e] through the decoupled law's Jacobian predicts the control
    error's scatter over frames with independent noise σ 8 within 25 %."""
    from ddvs_service.camera import Intrinsics
    from ddvs_service.control.law import ControlLaw
    from ddvs_service.lie import pose, so3_exp
    from ddvs_service.registration.general_register import register_general
    from ddvs_service.service.config import ServiceConfig
    from ddvs_service.service.settling import error_jacobian
    from sim.freeflyer import render_camera
    from sim.surfaces import paper_saddle
    from sim.textures import load_texture

    cam = Intrinsics.centred(500.0, 550, 418)
    roi = (175, 134, 200, 150)
    saddle, texture = paper_saddle(), load_texture("graf")
    reference = np.clip(np.rint(render_camera(saddle, texture, cam, np.eye(4))), 0, 255)
    current = np.clip(np.rint(render_camera(saddle, texture, cam, pose(so3_exp([0.0, 0.05, 0.0]), (-0.05, 0, 0)))),
                      0, 255)
    first = register_general(reference, current, roi)
    assert first.converged and first.parallax_px > 0.2, first.reason
    law = ControlLaw(ServiceConfig().control.law_config(), cam)
    rng = np.random.default_rng(1)
    errors, predicted = [], []
    for _ in range(20):
        noisy = np.clip(np.rint(current + rng.normal(scale=8.0, size=current.shape)), 0, 255)
        result = register_general(reference, noisy, roi, G0=first.G, e0=first.e, rho0=first.rho_coeffs)
        assert result.converged and result.covariance is not None, result.reason
        rho = result.rho_at((cam.cx, cam.cy))
        A = error_jacobian(law, result.G, result.e, rho)
        errors.append(law.error(result.G, result.e, rho))
        predicted.append(np.trace(A @ result.covariance @ A.T))
    E = np.asarray(errors)
    measured = np.sqrt(np.mean(np.sum((E - E.mean(axis=0)) ** 2, axis=1)))
    assert measured / np.sqrt(np.mean(predicted)) == pytest.approx(1.0, abs=0.25)


def test_a_scattered_estimate_whose_mean_reads_zero_is_not_converged(frames) -> None:
    """Issue 20 (the arm, 70×70, a plate over 30 % of the template: CONVERGED 10.8 mm away): an estimate that
    scatters by several stop thresholds from frame to frame around a mean below the threshold is not evidence of the
    pose. Here real registrations (the shipped 140×140 template: at 70×70 the alternation itself drags the tilt
    estimate to a biased optimum) of views 3 mm to either side of the reference, alternating: each frame's error
    norm ≈ 5e-3, their 10-frame mean's norm below 1e-3 — the mean alone (the stop before) declared CONVERGED on
    the 8th frame; the scatter bound (2 × 1e-3) keeps the servo SERVOING. At the reference itself it converges once
    the scattered frames have left the window."""
    from ddvs_service.lie import pose

    pipeline, _ = _servo(frames, template_size=[140, 140])
    assert pipeline.config.control.scatter_factor == 2.0 and pipeline.config.control.settle_frames == 10
    sides = [_render(pose(np.eye(3), (dx, 0.0, 0.0))) for dx in (0.003, -0.003)]
    errors = []
    for k in range(30):
        step = pipeline.step(sides[k % 2])
        errors.append(step.error)
        assert step.state == ServoState.SERVOING, (k, step)
    recent = np.array(errors[-10:])
    assert np.linalg.norm(recent.mean(axis=0)) < 1e-3  # what the stop on the mean alone compared
    assert np.min(np.linalg.norm(recent, axis=1)) > 4e-3
    _, reference, _ = frames
    states = [pipeline.step(reference).state for _ in range(13)]
    # the mean alone stopped on the 3rd frame; the scatter falls below 2e-3 once 9 of the window's 10 frames are
    # the reference's (≈ 5e-3 · √(1/10)), then 3 frames in a row
    assert states[-1] == ServoState.CONVERGED and states.index(ServoState.CONVERGED) >= 10, states


# --- the inliers' scale (registration.integrity.inlier_scale) ---------------------------------------------------
def test_inlier_scale_removes_the_outliers_inflation_of_the_median() -> None:
    """The median |r| over inliers (Gaussian, σ 10) and 25 % outliers far beyond the cut-off is not the inliers'
    median: 1.4826 · median overstates σ by ~1.4×, the corrected scale recovers it; no correction without
    outliers."""
    from ddvs_service.registration.integrity import inlier_scale

    rng = np.random.default_rng(1)
    r = np.concatenate([rng.normal(scale=10.0, size=30000), rng.uniform(200.0, 400.0, size=10000)])
    mad = 1.4826 * float(np.median(np.abs(r)))
    assert mad > 13.0
    assert inlier_scale(mad, 0.75) == pytest.approx(10.0, rel=0.05)
    assert inlier_scale(10.0, 1.0) == pytest.approx(10.0)
    assert inlier_scale(float("nan"), 0.8) != inlier_scale(float("nan"), 0.8)  # nan stays nan


def test_occluder_on_a_dimmed_scene_stays_out_of_the_fit() -> None:
    """Issue 20 (the saddle's hard combination ended CONVERGED 20 mm from the goal): a scene dimmed to 1/3 (noise
    σ 4, × 3 in reference grey levels) and a foreign object at full brightness over the left 30 % of a 200×150 ROI.
    With σ at the frame's MAD (inflated 1.5× by the occluder) the occluder's pixels within Tukey's cut-off, their
    gradients × the gain, pulled one registration 0.9 px off at the ROI's corners; the tracker's cap (0.6 × the
    last good frames' inliers' scale) keeps the fit on the target."""
    import cv2

    from ddvs_service.registration.config import RegistrationConfig
    from ddvs_service.registration.planar import PlanarRegistration
    from ddvs_service.registration.tracker import Tracker
    from evaluation.pairs import load

    reference = cv2.GaussianBlur(load("boat", 1), (0, 0), 1.5).astype(np.float32)
    foreign = cv2.GaussianBlur(load("bikes", 1).astype(np.float32), (0, 0), 1.5)
    roi = (325, 265, 200, 150)
    x, y, w, h = roi
    corners = np.array([[x, x + w - 1, x + w - 1, x], [y, y, y + h - 1, y + h - 1], [1.0, 1.0, 1.0, 1.0]])

    def frame(k: int, occluded: bool) -> np.ndarray:
        current = reference / 3.0 + np.random.default_rng(k).normal(scale=4.0, size=reference.shape)
        if occluded:
            current[:, : x + 60] = foreign[: reference.shape[0], : x + 60]
        return np.clip(np.rint(current), 0, 255).astype(np.float32)

    def corner_error(G: np.ndarray) -> float:
        q = G @ corners
        return float(np.max(np.linalg.norm(q[:2] / q[2] - corners[:2], axis=0)))

    config = RegistrationConfig(levels=3, gain_grid=(3, 3), robust="tukey")
    uncapped = PlanarRegistration.prepare(reference, roi, config=config).run(
        frame(0, True), G0=np.eye(3), gains0=3.0, scale0=12.0, first_level=0, tolerance_px=1e-2)
    assert uncapped.converged and corner_error(uncapped.G) > 0.5  # the failure this guards against
    tracker = Tracker.prepare(reference, roi, config)
    errors = []
    for k in range(16):
        result = tracker.track(frame(k, k >= 6))
        assert result.converged, (k, result.reason)
        errors.append(corner_error(result.G))
    assert max(errors) < 0.2, errors
