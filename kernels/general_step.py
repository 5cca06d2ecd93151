"""One robust Gauss-Newton step of general (non-planar) direct registration, eq. (2) `p ∝ G p* + ρ*(p*) e` with the
photometric model (4), fused: residuals, Jacobian columns, robust normal equations in one launch.

For every reference pixel `p* = (u, v)` of the region of interest (level pixels, pixel centres):
- warp: `P = G p* + ρ(p*) e = [X, Y, Z]`, `w = (X/Z, Y/Z)`; `ρ(p*) = Σ_m a_m x^i y^j` with `(x, y)` the basis
  normalisation of the reference pixel (`PARAMS_BNORM`) and `a` the monomial coefficients of the current `ρ*`;
- residual `r = S(p*) · I(w) + β − I*(p*)`;
- `I(w)` and its exact gradient `∇I(w)` from one Keys bicubic interpolation (`cubic_sample`, 4×4 taps): bilinear
  interpolation's phase-dependent blur biased the optimum (gain 1.01–1.015 on unit-gain renders, warp 0.01–0.03 px
  off on the paper's trajectory); bicubic brings the gain to 1.000–1.001 and lowers that warp error by 30–40 %;
- image gradient in current pixels, mean of both sides (ESM-like): `g = ½ (S ∇I(w) + ∇I*(p*) A⁻¹)`, `A = ∂w/∂p*`
  (analytic, including `∇ρ`);
- Jacobian columns, in this order:
  - 8 sl(3) coordinates of a left increment `P ← N⁻¹ exp(Σ xᵢ Aᵢ) N P` (so `G ← M G`, `e ← M e`; `Aᵢ` =
    `ddvs_service.lie.SL3_GENERATORS`, `N` the normalisation `q = (p − c) / s` of the current-image point);
  - 3 epipole coordinates `e ← e + N⁻¹ δe'` (normalised units): `∂P = ρ N⁻¹ δe'`;
  - when `with_rho`: one per parallax basis function `φ_k = Σ_m B_km x^i y^j`: `∂P = φ_k e δc_k`;
  - gain nodes `φ_gain · I(w)` and the bias 1 (as `kernels.planar_step`);
- reference pixels masked by the caller (`planar_step.MASKED`) are skipped, as are warps whose 4×4 taps leave the
  image;
- robust weight and statistics exactly as `kernels.planar_step` (Huber/Tukey with a caller-given σ, valid and inlier
  counts, Σ r², the histogram of |r| of `planar_step.hist_bin` whose median gives the next MAD scale).

Reduction as in PLATFORM-NOTES: each thread owns a band of rows, sums into registers, writes one partial; a serial
pass adds the partials. One float32 parameter array in (`PARAMS_*`), one float32 work array out (`work_size`).
"""


import taichi as ti

from kernels.planar_step import (
    HIST_BINS,
    INLIER_C,
    MASK_LIMIT,
    MAX_BANDS,
    N_STATS,
    gain_at,
    hist_bin,
    hist_value,
    robust_weight,
)
from kernels.planar_step import PARAMS_GAINS as PLANAR_GAINS
from kernels.planar_step import PARAMS_SPAN as PLANAR_SPAN
from kernels.sampling import homography_apply, load_vector

MAX_MONOMIALS = 16  # degree ≤ 3 per axis: x^i y^j, 0 ≤ i, j ≤ 3

# Offsets in the float32 parameter array. The gain span and nodes sit where `planar_step.gain_at` reads them.
PARAMS_G = 0  # 9: G row-major (level pixels, reference → current)
PARAMS_E = 9  # 3: epipole e (level pixels, homogeneous, same scale as G)
PARAMS_NORM = 12  # 3: cx, cy, s of the sl(3)/epipole normalisation (level pixels)
PARAMS_BETA = 15  # 1: bias β (grey levels)
PARAMS_SPAN = PLANAR_SPAN  # 4: gain-grid node span (level pixels)
PARAMS_SIGMA = 20  # 1: robust scale σ (grey levels)
PARAMS_ROBUST = 21  # 1: 0 none, 1 Huber, 2 Tukey
PARAMS_BANDS = 22  # 1: number of row bands
PARAMS_GAINS = PLANAR_GAINS  # 16 at most: gain node values, row-major
PARAMS_ROI = 40  # 4: u0, v0, u1, v1 inclusive
PARAMS_BNORM = 44  # 3: cx, cy, s of the parallax-basis coordinates (x, y) = (p − c) / s (level pixels)
PARAMS_RHO = 48  # 16: monomial coefficients a_m of ρ*, m = i·(degree + 1) + j for x^i y^j
PARAMS_BASIS = 64  # n_rho × 16: basis coefficients B_km (same monomial order)
N_GEOMETRIC = 8
N_EPIPOLE = 3


def params_size(n_rho: int) -> int:
    """Length of the float32 parameter array for `n_rho` parallax basis functions."""
    return PARAMS_BASIS + MAX_MONOMIALS * max(n_rho, 1)


def n_columns(n_rho: int, with_rho: bool, grid_rows: int, grid_cols: int) -> int:
    """Number of Jacobian columns: 8 sl(3) + 3 epipole (+ n_rho when `with_rho`) + gain nodes + bias."""
    return N_GEOMETRIC + N_EPIPOLE + (n_rho if with_rho else 0) + grid_rows * grid_cols + 1


def n_acc(n: int) -> int:
    """Length of one accumulator: upper triangle of `JᵀWJ`, `JᵀWr`, statistics."""
    return n * (n + 1) // 2 + n + N_STATS


def work_size(n: int) -> int:
    """float32 work array size for `n` columns: final sums, per-band partials, per-band histograms."""
    return n_acc(n) * (1 + MAX_BANDS) + HIST_BINS * MAX_BANDS


@ti.func
def _powers(t: ti.f32, degree: ti.template()):
    p = ti.Vector.zero(ti.f32, degree + 1)
    p[0] = 1.0
    for i in ti.static(range(1, degree + 1)):
        p[i] = p[i - 1] * t
    return p


@ti.func
def _keys(t: ti.f32):
    """Keys cubic convolution (a = −½) weights of taps −1, 0, 1, 2 at fraction `t` ∈ [0, 1), and their derivatives."""
    t2 = t * t
    t3 = t2 * t
    w = ti.Vector([-0.5 * (t3 + t) + t2, 1.5 * t3 - 2.5 * t2 + 1.0, -1.5 * t3 + 2.0 * t2 + 0.5 * t, 0.5 * (t3 - t2)])
    d = ti.Vector([-1.5 * t2 + 2.0 * t - 0.5, 4.5 * t2 - 5.0 * t, -4.5 * t2 + 4.0 * t + 0.5, 1.5 * t2 - t])
    return w, d


@ti.func
def cubic_sample(img: ti.template(), x: ti.f32, y: ti.f32):
    """Keys bicubic sample of `img` at column `x`, row `y` and its exact gradient (grey levels per pixel).

    Returns `(value, d/dx, d/dy, ok)`; `ok = 0` (zeros) unless the 4×4 taps lie inside, i.e. `1 ≤ x, y` and
    `x ≤ W − 2`, `y ≤ H − 2` (the same domain as a bilinear sample with ±1 px central differences)."""
    h = img.shape[0]
    w = img.shape[1]
    val = 0.0
    gx = 0.0
    gy = 0.0
    ok = 0
    if x >= 1.0 and y >= 1.0 and x <= w - 2.0 and y <= h - 2.0:
        x0 = ti.min(ti.cast(ti.floor(x), ti.i32), w - 3)
        y0 = ti.min(ti.cast(ti.floor(y), ti.i32), h - 3)
        wx, dx = _keys(x - x0)
        wy, dy = _keys(y - y0)
        for i in ti.static(range(4)):
            row = 0.0
            row_dx = 0.0
            for j in ti.static(range(4)):
                c = img[y0 - 1 + i, x0 - 1 + j]
                row += wx[j] * c
                row_dx += dx[j] * c
            val += wy[i] * row
            gx += wy[i] * row_dx
            gy += dy[i] * row
        ok = 1
    return val, gx, gy, ok


@ti.kernel
def general_step(
    ref: ti.types.ndarray(dtype=ti.f32, ndim=2),
    cur: ti.types.ndarray(dtype=ti.f32, ndim=2),
    params: ti.types.ndarray(dtype=ti.f32, ndim=1),
    work: ti.types.ndarray(dtype=ti.f32, ndim=1),
    degree: ti.template(),
    n_rho: ti.template(),
    with_rho: ti.template(),
    grid_rows: ti.template(),
    grid_cols: ti.template(),
):
    """Residuals, robust weights and normal equations of eq. (5) under the warp (2) (module docstring)."""
    NR = ti.static(n_rho if with_rho else 0)
    NG = ti.static(grid_rows * grid_cols)
    P = ti.static(N_GEOMETRIC + N_EPIPOLE + NR + NG + 1)
    NT = ti.static(P * (P + 1) // 2)
    NACC = ti.static(NT + P + N_STATS)
    D1 = ti.static(degree + 1)
    hist0 = ti.static(NACC * (1 + MAX_BANDS))
    nb = ti.cast(params[PARAMS_BANDS], ti.i32)
    u0 = ti.cast(params[PARAMS_ROI + 0], ti.i32)
    v0 = ti.cast(params[PARAMS_ROI + 1], ti.i32)
    u1 = ti.cast(params[PARAMS_ROI + 2], ti.i32)
    v1 = ti.cast(params[PARAMS_ROI + 3], ti.i32)
    cx = params[PARAMS_NORM + 0]
    cy = params[PARAMS_NORM + 1]
    s = params[PARAMS_NORM + 2]
    bcx = params[PARAMS_BNORM + 0]
    bcy = params[PARAMS_BNORM + 1]
    bs = params[PARAMS_BNORM + 2]
    e0 = params[PARAMS_E + 0]
    e1 = params[PARAMS_E + 1]
    e2 = params[PARAMS_E + 2]
    beta = params[PARAMS_BETA]
    sigma = params[PARAMS_SIGMA]
    kind = ti.cast(params[PARAMS_ROBUST], ti.i32)
    G = load_vector(params, PARAMS_G, 9)
    span = load_vector(params, PARAMS_SPAN, 4)
    gains = load_vector(params, PARAMS_GAINS, grid_rows * grid_cols)
    hr = ref.shape[0]
    wr = ref.shape[1]
    for it in range(nb * 512):  # one band per 512-iteration block (PLATFORM-NOTES)
        if it % 512 == 0:
            b = it // 512
            hoff = hist0 + b * HIST_BINS
            for k in range(HIST_BINS):
                work[hoff + k] = 0.0
            acc = ti.Vector.zero(ti.f32, NACC)
            rows = v1 - v0 + 1
            for v in range(v0 + b * rows // nb, v0 + (b + 1) * rows // nb):
                racc = ti.Vector.zero(ti.f32, NACC)
                vu = ti.max(v - 1, 0)
                vd = ti.min(v + 1, hr - 1)
                yp = _powers((v - bcy) / bs, degree)
                for u in range(u0, u1 + 1):
                    ul = ti.max(u - 1, 0)
                    ur = ti.min(u + 1, wr - 1)
                    ir = ref[v, u]
                    gxr = (ref[v, ur] - ref[v, ul]) / (ur - ul)
                    gyr = (ref[vd, u] - ref[vu, u]) / (vd - vu)
                    xp = _powers((u - bcx) / bs, degree)
                    rho = 0.0
                    rho_x = 0.0
                    rho_y = 0.0
                    for i in ti.static(range(D1)):
                        for j in ti.static(range(D1)):
                            a = params[PARAMS_RHO + i * D1 + j]
                            rho += a * xp[i] * yp[j]
                            if ti.static(i > 0):
                                rho_x += a * i * xp[i - 1] * yp[j]
                            if ti.static(j > 0):
                                rho_y += a * j * xp[i] * yp[j - 1]
                    rho_u = rho_x / bs
                    rho_v = rho_y / bs
                    X, Y, Z = homography_apply(G, ti.cast(u, ti.f32), ti.cast(v, ti.f32))
                    X += rho * e0
                    Y += rho * e1
                    Z += rho * e2
                    ok_z = Z > 1e-8
                    iz = 1.0 / ti.select(ok_z, Z, 1.0)
                    x = X * iz
                    y = Y * iz
                    c0, cgx, cgy, ok = cubic_sample(cur, x, y)
                    unmasked = ir > MASK_LIMIT and ti.abs(gxr) < -MASK_LIMIT and ti.abs(gyr) < -MASK_LIMIT
                    if ok_z and unmasked and ok == 1:
                        gain, phi = gain_at(span, gains, ti.cast(u, ti.f32), ti.cast(v, ti.f32), grid_rows, grid_cols)
                        r = gain * c0 + beta - ir
                        # A = ∂w/∂p*, columns from ∂P/∂u = G[:, 0] + ρ_u e and ∂P/∂v = G[:, 1] + ρ_v e
                        pxu = params[0] + rho_u * e0
                        pyu = params[3] + rho_u * e1
                        pzu = params[6] + rho_u * e2
                        pxv = params[1] + rho_v * e0
                        pyv = params[4] + rho_v * e1
                        pzv = params[7] + rho_v * e2
                        a00 = (pxu - x * pzu) * iz
                        a10 = (pyu - y * pzu) * iz
                        a01 = (pxv - x * pzv) * iz
                        a11 = (pyv - y * pzv) * iz
                        det = a00 * a11 - a01 * a10
                        gx = gain * cgx
                        gy = gain * cgy
                        if ti.abs(det) > 1e-12:
                            gx = 0.5 * (gx + (gxr * a11 - gyr * a10) / det)
                            gy = 0.5 * (gy + (gyr * a00 - gxr * a01) / det)
                        du = x - cx  # = s · q_u in the current image
                        dv = y - cy
                        radial = (gx * du + gy * dv) / s
                        J = ti.Vector.zero(ti.f32, P)
                        J[0] = s * gx
                        J[1] = s * gy
                        J[2] = gy * du - gx * dv
                        J[3] = gx * du - gy * dv
                        J[4] = 3.0 * s * radial
                        J[5] = gx * dv + gy * du
                        J[6] = -du * radial
                        J[7] = -dv * radial
                        # ∂w = (∂X − x ∂Z, ∂Y − y ∂Z) / Z
                        J[8] = rho * s * gx * iz
                        J[9] = rho * s * gy * iz
                        J[10] = -rho * (gx * du + gy * dv) * iz
                        if ti.static(with_rho):
                            ge = (gx * (e0 - x * e2) + gy * (e1 - y * e2)) * iz
                            for k in ti.static(range(n_rho)):
                                f = 0.0
                                for i in ti.static(range(D1)):
                                    for j in ti.static(range(D1)):
                                        f += params[PARAMS_BASIS + k * MAX_MONOMIALS + i * D1 + j] * xp[i] * yp[j]
                                J[N_GEOMETRIC + N_EPIPOLE + k] = f * ge
                        for k in ti.static(range(NG)):
                            J[N_GEOMETRIC + N_EPIPOLE + NR + k] = phi[k] * c0
                        J[P - 1] = 1.0
                        w = robust_weight(r, sigma, kind)
                        idx = 0
                        for i in ti.static(range(P)):
                            wji = w * J[i]
                            for j in ti.static(range(i, P)):
                                racc[idx] += wji * J[j]
                                idx += 1
                            racc[NT + i] += wji * r
                        racc[NT + P + 0] += 1.0
                        if ti.abs(r) <= INLIER_C * sigma:
                            racc[NT + P + 1] += 1.0
                        racc[NT + P + 2] += r * r
                        k_bin = hoff + hist_bin(ti.abs(r))
                        work[k_bin] = work[k_bin] + 1.0  # band-owned: plain store, no atomic
                acc += racc
            for k in ti.static(range(NACC)):
                work[(1 + b) * NACC + k] = acc[k]
    ti.loop_config(serialize=True)
    for _ in range(1):
        for k in range(NACC):
            total = ti.cast(0.0, ti.f64)
            for b in range(nb):
                total += ti.cast(work[(1 + b) * NACC + k], ti.f64)
            work[k] = ti.cast(total, ti.f32)
        half = 0.5 * work[NT + P]
        cum = 0.0
        median = 0.0
        found = 0
        for k in range(HIST_BINS):
            count = 0.0
            for b in range(nb):
                count += work[hist0 + b * HIST_BINS + k]
            if found == 0 and count > 0.0 and cum + count >= half:
                median = hist_value(k, (half - cum) / count)
                found = 1
            cum += count
        work[NACC - 1] = median


@ti.kernel
def render_general(
    cur: ti.types.ndarray(dtype=ti.f32, ndim=2),
    params: ti.types.ndarray(dtype=ti.f32, ndim=1),
    out: ti.types.ndarray(dtype=ti.f32, ndim=2),
    degree: ti.template(),
    grid_rows: ti.template(),
    grid_cols: ti.template(),
):
    """`out[v − v0, u − u0] = S(p*) · I(w(p*)) + β` over the ROI under the warp (2); NaN where it leaves `cur`."""
    D1 = ti.static(degree + 1)
    u0 = ti.cast(params[PARAMS_ROI + 0], ti.i32)
    v0 = ti.cast(params[PARAMS_ROI + 1], ti.i32)
    bcx = params[PARAMS_BNORM + 0]
    bcy = params[PARAMS_BNORM + 1]
    bs = params[PARAMS_BNORM + 2]
    for rr, cc in ti.ndrange(out.shape[0], out.shape[1]):
        u = ti.cast(u0 + cc, ti.f32)
        v = ti.cast(v0 + rr, ti.f32)
        xp = _powers((u - bcx) / bs, degree)
        yp = _powers((v - bcy) / bs, degree)
        rho = 0.0
        for i in ti.static(range(D1)):
            for j in ti.static(range(D1)):
                rho += params[PARAMS_RHO + i * D1 + j] * xp[i] * yp[j]
        X, Y, Z = homography_apply(load_vector(params, PARAMS_G, 9), u, v)
        Z += rho * params[PARAMS_E + 2]
        iz = 1.0 / ti.select(Z > 1e-8, Z, 1.0)
        val, _gx, _gy, ok = cubic_sample(cur, (X + rho * params[PARAMS_E]) * iz, (Y + rho * params[PARAMS_E + 1]) * iz)
        ok = ok if Z > 1e-8 else 0
        gain, _phi = gain_at(load_vector(params, PARAMS_SPAN, 4),
                             load_vector(params, PARAMS_GAINS, grid_rows * grid_cols), u, v, grid_rows, grid_cols)
        out[rr, cc] = gain * val + params[PARAMS_BETA] if ok == 1 else ti.math.nan
