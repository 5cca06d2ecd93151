"""Bad input and the tracker's contract: clear errors, or not-converged results with a reason; never a NaN G."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ddvs_service.registration.config import RegistrationConfig
from ddvs_service.registration.planar import register
from ddvs_service.registration.tracker import Tracker
from sim.textures import load_texture

IMG = cv2.GaussianBlur(
    load_texture("boat"), (0, 0), 1.5
)
ROI = (325, 265, 200, 150)


def shifted(dx: float, dy: float) -> np.ndarray:
    H = np.array([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1.0]])
    return cv2.warpPerspective(IMG, H, (IMG.shape[1], IMG.shape[0]))


def test_mismatched_sizes():
    with pytest.raises(ValueError, match="expected the reference's"):
        register(IMG, IMG[:-10], roi=ROI)


@pytest.mark.parametrize("roi", [(800, 600, 200, 150), (-1, 0, 100, 100), (10, 10, 4, 100)])
def test_roi_outside_or_too_small(roi):
    with pytest.raises(ValueError, match="roi"):
        register(IMG, IMG, roi=roi)


def test_nan_pixels_are_refused():
    bad = IMG.copy()
    bad[100, 100] = np.nan
    with pytest.raises(ValueError, match="NaN/Inf"):
        register(IMG, bad, roi=ROI)


def test_an_integer_frame_registers_as_its_float32_copy():
    """`run` takes a camera's uint8 frame without a float32 copy of its own (`images.checked_image`): the workspace's
    copy converts it, with the same result as the converted frame."""
    cur = np.clip(np.rint(shifted(1.5, -0.7)), 0, 255).astype(np.uint8)
    as_is, converted = (register(IMG, frame, roi=ROI) for frame in (cur, cur.astype(np.float32)))
    assert as_is.converged and np.array_equal(as_is.G, converted.G)
    assert as_is.iterations == converted.iterations


def test_config_values_are_validated():
    with pytest.raises(ValueError, match="gain_grid"):
        RegistrationConfig(gain_grid=(0, 2))
    with pytest.raises(ValueError, match="robust"):
        RegistrationConfig(robust="cauchy")  # type: ignore[arg-type]


def test_small_levels_use_fewer_bands_never_more_than_configured():
    config = RegistrationConfig(bands=8)
    assert config.bands_for(35 * 35) == 1
    assert config.bands_for(200 * 150) == 2
    assert config.bands_for(640 * 480) == 8
    assert RegistrationConfig(bands=3).bands_for(640 * 480) == 3


def test_textureless_is_not_converged():
    flat = np.full_like(IMG, 128.0)
    result = register(flat, flat, roi=ROI)
    assert not result.converged
    assert "degenerate" in result.reason
    assert np.all(np.isfinite(result.G))


def test_divergence_is_reported():
    noise = np.random.default_rng(1).uniform(0, 255, IMG.shape).astype(np.float32)
    result = register(IMG, noise, roi=ROI, config=RegistrationConfig(levels=1, max_iterations=10))
    assert not result.converged
    assert result.reason
    assert np.all(np.isfinite(result.G))


def test_mask_excludes_pixels_and_all_masked_is_an_error():
    mask = np.zeros(IMG.shape, dtype=bool)
    with pytest.raises(ValueError, match="mask excludes every pixel"):
        register(IMG, IMG, roi=ROI, mask=mask)
    mask[ROI[1] : ROI[1] + 100, ROI[0] : ROI[0] + 200] = True
    result = register(IMG, shifted(3.0, -2.0), roi=ROI, mask=mask)
    assert result.converged, result.reason
    assert np.allclose(result.H[:2, 2], [3.0, -2.0], atol=0.02)


def test_tracker_follows_a_smooth_trajectory_and_survives_bad_frames():
    tracker = Tracker.prepare(IMG, ROI, RegistrationConfig(levels=2))
    for k in range(1, 8):
        dx, dy = 2.0 * k, 1.0 * k
        result = tracker.track(shifted(dx, dy))
        assert result.converged, result.reason
        assert np.allclose(tracker.G / tracker.G[2, 2], [[1, 0, dx], [0, 1, dy], [0, 0, 1]], atol=0.02)
    before = tracker.G
    bad = shifted(16.0, 8.0)
    bad[0, 0] = np.inf
    result = tracker.track(bad)
    assert not result.converged and "NaN/Inf" in result.reason
    result = tracker.track(np.zeros((5, 5), dtype=np.float32))
    assert not result.converged and result.reason.startswith("error")
    assert np.array_equal(tracker.G, before)
    tracker.reset()
    assert np.array_equal(tracker.G, np.eye(3))
