"""Camera response and defocus (`kernels.image_formation`, `RegistrationConfig.gamma` / `.defocus_px`,
`registration.defocus.register_defocus`): kernels against OpenCV / numpy, a synthetic pair defocused in irradiance,
and the blurriest Oxford bikes pairs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from conftest import pairs

from ddvs_service.registration.config import RegistrationConfig
from ddvs_service.registration.defocus import DEFAULT_RADII, register_defocus
from ddvs_service.registration.images import irradiance
from ddvs_service.registration.planar import register
from evaluation.defocus import defocused
from evaluation.pairs import CAMERA_GAMMA, ONE_GAIN_HUBER, centred_roi, corner_error, ground_truth, load
from kernels.backend import init
from kernels.image_formation import defocus_kernel, disk_blur, linearise


@pytest.mark.parametrize("radius", [0.0, 0.4, 1.0, 2.5, 5.5])
def test_defocus_kernel_is_the_disk_area(radius):
    k = defocus_kernel(radius)
    n = k.shape[0] // 2
    assert k.shape == (2 * n + 1, 2 * n + 1) and abs(float(k.sum()) - 1.0) < 1e-6
    assert np.allclose(k, k.T) and np.allclose(k, k[::-1]) and np.allclose(k, k[:, ::-1])
    if radius >= 2.5:  # a pixel wholly inside weighs 1 / (disk area); the kernel's corners lie outside the disk
        assert k[n, n] == pytest.approx(float(k.max())) and k[0, 0] == 0.0
        assert float(k.max()) == pytest.approx(1.0 / (np.pi * radius**2), rel=0.02)


def test_defocus_kernel_refuses_a_negative_radius():
    with pytest.raises(ValueError, match="defocus radius"):
        defocus_kernel(-1.0)


@pytest.mark.parametrize("radius", [1.0, 3.5, 6.0])
def test_disk_blur_matches_opencv(radius):
    init()
    rng = np.random.default_rng(1)
    src = (rng.random((61, 83)) * 255).astype(np.float32)
    out = np.empty_like(src)
    k = defocus_kernel(radius)
    disk_blur(src, out, k)
    expected = cv2.filter2D(src, -1, k, borderType=cv2.BORDER_REPLICATE)
    assert np.abs(out - expected).max() <= 1e-3


def test_linearise_matches_numpy():
    init()
    img = np.linspace(-5.0, 300.0, 64 * 48, dtype=np.float32).reshape(48, 64)
    out = img.copy()
    linearise(out, CAMERA_GAMMA)
    expected = 255.0 * (np.maximum(img.astype(np.float64), 0.0) / 255.0) ** CAMERA_GAMMA
    assert np.allclose(out, expected, rtol=1e-5, atol=1e-4)
    assert irradiance(img, 1.0) is img  # nothing to do: no copy


@pytest.mark.parametrize("field, value", [("gamma", 0.1), ("gamma", 6.0), ("defocus_px", -0.5), ("defocus_px", 17.0)])
def test_config_refuses_out_of_range(field, value):
    with pytest.raises(ValueError, match=field):
        RegistrationConfig(**{field: value})


@pytest.fixture(scope="module")
def synthetic_pair():
    sharp = load("bikes", 1)  # the white door and window bars: bright structure on a darker wall
    roi = centred_roi(sharp.shape, 200, 150)
    cx, cy = roi[0] + roi[2] / 2, roi[1] + roi[3] / 2
    a, s = np.deg2rad(3.0), 1.04
    H = np.eye(3)
    H[:2, :2] = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    H[:2, 2] = np.array([cx + 25.0, cy - 12.0]) - H[:2, :2] @ np.array([cx, cy])
    return sharp, defocused(sharp, H, 5.0, CAMERA_GAMMA), H, roi  # what a γ-encoding camera records through the lens


def test_defocus_in_irradiance_biases_encoded_levels(synthetic_pair):
    """The bias the model removes: compared in encoded levels, with or without a blurred reference, the optimum is
    off by far more than the engine's accuracy."""
    sharp, current, H, roi = synthetic_pair
    plain = register(sharp, current, roi=roi, config=RegistrationConfig(**ONE_GAIN_HUBER))
    assert corner_error(H, plain.H, roi) > 0.5
    blurred_only = register(sharp, current, roi=roi, config=RegistrationConfig(defocus_px=5.0, **ONE_GAIN_HUBER))
    assert corner_error(H, blurred_only.H, roi) > 0.3


def test_gamma_and_defocus_recover_the_warp(synthetic_pair):
    sharp, current, H, roi = synthetic_pair
    fixed = register(sharp, current, roi=roi, config=RegistrationConfig(gamma=CAMERA_GAMMA, defocus_px=5.0,
                                                                                     **ONE_GAIN_HUBER))
    assert fixed.converged, fixed.reason
    assert corner_error(H, fixed.H, roi) < 0.1
    fit = register_defocus(sharp, current, roi=roi, config=RegistrationConfig(gamma=CAMERA_GAMMA, **ONE_GAIN_HUBER))
    assert fit.result.converged, fit.result.reason
    assert fit.defocus_px == pytest.approx(5.0, abs=0.5)
    assert corner_error(H, fit.result.H, roi) < 0.1
    radii = [r for r, _, _ in fit.trials]
    assert radii[:6] == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0] and len(radii) <= 9  # stopped after the minimum


def test_register_defocus_refuses_bad_radii(synthetic_pair):
    sharp, current, _, roi = synthetic_pair
    with pytest.raises(ValueError, match="radii"):
        register_defocus(sharp, current, roi=roi, radii=(2.0, 1.0))


@pytest.mark.slow
@pytest.mark.parametrize("seq, k", pairs([("bikes", 4), ("bikes", 5), ("bikes", 6)]))
@pytest.mark.parametrize("size", [(200, 150), (400, 300)])
def test_blurred_bikes_within_a_pixel(seq, k, size):
    """Bikes 1→4…6 (defocus disks of ~3.5–5.5 px) with the camera's response (γ 2.2) and the defocus estimated:
    within 1 px of the ground truth, except bikes 1→6 at 400×300, where the ground truth itself is 1.37 px from
    two independent SIFT fits (`benchmarks/bikes_ground_truth.py`) and is held to 2 px."""
    ref, cur = load(seq, 1), load(seq, k)
    roi = centred_roi(ref.shape, *size)
    fit = register_defocus(ref, cur, roi=roi, config=RegistrationConfig(gamma=CAMERA_GAMMA, **ONE_GAIN_HUBER))
    assert fit.result.converged, fit.result.reason
    assert 2.5 <= fit.defocus_px <= 6.5
    bound = 2.0 if (k, size) == (6, (400, 300)) else 1.0
    assert corner_error(ground_truth(seq, k), fit.result.H, roi) <= bound


def test_register_cli_gamma_and_defocus_search(synthetic_pair, tmp_path, capsys):
    """`ddvs register REF CUR --gamma 2.2 --defocus search` on 8-bit files of the synthetic pair: the estimated
    radius and its trials in the JSON line; a bad `--defocus` or a search with the general model exits with 2."""
    import argparse
    import json

    from ddvs_service import register_cli

    sharp, current, H, roi = synthetic_pair
    files = []
    for name, image in (("ref", sharp), ("cur", current)):
        files.append(str(tmp_path / f"{name}.png"))
        cv2.imwrite(files[-1], np.clip(np.round(image), 0, 255).astype(np.uint8))
    parser = argparse.ArgumentParser()
    register_cli.add_arguments(parser)
    common = [*files, "--roi", *(str(v) for v in roi), "--gamma", str(CAMERA_GAMMA)]
    assert register_cli.run(parser.parse_args([*common, "--defocus", "search"])) == 0
    out = json.loads(capsys.readouterr().out.splitlines()[-1])  # the last line (Taichi may print a banner first)
    assert out["converged"] and out["defocus_px"] == pytest.approx(5.0, abs=0.5)
    assert [trial[0] for trial in out["defocus_trials"]][:2] == [0.0, 1.0]
    assert corner_error(H, np.array(out["H"]), roi) < 0.15  # 8-bit images
    for bad in (["--defocus", "near"], ["--defocus", "search", "--model", "general"], ["--defocus", "-1"]):
        assert register_cli.run(parser.parse_args([*common, *bad])) == 2
        assert "defocus" in json.loads(capsys.readouterr().out.splitlines()[-1])["error"]


def test_tracker_follows_a_defocused_stream_in_irradiance():
    """The `Tracker` with the camera response and a known defocus: consecutive frames 2 px apart, each recorded
    through a lens defocused by 4 px (in irradiance), tracked within 0.1 px from a start at the first frame's warp."""
    from ddvs_service.registration.tracker import Tracker

    sharp = load("bikes", 1)
    roi = centred_roi(sharp.shape, 200, 150)
    tracker = Tracker.prepare(sharp, roi, RegistrationConfig(gamma=CAMERA_GAMMA, defocus_px=4.0))
    H = np.eye(3)
    tracker.reset(H)
    for step in range(4):
        H = np.array([[1.0, 0.0, 2.0 * (step + 1)], [0.0, 1.0, -1.0 * (step + 1)], [0.0, 0.0, 1.0]])
        result = tracker.track(defocused(sharp, H, 4.0, CAMERA_GAMMA))
        assert result.converged, result.reason
        assert corner_error(H, result.H, roi) < 0.1


def test_register_defocus_on_a_textureless_pair_reports_not_converged():
    """No radius can converge on a flat image: the fit at the smallest radius comes back flagged, no exception."""
    flat = np.full((120, 160), 90.0, dtype=np.float32)
    fit = register_defocus(flat, flat, roi=(40, 30, 80, 60), config=RegistrationConfig(gamma=CAMERA_GAMMA))
    assert not fit.result.converged and "degenerate" in fit.result.reason
    assert fit.defocus_px == 0.0 and np.all(np.isfinite(fit.result.G))
    assert len(fit.trials) == len(DEFAULT_RADII) and not any(converged for _, _, converged in fit.trials)


def test_general_model_honours_gamma_and_defocus():
    """The general model (eq. (2)) runs on the planar engine's reference and current buffers, so it registers
    irradiance with the reference defocused too: a planar scene defocused by 4 px in irradiance, 7 px away."""
    from ddvs_service.registration.general_config import GeneralConfig
    from ddvs_service.registration.general_register import register_general

    sharp = load("bikes", 1)
    roi = centred_roi(sharp.shape, 200, 150)
    H = np.array([[1.0, 0.0, 6.0], [0.0, 1.0, -4.0], [0.0, 0.0, 1.0]])
    current = defocused(sharp, H, 4.0, CAMERA_GAMMA)
    result = register_general(sharp, current, roi=roi,
                              config=GeneralConfig(base=RegistrationConfig(gamma=CAMERA_GAMMA, defocus_px=4.0)))
    assert result.converged, result.reason
    assert corner_error(H, result.G / result.G[2, 2], roi) < 0.05
    assert np.all(np.abs(result.warp(np.array([[450.0, 300.0]])) - [456.0, 296.0]) < 0.05)
