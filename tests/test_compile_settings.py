"""`kernels.backend.compile_settings` (issue 21): the frame-path kernels compile with Taichi's CFG and advanced IR
optimisations off. The settings are process-wide, so they must come back whatever happens inside, and a kernel
compiled under them must give the normal equations of the kernel compiled with Taichi's defaults (to float32
rounding): `general_step` here, `planar_step` against a float64 oracle in tests/test_kernels_planar_step.py. Real
Taichi kernels, a real texture."""

from __future__ import annotations

import contextlib
import importlib.util

import cv2
import numpy as np
import pytest
from taichi.lang import impl

from kernels import general_step as gs
from kernels.backend import compile_settings, init
from sim.textures import load_texture

ROI = (300, 250, 399, 329)  # u0, v0, u1, v1 (inclusive): 100×80
H = np.array([[1.01, 0.02, 3.3], [-0.015, 0.99, -2.7], [1e-5, -2e-5, 1.0]])


def _settings() -> tuple[bool, bool]:
    config = impl.current_cfg()
    return config.cfg_optimization, config.advanced_optimization


def test_settings_are_off_inside_and_restored_after_an_error() -> None:
    init()
    before = _settings()
    with compile_settings():
        assert _settings() == (False, False)
    assert _settings() == before
    with pytest.raises(RuntimeError), compile_settings():
        raise RuntimeError("inside")
    assert _settings() == before


def test_sums_match_the_kernel_compiled_with_taichis_defaults() -> None:
    """The tracking specialisation (no ρ* columns, Keys, 1×1 grid) on a warped boat pair: once from this module
    under `compile_settings`, once from a second copy of the module compiled with the defaults."""
    init()
    spec = importlib.util.spec_from_file_location("general_step_defaults", gs.__file__)
    assert spec is not None and spec.loader is not None
    defaults = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(defaults)
    ref = cv2.GaussianBlur(load_texture("boat"), (0, 0), 1.0).astype(np.float32)
    cur = (cv2.warpPerspective(ref, H, (ref.shape[1], ref.shape[0])) * 0.9 + 7.0).astype(np.float32)
    u0, v0, u1, v1 = ROI
    params = np.zeros(gs.params_size(1), dtype=np.float32)
    params[gs.PARAMS_G:gs.PARAMS_G + 9] = H.ravel()
    params[gs.PARAMS_E:gs.PARAMS_E + 3] = (0.3, -0.2, 0.001)
    params[gs.PARAMS_NORM:gs.PARAMS_NORM + 3] = (0.5 * (u0 + u1), 0.5 * (v0 + v1), 0.5 * (u1 - u0))
    params[gs.PARAMS_BNORM:gs.PARAMS_BNORM + 3] = (0.5 * (u0 + u1), 0.5 * (v0 + v1), 0.5 * (u1 - u0))
    params[gs.PARAMS_ROI:gs.PARAMS_ROI + 4] = ROI
    params[gs.PARAMS_SPAN:gs.PARAMS_SPAN + 4] = ROI
    params[gs.PARAMS_DOMAIN:gs.PARAMS_DOMAIN + 4] = (-1e9, -1e9, 1e9, 1e9)
    params[gs.PARAMS_SIGMA], params[gs.PARAMS_ROBUST], params[gs.PARAMS_BANDS] = 4.0, 1, 4
    params[gs.PARAMS_GAINS] = 1.0
    params[gs.PARAMS_RHO] = 0.3  # ρ* ≡ 0.3: live epipole columns
    n = gs.n_columns(1, False, 1, 1)
    sums = {}
    for name, module in (("settings", gs), ("defaults", defaults)):
        work = np.zeros(gs.work_size(n), dtype=np.float32)
        with compile_settings() if module is gs else contextlib.nullcontext():
            module.general_step(ref, cur, params, work, 2, 1, False, 1, 1, 0)
        sums[name] = work[:gs.n_acc(n)].astype(np.float64)
    nt = n * (n + 1) // 2
    a, b = sums["settings"], sums["defaults"]
    assert a[nt + n] == b[nt + n] > 7000  # the same valid pixels (of 8000)
    hess = np.zeros((n, n))
    hess[np.triu_indices(n)] = b[:nt]
    scale = np.sqrt(np.diag(hess))
    assert np.all(np.abs(a[:nt] - b[:nt]) <= 1e-5 * np.outer(scale, scale)[np.triu_indices(n)])
    np.testing.assert_allclose(a[nt:nt + n], b[nt:nt + n], rtol=0, atol=1e-5 * np.abs(b[nt:nt + n]).max())
