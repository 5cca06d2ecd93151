"""One re-acquisition path for both models (`registration.reacquisition`), on the tracker's own prepared reference;
in the service, beside the servo loop (`service.reacquirer`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ddvs_service.camera import Intrinsics
from ddvs_service.lie import so3_exp
from ddvs_service.registration.general import GeneralRegistration
from ddvs_service.registration.general_tracker import GeneralTracker
from ddvs_service.registration.global_init import GlobalInitConfig, PlanarRefiner
from ddvs_service.registration.planar import PlanarRegistration
from ddvs_service.registration.reacquisition import Reacquisition
from ddvs_service.registration.session import TrackingSession
from ddvs_service.registration.warp_distance import warp_rms
from ddvs_service.service.config import ServiceConfig
from ddvs_service.service.pipeline import ServoPipeline
from ddvs_service.service.reacquirer import BackgroundReacquisition
from ddvs_service.service.state import ServoState
from kernels.exclusive import GATE
from sim.planar_scene import POSTER_BLUR_SIGMA, PlanarScene
from sim.textures import TEXTURES, load_texture

CAM = Intrinsics.centred(420.0, 320, 240)
ROI = (125, 85, 70, 70)  # 70×70 template centred on the control point (image centre)
CENTRE = (159.5, 119.5)


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


def test_general_session_reacquires_only_when_asked(scene: PlanarScene) -> None:
    """Re-acquisition on: a 60° rotation is found on the first frame. Off: the tracker starts from its last good
    estimate (identity on the first frame), which a 60° rotation is out of reach of."""
    H = rotated(scene, 60.0)
    current = scene.render(H)
    engine = GeneralRegistration.prepare(scene.render(), ROI)
    on = TrackingSession(GeneralTracker(engine), Reacquisition(engine.planar, engine, GlobalInitConfig()))
    found = on.estimate(current, CENTRE)
    assert found.tracked, found.message
    assert warp_rms(found.G, H, ROI) < 0.1
    off = TrackingSession(GeneralTracker(engine), Reacquisition(engine.planar, engine, config=None))
    missed = off.estimate(current, CENTRE)
    assert not (missed.tracked and warp_rms(missed.G, H, ROI) < 1.0)


@pytest.mark.parametrize("model", ["planar", "general"])
def test_service_global_init_setting_is_honoured_by_both_models(scene: PlanarScene, model: str) -> None:
    from ddvs_service.service.config import RegistrationSettings
    from ddvs_service.service.estimators import tracking_session

    H = rotated(scene, 60.0)
    reference, current = scene.render(), scene.render(H)
    on = tracking_session(reference, ROI, RegistrationSettings(model=model)).estimate(current, CENTRE)  # type: ignore[arg-type]
    assert on.tracked, on.message
    assert warp_rms(on.G, H, ROI) < 0.1
    settings = RegistrationSettings(model=model, global_init=False)  # type: ignore[arg-type]
    off = tracking_session(reference, ROI, settings).estimate(current, CENTRE)
    assert not (off.tracked and warp_rms(off.G, H, ROI) < 1.0)


def servo_pipeline(roi: tuple[int, int, int, int] = ROI, background: bool = True) -> ServoPipeline:
    """The service's per-frame code with the shipped configuration on the test camera."""
    shipped = Path(__file__).resolve().parents[1] / "configs" / "serve" / "ur5_poster.json"
    config = ServiceConfig.from_file(shipped).merged({
        "intrinsics": {"fx": CAM.fx, "fy": CAM.fy, "cx": CAM.cx, "cy": CAM.cy, "width": CAM.width,
                       "height": CAM.height},
        "registration": {"roi": list(roi)}})
    return ServoPipeline(config, CAM, background_reacquisition=background)


def test_lost_frames_are_answered_while_the_worker_searches_then_servoing_resumes(scene: PlanarScene) -> None:
    """The view turns 40° (beyond the tracker's reach): every frame is answered LOST with a zero twist while the
    worker searches — here held off the Taichi gate by this thread, so the count does not depend on timing — then
    the worker's pose is adopted only once the tracker registers a newer frame from it, and the servo moves again
    only after the error guard saw the jumped error agree for `rebase_frames` frames."""
    servo = servo_pipeline()
    reference = np.clip(np.rint(scene.render()), 0, 255).astype(np.uint8)
    servo.set_reference(reference, ROI, G0=np.eye(3))
    servo.machine.start()
    for _ in range(3):
        assert servo.step(reference).state in (ServoState.SERVOING, ServoState.CONVERGED)
    worker = servo.reacquisition
    assert isinstance(worker, BackgroundReacquisition)
    H = rotated(scene, 40.0)
    moved = np.clip(np.rint(scene.render(H)), 0, 255).astype(np.uint8)
    try:
        step = servo.step(moved)  # the tracker fails: LOST; the next frame needs re-acquisition
        assert step.state == ServoState.LOST and not np.any(step.twist), step
        with GATE.hold():  # the worker cannot search: it waits at the gate with the newest frame
            for k in range(10):
                step = servo.step(moved)
                assert step.state == ServoState.LOST and not np.any(step.twist), step
                assert "searching in the background" in step.message, step.message
                assert worker.busy, k
        assert worker.searches == 0
        assert worker.wait_idle(300.0), "the worker did not finish its search"
        assert worker.busy  # its OK result waits: the next frame takes it without first tracking from the last good
        adopted_at, servoing_at = None, None
        for k in range(60):
            step = servo.step(moved)
            if adopted_at is None and step.message.startswith("global initialisation: ok"):
                adopted_at = k
                assert servo.G is not None and warp_rms(servo.G, H, ROI) < 0.1
            if step.state == ServoState.SERVOING:
                servoing_at = k
                break
            assert not np.any(step.twist), step
            worker.wait_idle(300.0)
        assert worker.searches >= 1 and adopted_at == 0
        assert servoing_at is not None and servoing_at - adopted_at >= servo.guard.rebase_frames - 1
        assert np.any(step.twist) and servo.G is not None and warp_rms(servo.G, H, ROI) < 0.1
    finally:
        servo.close()


def test_a_tracked_frame_after_a_lost_one_needs_no_search(scene: PlanarScene) -> None:
    """The target is hidden for a frame (an unrelated image: LOST) and comes back where it was: the loop hands that
    frame to the worker at once, with no registration of its own (the first frame back is answered untracked), the
    worker registers it from the last good estimate before any global search, and the next frame is re-acquired by
    tracking from the last good estimate, with the initialiser's pose count unchanged."""
    servo = servo_pipeline()
    reference = np.clip(np.rint(scene.render()), 0, 255).astype(np.uint8)
    servo.set_reference(reference, ROI, G0=np.eye(3))
    servo.machine.start()
    servo.step(reference)
    H = scene.homography(np.eye(3), np.array([0.002, 0.0, 0.0]))
    near = np.clip(np.rint(scene.render(H)), 0, 255).astype(np.uint8)
    hidden = np.random.default_rng(0).integers(0, 256, reference.shape, dtype=np.uint8)
    try:
        assert servo.step(hidden).state == ServoState.LOST
        worker = servo.reacquisition
        assert worker is not None
        assert isinstance(worker, BackgroundReacquisition)
        step = servo.step(near)  # the worker searches from the last good estimate first
        assert step.state == ServoState.LOST and step.message == "global initialisation: LOST (searching in the " \
            "background)", step.message
        assert step.iterations == 0
        assert worker.wait_idle(300.0)
        step = servo.step(near)
        assert step.message.startswith("re-acquired by tracking from the last good estimate"), step.message
        assert servo.G is not None and warp_rms(servo.G, H, ROI) < 0.05
        assert not worker.busy and worker.adopted == 0
    finally:
        servo.close()


def test_general_session_reacquires_from_the_last_good_estimate_under_an_occluder(scene: PlanarScene) -> None:
    """The general model LOST (textureless frames), then the view comes back with 30 % of the template covered by a
    foreign object, where the global initialiser's cost is above its threshold: the first frame is tracked from the
    last good estimate (`registration.session`), within 1 px RMS of the unoccluded view's estimate (the occluder
    biases the general model's fit by about half a pixel here)."""
    from ddvs_service.service.config import RegistrationSettings
    from ddvs_service.service.estimators import tracking_session
    from sim.conditions import FrameContext, Occluder, apply

    estimator = tracking_session(scene.render(), ROI, RegistrationSettings(model="general"))
    view = scene.render(scene.homography(so3_exp(np.radians([0.0, 0.0, 2.0])), np.array([0.005, 0.0, 0.0])))
    clean = estimator.estimate(view, CENTRE)
    assert clean.tracked, clean.message
    for _ in range(5):
        assert not estimator.estimate(np.full_like(view, 128.0), CENTRE).tracked
    occluded = apply((Occluder(fraction=0.3, start_frame=0, enter_frames=1),), view, FrameContext(5, 0.2, ROI))
    found = estimator.estimate(occluded, CENTRE)
    assert found.tracked and found.message == "re-acquired by tracking from the last good estimate", found.message
    assert warp_rms(found.G, clean.G, ROI) < 1.0  # the same optimum, biased by the occluder (a wrong one: pixels)


@pytest.mark.parametrize("model", ["planar", "general"])
def test_the_worker_reacquires_from_the_last_good_estimate_under_an_occluder(scene: PlanarScene, model: str) -> None:
    """With the search on the worker, the attempt from the last good estimate is the worker's too: after LOST
    (textureless frames) the view comes back with 30 % of the template covered, the frame is answered at once with
    no registration of its own, the worker registers it from the last good estimate (the global initialiser's cost
    is above its threshold under such an occluder), and the next frame is tracked from there, near the unoccluded
    view's estimate (1 px RMS: the occluder biases the general model's fit by about half a pixel)."""
    from ddvs_service.service.config import RegistrationSettings
    from ddvs_service.service.estimators import tracking_session
    from sim.conditions import FrameContext, Occluder, apply

    settings = RegistrationSettings(model=model)  # type: ignore[arg-type]
    estimator = tracking_session(scene.render(), ROI, settings, background=True)
    estimator.assume(np.eye(3))
    worker = estimator.acquisition
    assert isinstance(worker, BackgroundReacquisition)
    try:
        view = scene.render(scene.homography(so3_exp(np.radians([0.0, 0.0, 2.0])), np.array([0.005, 0.0, 0.0])))
        clean = estimator.estimate(view, CENTRE)
        assert clean.tracked, clean.message
        adopted = worker.adopted
        for _ in range(5):
            assert not estimator.estimate(np.full_like(view, 128.0), CENTRE).tracked
            assert worker.wait_idle(300.0)
        occluded = apply((Occluder(fraction=0.3, start_frame=0, enter_frames=1),), view, FrameContext(5, 0.2, ROI))
        handed = estimator.estimate(occluded, CENTRE)
        assert not handed.tracked and handed.iterations == 0, handed.message
        assert worker.busy  # its search of this frame runs, or its OK answer waits
        assert worker.wait_idle(300.0)
        found = estimator.estimate(occluded, CENTRE)
        assert found.tracked and found.message == "re-acquired by tracking from the last good estimate", found.message
        assert warp_rms(found.G, clean.G, ROI) < 1.0
        assert worker.adopted == adopted  # no pose of the global initialiser's since
    finally:
        estimator.close()
