"""General registration of eq. (2) on frames ray-cast by the analytic renderer (`sim.freeflyer`): the paper's saddle
along its synthetic trajectory from a cold start, an oblique plane (ρ* ≈ 0), the failure modes and LOST recovery,
and the gauge of the parallax basis."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import replace
from functools import cache

import cv2
import numpy as np
import pytest

from ddvs.cli import main
from ddvs_service.camera import Intrinsics
from ddvs_service.lie import pose, so3_exp
from ddvs_service.registration.config import RegistrationConfig
from ddvs_service.registration.general import (
    EPIPOLE_EVIDENCE_FRAMES,
    FREE_EPIPOLE_MEAN_WALD,
    FREE_EPIPOLE_WALD,
    GeneralRegistration,
)
from ddvs_service.registration.general_basis import ParallaxBasis, coefficient_count
from ddvs_service.registration.general_config import FLAG_NO_PARALLAX, FLAG_OCCLUSION, GeneralConfig
from ddvs_service.registration.general_register import register_general
from ddvs_service.registration.general_result import warp_points
from ddvs_service.registration.general_tracker import GeneralTracker
from ddvs_service.registration.global_init import GlobalInitConfig
from ddvs_service.registration.reacquisition import Reacquisition
from ddvs_service.registration.session import TrackingSession
from evaluation.general_accuracy import measure
from evaluation.pairs import ONE_GAIN_HUBER
from orchestration.experiment_synthetic import SyntheticSetup, run_synthetic
from sim.freeflyer import render_camera, render_view
from sim.ground_truth import ground_truth, parallax_map
from sim.surfaces import Plane, paper_saddle
from sim.textures import texture_path

MEASURED = GeneralConfig(base=RegistrationConfig(**ONE_GAIN_HUBER))  # the settings the accuracy was measured with

INTR = Intrinsics.centred(500.0, 550, 418)
ROI = (175, 134, 200, 150)  # 200×150, centred on the principal point (the control point)
CONTROL_POINT = (INTR.cx, INTR.cy)
PHOTO = str(texture_path("graf"))


@cache
def texture() -> np.ndarray:
    return cv2.imread(PHOTO, cv2.IMREAD_GRAYSCALE).astype(np.float32)


def roi_pixels() -> np.ndarray:
    x, y, w, h = ROI
    u, v = np.meshgrid(np.arange(x, x + w, dtype=float), np.arange(y, y + h, dtype=float))
    return np.c_[u.ravel(), v.ravel()]


def true_warp(surface, T_cur: np.ndarray) -> np.ndarray:
    """Ground-truth current pixels of the ROI's reference pixels, eq. (2) with the exact G, e, ρ*."""
    gt = ground_truth(surface, INTR, np.eye(4), T_cur)
    p = roi_pixels()
    rho = parallax_map(surface, INTR, np.eye(4))[p[:, 1].astype(int), p[:, 0].astype(int)]
    P = np.c_[p, np.ones(len(p))] @ gt.G.T + np.outer(rho, gt.e)
    return P[:, :2] / P[:, 2:]


def warp_rms(result, surface, T_cur: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((result.warp(roi_pixels()) - true_warp(surface, T_cur)) ** 2, axis=1))))


def render(surface, T: np.ndarray) -> np.ndarray:
    return render_view(surface, texture(), INTR, T)[0]


def test_basis_fixes_the_plane_gauge() -> None:
    """Every basis function has zero mean and zero first moments over the ROI, unit RMS, and they are orthogonal."""
    for degree, n in ((2, 6), (3, 13)):
        basis = ParallaxBasis.over(ROI, degree)
        p = roi_pixels()
        phi = basis.values(p)
        assert phi.shape == (len(p), n)
        assert basis.size == coefficient_count(degree) == n  # the count the warm-up sizes a persisted ρ* by
        x, y = basis.coordinates(p)
        moments = np.c_[np.ones(len(p)), x, y].T @ phi / len(p)
        np.testing.assert_allclose(moments, 0.0, atol=1e-10)
        np.testing.assert_allclose(phi.T @ phi / len(p), np.eye(n), atol=1e-10)


def track_trajectory(render_frame: Callable[[np.ndarray], np.ndarray], config: GeneralConfig | None = None):
    """The paper's trajectory tracked from a cold start on frames `render_frame(T_world_cam)`
    (`benchmarks.general_accuracy.measure`: no ρ* prior, G from the global initialiser, every 2nd image of the first
    20 and every 10th to convergence of the exact-geometry decoupled run): (images, worst warp RMS error over the
    ROI (px), per image the error of the control error (16) from the estimate relative to the criterion's tolerance
    max(1 % of its norm, 1e-4), the tracker, the last result). Every frame must converge."""
    run = measure(render_frame, config or MEASURED)
    failed = [row["image"] for row in run.rows if not row["converged"]]
    assert not failed, f"frames {failed} did not converge"
    return ([row["image"] for row in run.rows], max(row["warp_px"] for row in run.rows),
            [row["relative"] for row in run.rows], run.tracker, run.last)


@pytest.mark.slow
def test_paper_trajectory_from_a_cold_start() -> None:
    """Point-sampled frames (`render_view`) along the paper's trajectory (`track_trajectory`), Keys interpolation:
    the estimated warp is within 0.1 px RMS of the true warp over the ROI, and the control error (16) from the
    estimate matches the ground-truth one to 1 % of its norm or 1e-4 absolute on the first part (see the
    assertion's comment; with the default B-spline these aliased frames give 1.05× there and 8.7× overall)."""
    saddle = paper_saddle()
    frames, worst_rms, worst_err, tracker, result = track_trajectory(lambda T: render(saddle, T),
                                                                      MEASURED.replaced(interpolation="keys"))
    assert worst_rms < 0.1
    assert FLAG_NO_PARALLAX not in result.flags
    # Met (≤ 1) over images 0–180 (|ε̄| from 1.7 down to ~0.05; measured ≤ 0.76). NOT met nearer the equilibrium:
    # up to 13× the tolerance (image 390, 1.3e-3 absolute) and 3–5× on the last images (3–5e-4 absolute); the
    # bound below only guards against regressions of that gap. Diagnosis (benchmarks/general_accuracy.py): the
    # cost is lower at the estimate than at the true warp, so the optimum itself is off, by the residual of the
    # interpolated current image at the true warp (2.6–5 grey levels RMS near the equilibrium, for sub-pixel
    # motions): these frames point-sample a texture of ~1.6 texels per pixel, and that aliasing, which no
    # interpolator of the frame undoes, moves the warp by 0.01–0.02 px, mostly in G's perspective terms, which
    # (16) amplifies (the tolerance asks ~0.002 px there). Not the cause: the ρ* model (a geometric fit of G, e
    # with the estimated ρ* to the true warp gives ≤ 0.4×), the robust loss, the gradient (ESM or current only),
    # the stopping tolerance (1e-5 px changes nothing). Pixel-area integration alone (4×4 rays) gives 10×;
    # camera frames and B-spline interpolation: `test_camera_frames_near_the_equilibrium`.
    early = [err for k, err in zip(frames, worst_err) if k <= 180]
    assert max(early) <= 1.0, worst_err
    assert max(worst_err) <= 15.0, worst_err
    assert np.all(np.linalg.eigvalsh(tracker.rho_information) > 0.0)


@pytest.mark.slow
def test_camera_frames_near_the_equilibrium() -> None:
    """Frames as a camera forms them (`render_camera`: 0.7 px Gaussian optical blur, each pixel integrating its
    area with 4×4 rays; the band-limiting a real lens and sensor apply, which the point-sampled frames of the test
    above lack) along the same trajectory, registered with cubic B-spline interpolation: the control error (16)
    from the estimate matches the ground-truth one to 1e-4 absolute near the equilibrium (images ≥ 380, |ε̄| ≤ 5.2e-3;
    measured ≤ 0.86× the tolerance, against 4.3× with Keys interpolation of the same frames and 13× on point-sampled
    frames), and the warp is within 0.1 px of the truth throughout.

    NOT met in between (images 180–370: up to 1.8× the tolerance, 2.5e-4 absolute; 1.2× already on images ≤ 180):
    the blur costs accuracy on ρ*, estimated once on the first image (62° of rotation from the reference): tracking
    these same frames with the ρ* estimated on the first *point-sampled* image gives ≤ 0.93× over the whole
    trajectory. Refining ρ* over the frames does not close it (an information filter on ρ*, joint Gauss-Newton
    with the accumulated information as prior, measured 1.30× / 1.86×): every frame's data carry the same bias,
    because the optical blur is the same in each *image* and so differs between two frames by the warp's local
    distortion, which varies with the parallax. ρ* shape error (`benchmarks/general_accuracy.py`): 0.64 % here,
    1.02 % at 1.2 px, 0.26 % point-sampled, 0.23 % with the blur carried by the texture instead
    (`test_surface_blur_meets_the_criterion`). The bound below guards that gap against regressions."""
    saddle = paper_saddle()
    frames, worst_rms, errors, _, result = track_trajectory(
        lambda T: render_camera(saddle, texture(), INTR, T, psf_sigma=0.7), MEASURED.replaced(interpolation="bspline"))
    assert worst_rms < 0.1
    assert FLAG_NO_PARALLAX not in result.flags
    assert max(err for k, err in zip(frames, errors) if k >= 380) <= 1.0, errors
    assert max(errors) <= 2.5, errors


@pytest.mark.slow
def test_surface_blur_meets_the_criterion() -> None:
    """The same blur as a texture property (texture blurred by a Gaussian of 2 texels, about 1.25 px; frames
    integrated over each pixel's area with 4×4 rays, no optical blur), so that it warps with the scene and the
    frames differ by the motion alone: with B-spline interpolation the control error (16) from the estimate meets
    the criterion along the whole trajectory (measured ≤ 0.80×). With the blur in the image (`render_camera`'s
    optical blur, the test above) it does not: what is left there is that blur's mismatch between frames."""
    saddle = paper_saddle()
    blurred = cv2.GaussianBlur(texture(), (0, 0), 2.0)
    _, worst_rms, errors, _, result = track_trajectory(
        lambda T: render_camera(saddle, blurred, INTR, T, psf_sigma=0.0), MEASURED.replaced(interpolation="bspline"))
    assert worst_rms < 0.1
    assert FLAG_NO_PARALLAX not in result.flags
    assert max(errors) <= 1.0, errors


@pytest.mark.slow
def test_oblique_plane_gives_zero_parallax() -> None:
    """A plane tilted by ~26° seen after a displacement with translation: the parallax estimated with ρ* free stays
    below 0.05 px RMS over the ROI, ρ* is reported unobserved (set to 0) and the warp is within 0.1 px."""
    plane = Plane(pose(so3_exp([np.pi + 0.4, 0.3, 0.0]), [0.0, 0.05, 0.9]), (1.0, 1.0))
    T = pose(so3_exp([-0.03, -0.1, 0.35]), [0.06, -0.04, 0.02])
    gt = ground_truth(plane, INTR, np.eye(4), T)
    result = register_general(render(plane, np.eye(4)), render(plane, T), ROI, G0=gt.G)
    assert result.converged, result.reason
    assert result.parallax_px < 0.05
    assert FLAG_NO_PARALLAX in result.flags
    assert result.rho_at(CONTROL_POINT) == 0.0
    assert warp_rms(result, plane, T) < 0.1


@pytest.mark.slow
def test_failure_modes_are_reported() -> None:
    """Pure rotation (no translation): ρ* unobserved; a textureless target: not converged, never NaN; half of the
    ROI occluded by a foreign patch: reported."""
    saddle = paper_saddle()
    reference = render(saddle, np.eye(4))
    T_rot = pose(so3_exp([0.02, -0.05, 0.2]), [0.0, 0.0, 0.0])
    G_rot = ground_truth(saddle, INTR, np.eye(4), T_rot).G
    rotation = register_general(reference, render(saddle, T_rot), ROI, G0=G_rot)
    assert FLAG_NO_PARALLAX in rotation.flags and rotation.parallax_px < 0.05

    flat = np.full_like(reference, 128.0)
    textureless = register_general(flat, flat, ROI, G0=np.eye(3))
    assert not textureless.converged and textureless.flags and np.all(np.isfinite(textureless.G))

    T = pose(so3_exp([-0.03, -0.1, 0.35]), [0.06, -0.04, 0.0])
    occluded = render(saddle, T)
    x, y, w, h = ROI
    patch = np.random.default_rng(1).uniform(0, 255, (h + 60, w // 2 + 70))
    occluded[y - 30 : y + h + 30, x - 30 : x + w // 2 + 40] = patch
    result = register_general(reference, occluded, ROI, G0=ground_truth(saddle, INTR, np.eye(4), T).G)
    assert FLAG_OCCLUSION in result.flags or not result.converged


@pytest.mark.slow
def test_rho_survives_standstill_and_lost_target() -> None:
    """ρ* is kept while the camera does not translate (e → 0) and through LOST and re-acquisition (the tracking
    session's: from the last good estimate first, then by the global initialiser)."""
    saddle = paper_saddle()
    reference = render(saddle, np.eye(4))
    engine = GeneralRegistration.prepare(reference, ROI, config=MEASURED)
    tracker = GeneralTracker(engine)
    session = TrackingSession(tracker, Reacquisition(engine.planar, engine, GlobalInitConfig()))
    T = pose(so3_exp([-0.05, -0.15, 0.5]), [0.08, -0.05, 0.0])
    first = session.estimate(render(saddle, T), CONTROL_POINT)
    assert first.tracked, first.message
    rho = tracker.rho_coeffs
    assert rho is not None and np.any(rho != 0.0)
    for s in (0.6, 0.3, 0.1):  # back to the reference pose in steps a warm start follows
        assert tracker.track(render(saddle, pose(so3_exp(s * np.array([-0.05, -0.15, 0.5])), s * T[:3, 3]))).converged
    for _ in range(3):  # at the reference pose: no translation
        still = tracker.track(reference)
        assert still.converged
        assert np.linalg.norm(still.e) < 0.01 * np.linalg.norm(first.e)
    np.testing.assert_array_equal(tracker.rho_coeffs, rho)
    noise = np.random.default_rng(0).uniform(0, 255, reference.shape).astype(np.float32)
    for _ in range(2):
        assert not session.estimate(noise, CONTROL_POINT).tracked
    back = session.estimate(render(saddle, T), CONTROL_POINT)
    assert back.tracked, back.message
    np.testing.assert_array_equal(tracker.rho_coeffs, rho)
    warp = warp_points(back.G, back.e, tracker.basis, rho, roi_pixels())
    assert np.sqrt(np.mean(np.sum((warp - true_warp(saddle, T)) ** 2, axis=1))) < 0.1


@pytest.mark.slow
def test_closed_loop_on_rendered_images_follows_the_exact_loop() -> None:
    """The first 30 images of the paper's decoupled loop closed on rendered frames by the general tracker (global
    initialisation and ρ* estimated on the first frame, no ground truth in the loop): never lost, and the camera
    follows the exact-geometry loop's path to within 2 mm and 0.2°. The full runs (both laws to convergence) are
    too long for CI: `ddvs experiment synthetic --law {dvs,ddvs} --geometry estimated` (figures in the report)."""
    setup = replace(SyntheticSetup(), max_images=30)
    estimated = run_synthetic("ddvs", setup, "estimated")
    exact = run_synthetic("ddvs", setup)
    assert estimated.images == exact.images == 30, estimated.stopped
    assert np.max(np.linalg.norm(estimated.positions - exact.positions, axis=1)) < 2e-3
    dR = np.einsum("kji,kjl->kil", estimated.rotations, exact.rotations)
    angles = np.degrees(np.arccos(np.clip((np.trace(dR, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert np.max(angles) < 0.2
    np.testing.assert_allclose(estimated.error_norms, exact.error_norms, rtol=0.01)


@pytest.mark.slow
@pytest.mark.parametrize("interpolation", ["keys", "bspline"])
def test_register_cli_general_model(tmp_path, capsys, interpolation) -> None:
    """`ddvs register --model general [--interpolation ...]` on two PNG files of the saddle: one JSON line with the
    epipole and the parallax field, converged, warp within 0.1 px of the truth over the ROI."""
    saddle = paper_saddle()
    T = pose(so3_exp([-0.03, -0.1, 0.35]), [0.06, -0.04, 0.02])
    paths = [str(tmp_path / name) for name in ("ref.png", "cur.png", "G0.txt")]
    for path, image in zip(paths, (render(saddle, np.eye(4)), render(saddle, T))):
        cv2.imwrite(path, np.clip(np.rint(image), 0, 255).astype(np.uint8))
    np.savetxt(paths[2], ground_truth(saddle, INTR, np.eye(4), T).G)
    rc = main(["register", paths[0], paths[1], "--roi", *map(str, ROI), "--init", paths[2], "--model", "general",
               "--interpolation", interpolation])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])  # after Taichi's banner
    assert rc == 0 and out["converged"], out["reason"]
    assert FLAG_NO_PARALLAX not in out["flags"] and out["parallax_px"] > 0.1 and out["rho_degree"] == 2
    basis = ParallaxBasis.over(ROI, 2)
    estimated = warp_points(np.array(out["G"]), np.array(out["e"]), basis, np.array(out["rho_coeffs"]), roi_pixels())
    assert np.sqrt(np.mean(np.sum((estimated - true_warp(saddle, T)) ** 2, axis=1))) < 0.1


def test_register_general_refuses_bad_input() -> None:
    image = np.zeros((418, 550), dtype=np.float32)
    with pytest.raises(ValueError, match="coefficients"):
        register_general(image, image, ROI, G0=np.eye(3), rho0=np.zeros(4))
    with pytest.raises(ValueError, match="G0 is required"):
        register_general(image, image, ROI, rho0=np.zeros(6))
    with pytest.raises(ValueError, match="rho_degree"):
        GeneralConfig(rho_degree=5)
    with pytest.raises(ValueError, match="interpolation"):
        GeneralConfig(interpolation="lanczos")
    with pytest.raises(ValueError, match="not inside"):
        GeneralRegistration.prepare(image, (500, 400, 200, 150))


@pytest.mark.parametrize(("seed", "size", "trial"), [(0, 4.0, 5), (0, 4.0, 6), (0, 4.0, 9), (1, 5.0, 4)])
def test_first_frame_of_a_large_saddle_view_registers(seed: int, size: float, trial: int) -> None:
    """The domain sweep's 0.2 m / 60° starts with the whole ROI patch in view: the best homography leaves a
    parallax residual that keeps the planar stage's finest level from converging, yet it brings the general stage
    into its basin — the first frame registers, at the true warp (it used to fail: "planar stage failed"). Seed 1's
    0.25 m / 75° trial 4: the general stage's finest level converges slowly (a step about a fifth smaller each
    iteration) and ends `max_iterations` with about 1e-3 px still to come: converged, slowly (it used to fail, or
    not, with the float rounding of the kernels' sums)."""
    from ddvs_service.service.config import RegistrationSettings
    from orchestration.experiment_domain import ROI as DOMAIN_ROI
    from orchestration.experiment_domain import DomainSettings, make_surface, trial_start

    assert DOMAIN_ROI == ROI
    saddle = make_surface("saddle")
    T, _, _ = trial_start(DomainSettings(seed=seed), size, trial)
    engine = GeneralRegistration.prepare(render(saddle, np.eye(4)), ROI,
                                         config=RegistrationSettings(levels=3).general_config())
    current = render(saddle, T)
    start = Reacquisition(engine.planar, engine, GlobalInitConfig())(current)
    assert start.G is not None, start.reason
    result = engine.estimate(current, start.G)
    assert result.converged, result.reason
    assert warp_rms(result, saddle, T) < 0.5


@pytest.mark.slow
def test_held_epipole_near_the_goal_and_freed_away_from_it() -> None:
    """`hold_epipole_px`: tracked from `e` = 0 (a resumed tracker's start), a frame 2 mm from the reference pose holds
    `e` at 0 when its noise (Gaussian, 10 grey levels) hides the parallax, and frees it when it is clean (its step
    on `e` is significant), as `e` is estimated with 0 (never held); a frame 95 mm away, from the same start, sees
    its epipole and frees it. Every freed frame's warp is within 0.1 px of the truth, as never held."""
    saddle = paper_saddle()
    reference = render(saddle, np.eye(4))
    T_far = pose(so3_exp([-0.05, -0.15, 0.5]), [0.08, -0.05, 0.0])
    rho = register_general(reference, render(saddle, T_far), ROI,
                           G0=ground_truth(saddle, INTR, np.eye(4), T_far).G).rho_coeffs
    assert np.any(rho != 0.0)
    T_near = pose(so3_exp([0.001, -0.001, 0.0005]), [0.002, -0.001, 0.001])
    never, held = (GeneralRegistration.prepare(reference, ROI, config=MEASURED.replaced(hold_epipole_px=px))
                   for px in (0.0, 0.05))
    noise = np.random.default_rng(0).normal(0.0, 10.0, reference.shape).astype(np.float32)
    for T, noisy, expect_held in ((T_near, True, True), (T_near, False, False), (T_far, False, False)):
        G0 = ground_truth(saddle, INTR, np.eye(4), T).G
        current = render(saddle, T) + (noise if noisy else 0.0)
        always_free = never.track(current, G0, np.zeros(3), rho)
        result = held.track(current, G0, np.zeros(3), rho)
        assert always_free.converged and result.converged, (always_free.reason, result.reason)
        assert np.any(always_free.e != 0.0)
        assert np.all(result.e == 0.0) == expect_held, (T, noisy, result.e)
        if not expect_held:
            assert warp_rms(result, saddle, T) < 0.1
            assert warp_rms(always_free, saddle, T) < 0.1


@pytest.mark.slow
def test_an_epipole_every_frame_sees_is_freed_by_the_tracker() -> None:
    """`GeneralTracker` and the held epipole: a clean frame 1.2 mm from the reference pose whose parallax is too faint
    to free `e` on one frame (its statistic between `FREE_EPIPOLE_MEAN_WALD` and `FREE_EPIPOLE_WALD`), seen again
    frame after frame, frees it once `EPIPOLE_EVIDENCE_FRAMES` frames agree; the same frame under fresh noise (10 grey
    levels) each time keeps it held."""
    saddle = paper_saddle()
    reference = render(saddle, np.eye(4))
    T_far = pose(so3_exp([-0.05, -0.15, 0.5]), [0.08, -0.05, 0.0])
    rho = register_general(reference, render(saddle, T_far), ROI,
                           G0=ground_truth(saddle, INTR, np.eye(4), T_far).G).rho_coeffs
    T = pose(so3_exp([0.0006, -0.0006, 0.0003]), [0.0012, -0.0006, 0.0006])
    G0 = ground_truth(saddle, INTR, np.eye(4), T).G
    engine = GeneralRegistration.prepare(reference, ROI, config=MEASURED.replaced(hold_epipole_px=0.05))
    clean = render(saddle, T)
    rng = np.random.default_rng(0)
    for noisy in (False, True):
        tracker = GeneralTracker(engine, rho=rho, G=G0)
        results = [tracker.track(clean + (rng.normal(0.0, 10.0, clean.shape).astype(np.float32) if noisy else 0.0))
                   for _ in range(EPIPOLE_EVIDENCE_FRAMES + 2)]
        assert all(r.converged for r in results), [r.reason for r in results]
        held = [bool(np.all(r.e == 0.0)) for r in results]
        if noisy:
            assert all(held), [r.epipole_wald for r in results]
        else:
            assert all(FREE_EPIPOLE_MEAN_WALD <= r.epipole_wald < FREE_EPIPOLE_WALD for r in results[:-2])
            assert held == [True] * EPIPOLE_EVIDENCE_FRAMES + [False] * 2, [r.epipole_wald for r in results]
            assert warp_rms(results[-1], saddle, T) <= warp_rms(results[0], saddle, T)
