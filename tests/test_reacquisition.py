"""One re-acquisition path for both models (`registration.reacquisition`), on the tracker's own prepared reference."""

from __future__ import annotations

import numpy as np
import pytest

from ddvs_service.camera import Intrinsics
from ddvs_service.lie import so3_exp
from ddvs_service.registration.general import GeneralRegistration
from ddvs_service.registration.general_tracker import GeneralTracker
from ddvs_service.registration.global_init import GlobalInitConfig, PlanarRefiner
from ddvs_service.registration.planar import PlanarRegistration
from ddvs_service.registration.reacquisition import Reacquisition
from ddvs_service.registration.warp_distance import warp_rms
from sim.planar_scene import POSTER_BLUR_SIGMA, PlanarScene
from sim.textures import TEXTURES, load_texture

CAM = Intrinsics.centred(420.0, 320, 240)
ROI = (125, 85, 70, 70)  # 70×70 template centred on the control point (image centre)


@pytest.fixture(scope="module")
def scene() -> PlanarScene:
    return PlanarScene(CAM, load_texture(TEXTURES[1], POSTER_BLUR_SIGMA))


def rotated(scene: PlanarScene, degrees: float) -> np.ndarray:
    """The homography of the poster seen after a rotation about the optical axis and a small lateral shift."""
    return scene.homography(so3_exp(np.radians([0.0, 0.0, degrees])), np.array([0.05, 0.0, 0.0]))


def test_refines_on_the_trackers_prepared_reference(scene: PlanarScene) -> None:
    engine = PlanarRegistration.prepare(scene.render(), ROI)
    acquire = Reacquisition(engine, config=GlobalInitConfig())
    H = rotated(scene, 40.0)
    found = acquire(scene.render(H))
    assert found.status == "OK", found.reason
    assert found.G is not None and warp_rms(found.G, H, ROI) < 0.05
    assert acquire.initializer is not None
    refine = acquire.initializer.reference_side(engine.prepared.image, ROI).refine
    assert isinstance(refine, PlanarRefiner)
    assert refine.problem is engine  # no second pyramid of the same reference
    assert refine.rival_problem.prepared is engine.prepared and refine.rival_problem.current is engine.current


def test_off_reports_it_and_runs_no_initialiser(scene: PlanarScene) -> None:
    engine = PlanarRegistration.prepare(scene.render(), ROI)
    acquire = Reacquisition(engine, config=None)
    found = acquire(scene.render(rotated(scene, 40.0)))
    assert (found.status, found.G, found.found) == ("OFF", None, None)
    assert not acquire.enabled and acquire.initializer is None


def test_general_tracker_reacquires_only_when_asked(scene: PlanarScene) -> None:
    """Re-acquisition on (the default): a 60° rotation is found on the first frame. Off: the tracker starts from
    its last good estimate (identity on the first frame), which a 60° rotation is out of reach of."""
    H = rotated(scene, 60.0)
    current = scene.render(H)
    engine = GeneralRegistration.prepare(scene.render(), ROI)
    on = GeneralTracker(engine).track(current)
    assert on.converged, on.reason
    assert warp_rms(on.G, H, ROI) < 0.1
    off = GeneralTracker(engine, Reacquisition(engine.planar, engine, config=None)).track(current)
    assert not (off.converged and warp_rms(off.G, H, ROI) < 1.0)


@pytest.mark.parametrize("model", ["planar", "general"])
def test_service_global_init_setting_is_honoured_by_both_models(scene: PlanarScene, model: str) -> None:
    from ddvs_service.service.config import RegistrationSettings
    from ddvs_service.service.estimators import GeneralEstimator, PlanarEstimator

    H = rotated(scene, 60.0)
    reference, current = scene.render(), scene.render(H)
    estimator = GeneralEstimator if model == "general" else PlanarEstimator
    on = estimator(reference, ROI, RegistrationSettings(model=model)).estimate(current, (159.5, 119.5))
    assert on.tracked, on.message
    assert warp_rms(on.G, H, ROI) < 0.1
    off = estimator(reference, ROI, RegistrationSettings(model=model, global_init=False)).estimate(current,
                                                                                                 (159.5, 119.5))
    assert not (off.tracked and warp_rms(off.G, H, ROI) < 1.0)
