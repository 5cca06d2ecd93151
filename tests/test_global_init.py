"""Global initialisation (issue 9): Fourier–Mellin hypotheses, planar refinement, winner/margin and LOST."""

from __future__ import annotations

from typing import Literal

import numpy as np
import pytest

from ddvs_service.camera import Intrinsics
from ddvs_service.lie import pose, so3_exp
from ddvs_service.registration.global_fourier_mellin import (
    FourierMellinConfig,
    rotation_scale_candidates,
    similarity,
)
from ddvs_service.registration.global_init import GlobalInitConfig, GlobalInitializer, reacquire
from ddvs_service.registration.warp_distance import roi_grid, warp_rms
from kernels import backend
from sim.planar_scene import POSTER_BLUR_SIGMA, Displacement, PlanarScene
from sim.textures import TEXTURES, load_texture

CAM = Intrinsics.centred(420.0, 320, 240)
ROI = (125, 85, 70, 70)  # 70×70 template centred on the control point (image centre)
CENTRE = (159.5, 119.5)


@pytest.fixture(scope="module")
def scene() -> PlanarScene:
    return PlanarScene(CAM, load_texture(TEXTURES[1], POSTER_BLUR_SIGMA))


@pytest.fixture(scope="module")
def initializer() -> GlobalInitializer:
    return GlobalInitializer()


def test_log_polar_peaks_recover_rotation_and_scale(scene: PlanarScene) -> None:
    backend.init()
    ref = scene.render()
    theta, s = np.radians(35.0), 1.25
    G = similarity(theta, s, CENTRE, CENTRE)
    cur = scene.render(G / G[2, 2])
    found = rotation_scale_candidates(ref, cur, FourierMellinConfig())
    best_theta, best_s = found[0]
    assert abs(best_theta - theta % np.pi) < np.radians(1.5)
    assert abs(np.log(best_s / s)) < 0.03


def test_paper_planar_initial_pose_recovered_below_005_px(scene: PlanarScene, initializer: GlobalInitializer) -> None:
    """Paper, real planar experiment: poster at 0.7 m, f = 420 px, t = [0.13, −0.23, −0.08] m, r = [−20.3, 2.17,
    14.59]° (current camera in the reference frame) — 25° of rotation and the template ~70 px away."""
    H = scene.homography(so3_exp(np.radians([-20.3, 2.17, 14.59])), np.array([0.13, -0.23, -0.08]))
    result = initializer.initialize(scene.render(), ROI, scene.render(H))
    assert result.status == "OK", result.reason
    assert warp_rms(result.G, H, ROI) < 0.05
    assert result.margin >= initializer.config.min_margin


@pytest.mark.slow
def test_upside_down_scaled_and_shifted(scene: PlanarScene, initializer: GlobalInitializer) -> None:
    d = Displacement(roll=np.radians(170.0), tilt=np.radians(20.0), tilt_axis=1.0, scale=1.35, shift=(60.0, -30.0))
    H = scene.homography(*d.pose(scene, CENTRE))
    result = initializer.initialize(scene.render(), ROI, scene.render(H))
    assert result.status == "OK", result.reason
    assert warp_rms(result.G, H, ROI) < 0.05


def test_unrelated_image_is_lost(scene: PlanarScene, initializer: GlobalInitializer) -> None:
    other = PlanarScene(CAM, load_texture(TEXTURES[2], POSTER_BLUR_SIGMA))
    result = initializer.initialize(scene.render(), ROI, other.render())
    assert result.status == "LOST"
    assert result.G is None
    assert result.reason != "ok"


def test_tracker_contradiction_flag(scene: PlanarScene, initializer: GlobalInitializer) -> None:
    H = scene.homography(so3_exp(np.radians([0.0, 0.0, 40.0])), np.array([0.05, 0.0, 0.0]))
    cur = scene.render(H)
    shifted = np.array([[1.0, 0, 20.0], [0, 1.0, 0], [0, 0, 1.0]]) @ H
    wrong = shifted / np.cbrt(np.linalg.det(shifted))
    _, contradicts = reacquire(initializer, scene.render(), ROI, cur, tracking_G=wrong)
    assert contradicts
    _, agrees = reacquire(initializer, scene.render(), ROI, cur, tracking_G=H / np.cbrt(np.linalg.det(H)))
    assert not agrees


@pytest.mark.parametrize("source", ["orb", "sift"])
def test_feature_source_is_optional_and_selectable(scene: PlanarScene, source: Literal["orb", "sift"]) -> None:
    H = scene.homography(so3_exp(np.radians([5.0, 0.0, 90.0])), np.array([0.0, 0.05, 0.0]))
    with_features = GlobalInitializer(GlobalInitConfig(feature_source=source))
    hypotheses = with_features.hypotheses(scene.render(), ROI, scene.render(H))
    found = [h for h in hypotheses if h.source == source]
    assert len(found) == 1 and warp_rms(found[0].G, H, ROI) < 3.0
    assert any(h.source == "fourier-mellin" for h in hypotheses)


def test_bad_roi_is_explained(scene: PlanarScene, initializer: GlobalInitializer) -> None:
    with pytest.raises(ValueError, match="inside the reference image"):
        initializer.initialize(scene.render(), (300, 200, 70, 70), scene.render())


@pytest.mark.slow
def test_paper_saddle_initial_image_general_model_below_01_px() -> None:
    """The paper's synthetic initial image (saddle, f = 500 px, 550×418, 200×150 ROI on the control point; current
    camera at t = [0.17, −0.11, 0.01] m, r = [−0.1, −0.31, 1.04] rad in the reference frame): the global initialiser
    (planar) then the general model of eq. (2) recover the true warp `G p* + ρ*(p*) e` to < 0.1 px RMS."""
    from ddvs_service.registration.general_register import register_general
    from orchestration.experiment_synthetic import SyntheticSetup
    from sim.freeflyer import render_view
    from sim.ground_truth import ground_truth, parallax_map
    from sim.surfaces import paper_saddle

    setup = SyntheticSetup()
    cam = Intrinsics.centred(setup.f, setup.width, setup.height)
    roi = (175, 134, 200, 150)
    saddle = paper_saddle(setup.depth, setup.a)
    texture = load_texture(setup.texture, blur_sigma=0.0)
    T_cur = pose(so3_exp(setup.r), setup.t)
    ref = render_view(saddle, texture, cam, np.eye(4))[0]
    cur = render_view(saddle, texture, cam, T_cur)[0]
    result = register_general(ref, cur, roi)  # G0 from the global initialiser
    assert result.converged, result.reason
    truth = ground_truth(saddle, cam, np.eye(4), T_cur)
    p = roi_grid(roi)
    rho = parallax_map(saddle, cam, np.eye(4))[p[:, 1].astype(int), p[:, 0].astype(int)]
    q = np.c_[p, np.ones(len(p))] @ truth.G.T + np.outer(rho, truth.e)
    rms = float(np.sqrt(np.mean(np.sum((result.warp(p) - q[:, :2] / q[:, 2:]) ** 2, axis=1))))
    assert rms < 0.1, rms


@pytest.mark.slow
def test_oblique_saddle_rescued_by_general_model() -> None:
    """The paper's saddle seen 37.5° obliquely (a sweep trial, wall texture): the planar fit of the correct match keeps
    the parallax as residual (cost above max_cost: LOST with the planar refinement only); the general model of eq. (2)
    converges from it, and the initialiser answers OK with the true warp `G p* + ρ*(p*) e`."""
    from sim.freeflyer import render_view
    from sim.ground_truth import ground_truth, parallax_map
    from sim.surfaces import paper_saddle

    saddle = paper_saddle()
    raw = load_texture(TEXTURES[2], blur_sigma=0.0)
    texture = load_texture(TEXTURES[2], blur_sigma=0.5 * raw.shape[1] / (saddle.extent[0] * CAM.fx))
    d = Displacement(roll=np.radians(152.0), tilt=np.radians(37.5), tilt_axis=3.54, scale=0.85, shift=(83.5, -26.7))
    T_cur = pose(*d.pose(PlanarScene(CAM, texture, depth=1.0), CENTRE))
    ref = render_view(saddle, texture, CAM, np.eye(4))[0]
    cur = render_view(saddle, texture, CAM, T_cur)[0]
    planar_only = GlobalInitializer(GlobalInitConfig(general_max_cost=0.0)).initialize(ref, ROI, cur)
    assert planar_only.status == "LOST" and "cost" in planar_only.reason
    result = GlobalInitializer().initialize(ref, ROI, cur)
    assert result.status == "OK", result.reason
    assert result.winner is not None and result.winner.refinement.model == "general"
    truth = ground_truth(saddle, CAM, np.eye(4), T_cur)
    p = roi_grid(ROI)
    rho = parallax_map(saddle, CAM, np.eye(4))[p[:, 1].astype(int), p[:, 0].astype(int)]
    q = np.c_[p, np.ones(len(p))] @ truth.G.T + np.outer(rho, truth.e)
    rms = np.sqrt(np.mean(np.sum((result.winner.refinement.detail.warp(p) - q[:, :2] / q[:, 2:]) ** 2, axis=1)))
    assert rms < 0.1, rms


def test_register_cli_init_global(scene: PlanarScene, tmp_path, capsys) -> None:
    """`ddvs register REF CUR --roi … --init global`: the global initialiser starts the planar registration from a
    half-turn away; an unrelated current image exits with status 1 and the initialiser's LOST reason."""
    import argparse
    import json

    import cv2

    from ddvs_service import register_cli

    H = scene.homography(so3_exp(np.radians([5.0, -5.0, 120.0])), np.array([0.03, -0.02, 0.05]))
    files = {}
    for name, image in (("ref", scene.render()), ("cur", scene.render(H)),
                        ("other", PlanarScene(CAM, load_texture(TEXTURES[2], POSTER_BLUR_SIGMA)).render())):
        files[name] = str(tmp_path / f"{name}.png")
        cv2.imwrite(files[name], np.clip(np.round(image), 0, 255).astype(np.uint8))
    parser = argparse.ArgumentParser()
    register_cli.add_arguments(parser)
    roi = [str(v) for v in ROI]
    assert register_cli.run(parser.parse_args([files["ref"], files["cur"], "--roi", *roi, "--init", "global"])) == 0
    out = json.loads(capsys.readouterr().out.splitlines()[-1])  # the last line (Taichi may print a banner first)
    assert out["global_init"]["status"] == "OK" and out["converged"]
    assert warp_rms(np.array(out["H"]), H, ROI) < 0.3  # 8-bit images
    assert register_cli.run(parser.parse_args([files["ref"], files["other"], "--roi", *roi, "--init", "global"])) == 1
    lost = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert lost["global_init"]["status"] == "LOST" and not lost["converged"] and lost["reason"]


def test_a_large_occluder_does_not_make_a_wrong_warp_ok(scene: PlanarScene) -> None:
    """A foreign object over the left 35 % of the template inflates every solution's cost alike; a warp pushing the
    ROI partly off it ranked first at 12.6 px from the truth and was OK (step 6's check was added for it): it is
    LOST now, because the right solution fits the rest of the ROI better. Service engine (Tukey, 3×3 gains)."""
    import cv2

    from ddvs_service.registration.planar import PlanarRegistration
    from ddvs_service.service.config import RegistrationSettings

    reference = scene.render()
    settings = RegistrationSettings(template_size=(70, 70), levels=3, gain_grid=(3, 3), robust="tukey")
    engine = PlanarRegistration.prepare(reference, ROI, config=settings.engine_config())
    shown = Displacement(roll=1.2363320150008485, tilt=0.44021003326527797, tilt_axis=1.2199880136089372,
                         scale=1.0620555886182037, shift=(-2.3622855539970367, -15.603161807222348))
    H = scene.homography(*shown.pose(scene, CENTRE))
    current = scene.render(H)
    x, y, w, h = ROI
    q = H @ np.array([[x, x + w - 1, x + w - 1, x], [y, y, y + h - 1, y + h - 1], [1.0, 1.0, 1.0, 1.0]])
    u = q[0] / q[2]
    cut = round(u.min() + 0.35 * (u.max() - u.min()))
    foreign = cv2.resize(load_texture("boat"), (CAM.width, CAM.height), interpolation=cv2.INTER_AREA)
    current[:, :cut] = foreign[:, :cut]
    found = GlobalInitializer(engine=engine).initialize(reference, ROI, current)
    assert found.status == "LOST" and "partial occlusion" in found.reason, (found.status, found.reason)
    assert found.winner is not None and warp_rms(found.winner.refinement.G, H, ROI) > 5.0  # the wrong warp
    unchecked = GlobalInitializer(GlobalInitConfig(trimmed_tolerance=1.0), engine=engine)
    assert unchecked.initialize(reference, ROI, current).status == "OK"  # what happened without the check


def test_photometric_scores_in_chunks_equal_each_alone(scene: PlanarScene) -> None:
    """`photometric_scores` scores a stack `SCORE_CHUNK` values at a time (a frame waiting for the Taichi gate goes
    first between chunks): a stack spanning several chunks, some samplings partly outside the image, scores exactly
    as each sampling alone."""
    from ddvs_service.registration.global_cost import SCORE_CHUNK, photometric_score, photometric_scores, sample_through

    backend.init()
    image = scene.render()
    x, y, w, h = 60, 45, 200, 150
    Gs = np.stack([similarity(np.radians(10.0 * k), 1.0 + 0.05 * k, (159.5, 119.5), (159.5 + 15 * k, 119.5))
                   for k in range(7)])
    sampled, valid = sample_through(image, Gs, (h, w), (x, y))
    assert len(sampled) > SCORE_CHUNK // (w * h) and valid.min() == 0.0  # several chunks; pixels out of view
    template = image[y : y + h, x : x + w]
    assert photometric_scores(template, sampled, valid) == [photometric_score(template, s, v)
                                                            for s, v in zip(sampled, valid, strict=True)]


def _domain_start(target: str, size: float, trial: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference, first frame and true planar-part `G` of a convergence-domain trial (seed 0, finite scene)."""
    from orchestration.experiment_domain import CAMERA, DomainSettings, make_surface, trial_start
    from orchestration.experiment_synthetic import TEXTURE
    from sim.freeflyer import render_view
    from sim.ground_truth import ground_truth

    surface, texture = make_surface(target), load_texture(TEXTURE)
    T, _, _ = trial_start(DomainSettings(), size, trial)
    return (render_view(surface, texture, CAMERA, np.eye(4))[0], render_view(surface, texture, CAMERA, T)[0],
            ground_truth(surface, CAMERA, np.eye(4), T).G)


@pytest.mark.slow
def test_a_view_magnified_beyond_the_peaks_scale_range_is_found() -> None:
    """The domain's 0.4 m / 120° start (trial 3) sees the poster 1.75× larger with 78 % of the ROI patch in view:
    beyond the log-polar peaks' scale range, it was LOST (best cost 0.509). The grid's wider scale range starts it
    in the screening's basin: OK, at the truth."""
    from orchestration.experiment_domain import ROI as DOMAIN_ROI

    reference, current, G = _domain_start("planar", 8.0, 3)
    found = GlobalInitializer().initialize(reference, DOMAIN_ROI, current)
    assert found.status == "OK" and found.G is not None, found.reason
    assert warp_rms(found.G, G, DOMAIN_ROI) < 1.0


@pytest.mark.slow
def test_planar_fits_of_a_curved_target_that_differ_are_reconciled_by_the_general_model() -> None:
    """On the saddle seen 0.4 m / 120° away (trial 5), two planar fits of the curved patch farther apart than
    `distinct_px` both score as good solutions (margin 0.03 < 0.1: LOST as ambiguous); step 5 refines the winner with
    eq. (2), which removes the parallax the planar fits leave: OK, near the true plane-induced `G`."""
    from orchestration.experiment_domain import ROI as DOMAIN_ROI

    reference, current, G = _domain_start("saddle", 8.0, 5)
    found = GlobalInitializer().initialize(reference, DOMAIN_ROI, current)
    assert found.status == "OK" and found.G is not None and found.winner is not None, found.reason
    assert found.winner.refinement.model == "general"
    assert warp_rms(found.G, G, DOMAIN_ROI) < 3.0
