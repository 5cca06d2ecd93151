"""Vectorised numpy (float64) implementation of one `kernels.planar_step` evaluation: the correctness oracle of the
Taichi kernel and the numpy baseline of `bench_registration.py`. Reference code, not used by the product.

Same inputs (the kernel's float32 parameter array, `PARAMS_*` layout) and the same definitions (module docstring of
`kernels.planar_step`): residual `S·I(w(G, p*)) + β − I*(p*)`, ESM Jacobian, robust weights, normal equations.
The median of |r| is exact here (the kernel reads it from a histogram, within ~2 %).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from kernels.planar_step import (
    HUBER_K,
    INLIER_C,
    MASK_LIMIT,
    PARAMS_BETA,
    PARAMS_G,
    PARAMS_GAINS,
    PARAMS_NORM,
    PARAMS_ROBUST,
    PARAMS_ROI,
    PARAMS_SIGMA,
    PARAMS_SPAN,
    SATURATED,
    TUKEY_C,
)

F64 = NDArray[np.float64]


@dataclass
class StepSums:
    """`JᵀWJ` (P×P), `JᵀWr` (P), valid and inlier counts, Σ r², median |r|."""

    H: F64
    g: F64
    n_valid: float
    n_inliers: float
    sum_r2: float
    median_abs_r: float


def bilinear(img: F64, x: F64, y: F64) -> tuple[F64, NDArray[np.bool_]]:
    """Bilinear samples at (x, y) = (column, row) and the inside mask (0 ≤ x ≤ W − 1, 0 ≤ y ≤ H − 1)."""
    h, w = img.shape
    ok = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    xs = np.where(ok, x, 0.0)
    ys = np.where(ok, y, 0.0)
    x0 = np.minimum(np.floor(xs).astype(np.int64), w - 2)
    y0 = np.minimum(np.floor(ys).astype(np.int64), h - 2)
    ax, ay = xs - x0, ys - y0
    top = (1 - ax) * img[y0, x0] + ax * img[y0, x0 + 1]
    bottom = (1 - ax) * img[y0 + 1, x0] + ax * img[y0 + 1, x0 + 1]
    return np.where(ok, (1 - ay) * top + ay * bottom, 0.0), ok


def _tent_weights(t: F64, n: int) -> F64:
    return np.maximum(0.0, 1.0 - np.abs(t[..., None] - np.arange(n)))


def numpy_step(ref: NDArray, cur: NDArray, params: NDArray, grid: tuple[int, int]) -> StepSums:
    """One evaluation of the planar step at `params` (float32 array in the kernel's layout), in float64."""
    p = params.astype(np.float64)
    ref = ref.astype(np.float64)
    cur = cur.astype(np.float64)
    G = p[PARAMS_G : PARAMS_G + 9].reshape(3, 3)
    cx, cy, s = p[PARAMS_NORM : PARAMS_NORM + 3]
    u0, v0, u1, v1 = (int(v) for v in p[PARAMS_ROI : PARAMS_ROI + 4])
    sx0, sy0, sx1, sy1 = p[PARAMS_SPAN : PARAMS_SPAN + 4]
    rows, cols = grid
    gains = p[PARAMS_GAINS : PARAMS_GAINS + rows * cols].reshape(rows, cols)
    beta, sigma, kind = p[PARAMS_BETA], p[PARAMS_SIGMA], int(p[PARAMS_ROBUST])
    hr, wr = ref.shape

    v, u = np.mgrid[v0 : v1 + 1, u0 : u1 + 1].astype(np.float64)
    ui, vi = u.astype(np.int64), v.astype(np.int64)
    ul, ur = np.maximum(ui - 1, 0), np.minimum(ui + 1, wr - 1)
    vu, vd = np.maximum(vi - 1, 0), np.minimum(vi + 1, hr - 1)
    ir = ref[vi, ui]
    gxr = (ref[vi, ur] - ref[vi, ul]) / (ur - ul)
    gyr = (ref[vd, ui] - ref[vu, ui]) / (vd - vu)

    def sample(du: float, dv: float) -> tuple[F64, NDArray[np.bool_]]:
        x = G[0, 0] * (u + du) + G[0, 1] * (v + dv) + G[0, 2]
        y = G[1, 0] * (u + du) + G[1, 1] * (v + dv) + G[1, 2]
        z = G[2, 0] * (u + du) + G[2, 1] * (v + dv) + G[2, 2]
        zs = np.where(z > 1e-8, z, 1.0)
        val, ok = bilinear(cur, x / zs, y / zs)
        return val, ok & (z > 1e-8) & (val < SATURATED)  # a clipped sample is invalid, as in the kernel

    (c0, k0), (cl, kl), (cr, kr), (cu, ku), (cd, kd) = (
        sample(0, 0), sample(-1, 0), sample(1, 0), sample(0, -1), sample(0, 1)
    )
    valid = k0 & kl & kr & ku & kd & (ir > MASK_LIMIT) & (np.abs(gxr) < -MASK_LIMIT) & (np.abs(gyr) < -MASK_LIMIT)

    tc = np.zeros_like(u) if cols == 1 else np.clip((u - sx0) / max(sx1 - sx0, 1e-6), 0, 1) * (cols - 1)
    tr = np.zeros_like(v) if rows == 1 else np.clip((v - sy0) / max(sy1 - sy0, 1e-6), 0, 1) * (rows - 1)
    phi = _tent_weights(tr, rows)[..., :, None] * _tent_weights(tc, cols)[..., None, :]  # (h, w, R, C)
    gain = np.einsum("hwrc,rc->hw", phi, gains)

    r = gain * c0 + beta - ir
    gx = 0.5 * (gain * 0.5 * (cr - cl) + gxr)
    gy = 0.5 * (gain * 0.5 * (cd - cu) + gyr)
    du, dv = u - cx, v - cy
    radial = (gx * du + gy * dv) / s
    J_geo = np.stack([s * gx, s * gy, gy * du - gx * dv, gx * du - gy * dv, 3 * s * radial, gx * dv + gy * du,
                      -du * radial, -dv * radial], axis=-1)
    J = np.concatenate([J_geo, phi.reshape(*u.shape, rows * cols) * c0[..., None], np.ones((*u.shape, 1))], axis=-1)
    J, r = J[valid], r[valid]

    a = np.abs(r)
    w = np.ones_like(r)
    if kind == 1:
        k = HUBER_K * sigma
        w = np.where(a > k, k / np.maximum(a, 1e-300), 1.0)
    elif kind == 2:
        c = TUKEY_C * sigma
        w = np.where(a < c, (1 - (r / c) ** 2) ** 2, 0.0)
    Jw = J * w[:, None]
    return StepSums(
        H=Jw.T @ J, g=Jw.T @ r, n_valid=float(r.size), n_inliers=float(np.sum(a <= INLIER_C * sigma)),
        sum_r2=float(r @ r), median_abs_r=float(np.median(a)) if r.size else 0.0,
    )
