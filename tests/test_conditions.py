"""The imaging conditions of the robustness matrix (`sim.conditions`) and one short closed-loop run of it."""

from __future__ import annotations

import numpy as np
import pytest

from sim.conditions import Dimming, FrameContext, GainGradient, Jpeg, MotionBlur, Noise, Occluder, Specular, apply

ROI = (125, 85, 70, 70)


def ctx(index: int = 0, time: float = 0.0, motion=(0.0, 0.0)) -> FrameContext:
    return FrameContext(index, time, ROI, motion)


@pytest.fixture(scope="module")
def image() -> np.ndarray:
    rng = np.random.default_rng(1)
    import cv2

    return cv2.GaussianBlur(rng.uniform(40, 215, (240, 320)).astype(np.float32), (0, 0), 2.0)


def test_apply_quantises_like_an_8bit_camera(image) -> None:
    out = apply((Dimming(factor=3.0, duration_s=1.0),), image, ctx(time=5.0))
    assert out.dtype == np.float32 and out.max() == 255.0 and np.all(out == np.rint(out))


def test_light_conditions(image) -> None:
    np.testing.assert_allclose(Dimming()(image, ctx(time=10.0)), image / 3.0, rtol=1e-6)
    np.testing.assert_allclose(Dimming()(image, ctx(time=5.0)), image * (2.0 / 3.0), rtol=1e-6)
    flat = np.full((240, 320), 100.0, dtype=np.float32)
    ramp = GainGradient(turn_period_s=0.0)(flat, ctx())
    assert ramp[:, 0].mean() == pytest.approx(60.0) and ramp[:, -1].mean() == pytest.approx(140.0)
    turned = GainGradient(turn_period_s=20.0)(flat, ctx(time=5.0))  # a quarter turn: the ramp runs down the image
    assert turned[0].mean() == pytest.approx(60.0, abs=1e-3) and turned[-1].mean() == pytest.approx(140.0, abs=1e-3)
    blob = Specular()(flat, ctx(time=0.0)) - flat
    assert blob.max() == pytest.approx(150.0, rel=0.05)


def test_occluders_cover_the_stated_fraction_of_the_template(image) -> None:
    stays = Occluder()
    x, _, w, _ = ROI
    assert stays.covered_until(ctx(index=99)) == 0
    assert 0 < stays.covered_until(ctx(index=105)) < x + 0.3 * w
    assert stays.covered_until(ctx(index=500)) == round(x + 0.3 * w)
    out = stays(image, ctx(index=500))
    covered = np.mean(out[85:155, 125:195] != image[85:155, 125:195])
    assert covered == pytest.approx(0.3, abs=0.02)
    goes = Occluder(start_frame=0, enter_frames=10, leave_after=20)
    cols = [goes.covered_until(ctx(index=k)) for k in range(0, 60)]
    assert max(cols) == round(x + 0.3 * w) and cols[35] == max(cols) - round(0.5 * max(cols)) and cols[45] == 0


def test_sensor_conditions(image) -> None:
    noisy = Noise(sigma=4.0)(image, ctx(index=3))
    assert np.std(noisy - image) == pytest.approx(4.0, rel=0.05)
    np.testing.assert_array_equal(noisy, Noise(sigma=4.0)(image, ctx(index=3)))  # seeded per frame
    assert not np.array_equal(noisy, Noise(sigma=4.0)(image, ctx(index=4)))
    blurred = MotionBlur()(image, ctx(motion=(8.0, 0.0)))
    along, across = (np.abs(np.diff(blurred, axis=a)).mean() / np.abs(np.diff(image, axis=a)).mean() for a in (1, 0))
    assert along < 0.7 * across  # smoothed along the motion much more than across it
    compressed = Jpeg(quality=70)(image, ctx())
    assert 0.0 < np.abs(compressed - np.rint(image)).mean() < 3.0


def test_a_short_closed_loop_run_reports_its_measures() -> None:
    from orchestration.experiment_robustness import RobustnessSettings, run_one

    run = run_one("planar", "ddvs", "paper", "hard_combination", RobustnessSettings(max_images=8))
    assert run.outcome == "budget" and 0 < run.images <= 8 and len(run.error_norms) == run.images
    assert run.translation_error_mm > 200.0  # it has only started: 276 mm at the paper's start
