"""Kernel level: planar step vs the float64 numpy oracle, sampling vs cv2.remap, pyramid vs cv2 filtering."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from evaluation.numpy_iteration import bilinear, numpy_step
from kernels.backend import compile_settings, init
from kernels.planar_step import (
    N_STATS,
    PARAMS_BANDS,
    PARAMS_BETA,
    PARAMS_G,
    PARAMS_GAINS,
    PARAMS_NORM,
    PARAMS_ROBUST,
    PARAMS_ROI,
    PARAMS_SIGMA,
    PARAMS_SPAN,
    n_acc,
    n_params,
    planar_step,
    render_compensated,
    work_size,
)
from kernels.pyramid import downsample2
from sim.textures import load_texture

init()
IMG = cv2.GaussianBlur(load_texture("boat"), (0, 0), 1.0)
G_TEST = np.array([[1.01, 0.02, 3.3], [-0.015, 0.99, -2.7], [1e-5, -2e-5, 1.0]])


def make_params(grid, robust=1, sigma=4.0, gains=None, beta=5.0, bands=8):
    u0, v0, u1, v1 = 300, 250, 499, 399
    p = np.zeros(PARAMS_GAINS + grid[0] * grid[1], dtype=np.float32)
    p[PARAMS_G : PARAMS_G + 9] = G_TEST.reshape(9)
    p[PARAMS_NORM : PARAMS_NORM + 3] = (0.5 * (u0 + u1), 0.5 * (v0 + v1), 0.5 * (u1 - u0))
    p[PARAMS_ROI : PARAMS_ROI + 4] = (u0, v0, u1, v1)
    p[PARAMS_SPAN : PARAMS_SPAN + 4] = (u0, v0, u1, v1)
    p[PARAMS_BETA] = beta
    p[PARAMS_SIGMA] = sigma
    p[PARAMS_ROBUST] = robust
    p[PARAMS_BANDS] = bands
    rng = np.random.default_rng(0)
    p[PARAMS_GAINS:] = 1.0 + 0.1 * rng.standard_normal(grid[0] * grid[1]) if gains is None else gains
    return p


def run_kernel(ref, cur, params, grid):
    """The kernel compiled as the registration compiles it (`compile_settings`)."""
    n = n_params(*grid)
    work = np.zeros(work_size(n), dtype=np.float32)
    with compile_settings():
        planar_step(ref[None], cur[None], params[None], work[None], grid[0], grid[1])  # a stack of one
    acc = work[: n_acc(n)].astype(np.float64)
    nt = n * (n + 1) // 2
    H = np.zeros((n, n))
    H[np.triu_indices(n)] = acc[:nt]
    H = H + np.triu(H, 1).T
    return H, acc[nt : nt + n], acc[nt + n :]


@pytest.mark.parametrize("grid", [(1, 1), (2, 3)])
@pytest.mark.parametrize("robust", [0, 1, 2])
def test_normal_equations_match_float64_oracle(grid, robust):
    cur = cv2.warpPerspective(IMG, G_TEST, (IMG.shape[1], IMG.shape[0]))
    cur = cur * 0.9 + 7.0
    cur[300:330, 380:420] = 255.0  # outliers, so the robust weights matter
    params = make_params(grid, robust=robust)
    H, g, stats = run_kernel(IMG, cur, params, grid)
    ref = numpy_step(IMG, cur, params, grid)
    assert len(stats) == N_STATS
    assert np.linalg.norm(H - ref.H) / np.linalg.norm(ref.H) < 1e-5
    # Jᵀr sums terms of both signs that mostly cancel (‖g‖ ≪ Σ|J r|): float32 per-pixel rounding shows at ~1e-4…5e-4.
    assert np.linalg.norm(g - ref.g) / np.linalg.norm(ref.g) < 1e-3
    assert stats[0] == ref.n_valid
    assert abs(stats[1] - ref.n_inliers) <= 2  # float32 vs float64 on the |r| = 4.685 σ boundary
    assert abs(stats[2] - ref.sum_r2) / ref.sum_r2 < 1e-5
    assert abs(stats[3] - ref.median_abs_r) / ref.median_abs_r < 0.03  # histogram median


def test_band_count_does_not_change_the_sums():
    cur = cv2.warpPerspective(IMG, G_TEST, (IMG.shape[1], IMG.shape[0]))
    H1, g1, _ = run_kernel(IMG, cur, make_params((1, 1), bands=1), (1, 1))
    H8, g8, _ = run_kernel(IMG, cur, make_params((1, 1), bands=32), (1, 1))
    assert np.linalg.norm(H1 - H8) / np.linalg.norm(H1) < 1e-5
    assert np.linalg.norm(g1 - g8) / np.linalg.norm(g1) < 1e-5


def test_gradient_matches_finite_differences_of_the_cost():
    """With weights 1 and `cur` an exactly shifted smooth image, Jᵀr is the gradient of ½Σr² (ESM = true gradient
    when ∇Iw = ∇I*); checked by central finite differences of the cost rendered by `render_compensated`."""
    v, u = np.mgrid[0:240, 0:320].astype(np.float64)

    def scene(x, y):
        return (100 + 40 * np.sin(x / 9.0) * np.cos(y / 13.0) + 30 * np.cos((x + y) / 17.0)).astype(np.float32)

    ref = scene(u, v)
    cur = scene(u - 0.3, v - 0.2) + 10.0  # current(p + t) = ref(p) + 10: residuals 10 where G = translation t
    grid = (1, 1)
    params = make_params(grid, robust=0, sigma=1e30, gains=[1.0], beta=0.0)
    u0, v0, u1, v1 = 60, 50, 259, 189
    params[PARAMS_ROI : PARAMS_ROI + 4] = (u0, v0, u1, v1)
    params[PARAMS_SPAN : PARAMS_SPAN + 4] = (u0, v0, u1, v1)
    cx, cy, s = 0.5 * (u0 + u1), 0.5 * (v0 + v1), 0.5 * (u1 - u0)
    params[PARAMS_NORM : PARAMS_NORM + 3] = (cx, cy, s)
    G = np.array([[1.0, 0, 0.3], [0, 1.0, 0.2], [0, 0, 1.0]])
    params[PARAMS_G : PARAMS_G + 9] = G.reshape(9)
    _, g, _ = run_kernel(ref, cur, params, grid)

    from ddvs_service.lie import sl3_exp

    N = np.array([[1 / s, 0, -cx / s], [0, 1 / s, -cy / s], [0, 0, 1]])

    def cost(x):
        p = params.copy()
        p[PARAMS_G : PARAMS_G + 9] = (G @ np.linalg.inv(N) @ sl3_exp(x[:8]) @ N).reshape(9)
        p[PARAMS_GAINS] = 1.0 + x[8]
        p[PARAMS_BETA] = x[9]
        out = np.empty((v1 - v0 + 1, u1 - u0 + 1), dtype=np.float32)
        render_compensated(cur, p, out, 1, 1)
        r = out.astype(np.float64) - ref[v0 : v1 + 1, u0 : u1 + 1]
        return 0.5 * float(np.sum(r[1:-1, 1:-1] ** 2))  # interior: same pixel set as the kernel's

    eps = [1e-3] * 8 + [1e-4, 1e-2]
    fd = np.array([(cost(e) - cost(-e)) / (2 * h) for h, e in ((h, np.eye(10)[i] * h) for i, h in enumerate(eps))])
    # Central differences of the warped samples approximate the smooth image's derivative to O(h²): ~1 %.
    assert np.allclose(g, fd, rtol=0.03, atol=0.03 * np.abs(fd).max())


def test_sampling_matches_cv2_remap_and_exact_bilinear():
    grid = (1, 1)
    params = make_params(grid, gains=[1.0], beta=0.0)
    u0, v0, u1, v1 = (int(x) for x in params[PARAMS_ROI : PARAMS_ROI + 4])
    out = np.empty((v1 - v0 + 1, u1 - u0 + 1), dtype=np.float32)
    render_compensated(IMG, params, out, 1, 1)
    v, u = np.mgrid[v0 : v1 + 1, u0 : u1 + 1].astype(np.float64)
    q = np.tensordot(G_TEST, np.stack([u, v, np.ones_like(u)]), axes=1)
    mx, my = (q[0] / q[2]).astype(np.float32), (q[1] / q[2]).astype(np.float32)
    exact, ok = bilinear(IMG.astype(np.float64), q[0] / q[2], q[1] / q[2])
    assert ok.all()
    assert np.max(np.abs(out - exact)) < 1e-2  # float32 coordinates (~3e-5 px at u ≈ 500) × gradient
    cv = cv2.remap(IMG, mx, my, cv2.INTER_LINEAR)
    # OpenCV quantises the bilinear weights to 1/32 px: agreement to that resolution.
    assert np.mean(np.abs(out - cv)) < 0.1
    assert np.max(np.abs(out - cv)) < 2.0


def test_samples_outside_the_image_are_nan():
    params = make_params((1, 1), gains=[1.0], beta=0.0)
    params[PARAMS_G + 2] = 2000.0  # shift far to the right
    out = np.empty((150, 200), dtype=np.float32)
    render_compensated(IMG, params, out, 1, 1)
    assert np.isnan(out).all()


def test_pyramid_matches_cv2_filter():
    src = IMG[:301, :417].copy()  # odd sizes
    dst = np.empty((src.shape[0] // 2, src.shape[1] // 2), dtype=np.float32)
    downsample2(src, dst)
    k = np.array([1, 3, 3, 1], dtype=np.float64) / 8
    filt = cv2.sepFilter2D(src.astype(np.float64), -1, k, k, anchor=(1, 1), borderType=cv2.BORDER_REPLICATE)
    expected = filt[0::2, 0::2][: dst.shape[0], : dst.shape[1]]
    assert np.max(np.abs(dst - expected)) < 1e-3


@pytest.mark.parametrize("grid", [(1, 1), (2, 2)])
def test_reduced_sums_match_float64_at_1e5_where_terms_do_not_cancel(grid):
    """Every sum whose terms share one sign, compared entry by entry at 1e-5 relative: the diagonal of JᵀWJ (squares),
    the photometric entries of JᵀWr (current = reference + 40 > 0 everywhere, so r = S·I + β − I* > 0 and
    φ·I·r > 0), the valid count and Σ r². The geometric entries of JᵀWr add gradient terms of both signs that cancel
    to ~1e-3 of Σ|term|; there the float32 rounding of each term, not the reduction, limits the agreement (checked
    at 1e-3 in `test_normal_equations_match_float64_oracle`)."""
    cur = IMG + 40.0
    params = make_params(grid, robust=1, sigma=100.0, gains=np.full(grid[0] * grid[1], 1.05), beta=2.0)
    params[PARAMS_G : PARAMS_G + 9] = np.eye(3).reshape(9)
    H, g, stats = run_kernel(IMG, cur, params, grid)
    ref = numpy_step(IMG, cur, params, grid)
    assert np.all(np.abs(np.diag(H) - np.diag(ref.H)) <= 1e-5 * np.abs(np.diag(ref.H)))
    assert np.all(ref.g[8:] > 0)
    assert np.all(np.abs(g[8:] - ref.g[8:]) <= 1e-5 * np.abs(ref.g[8:]))
    assert stats[0] == ref.n_valid
    assert abs(stats[2] - ref.sum_r2) <= 1e-5 * ref.sum_r2
