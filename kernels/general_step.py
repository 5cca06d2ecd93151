"""One robust Gauss-Newton step of general (non-planar) direct registration, eq. (2) `p ∝ G p* + ρ*(p*) e` with the
photometric model (4), fused: residuals, Jacobian columns, robust normal equations in one launch.

For every reference pixel `p* = (u, v)` of the region of interest (level pixels, pixel centres):
- warp: `P = G p* + ρ(p*) e = [X, Y, Z]`, `w = (X/Z, Y/Z)`; `ρ(p*) = Σ_m a_m x^i y^j` with `(x, y)` the basis
  normalisation of the reference pixel (`PARAMS_BNORM`) and `a` the monomial coefficients of the current `ρ*`;
- residual `r = S(p*) · I(w) + β − I*(p*)`;
- `I(w)` and its exact gradient `∇I(w)` from one bicubic interpolation (`cubic_sample`, 4×4 taps): Keys cubic
  convolution of the image, or (`spline` ≠ 0: `GeneralConfig.interpolation` "bspline", full resolution) the
  interpolating cubic B-spline from the image's prefiltered coefficients (`kernels.bspline`); a run-time argument
  choosing the taps' polynomial coefficients, so both share one compiled kernel (`KEYS`, `BSPLINE`). Bilinear
  interpolation's phase-dependent blur biased the optimum (gain 1.01–1.015 on unit-gain renders, warp 0.01–0.03 px
  off on the paper's trajectory); Keys brings the gain to 1.000–1.001 and lowers that warp error by 30–40 %; near
  the paper's equilibrium its own error still dominates the residual at the true warp on band-limited frames
  (`sim.freeflyer.render_camera`), which the B-spline, flat much closer to the Nyquist frequency, lowers 2–3×
  (0.23 → 0.07 grey levels RMS with a 1 px optical blur);
- image gradient in current pixels, mean of both sides (ESM-like): `g = ½ (S ∇I(w) + ∇I*(p*) A⁻¹)`, `A = ∂w/∂p*`
  (analytic, including `∇ρ`);
- Jacobian columns, in this order:
  - 8 sl(3) coordinates of a left increment `P ← N⁻¹ exp(Σ xᵢ Aᵢ) N P` (so `G ← M G`, `e ← M e`; `Aᵢ` =
    `ddvs_service.lie.SL3_GENERATORS`, `N` the normalisation `q = (p − c) / s` of the current-image point);
  - 3 epipole coordinates `e ← e + N⁻¹ δe'` (normalised units): `∂P = ρ N⁻¹ δe'`;
  - when `with_rho`: one per parallax basis function `φ_k = Σ_m B_km x^i y^j`: `∂P = φ_k e δc_k`;
  - gain nodes `φ_ij · I(w)` and the bias 1 (as `kernels.planar_step`).
  The pixel loop accumulates a per-row layout whose size does not grow with the basis or the gain grid's rows: on one
  row (`y` fixed) `φ_k = Σ_i C_ki x^i` with `C_ki = Σ_j B_kij y^j`, so it carries the `degree + 1` columns `x^i ge`
  (`ge` the image derivative along `e`) instead of the `n_rho` columns `φ_k ge`, and `φ_ij = a_i(v) b_j(u)` (the
  gain surface is separable), so it carries one column `b_j I(w)` per grid column instead of one per node.
  `fold_row` expands each row's sums into the output layout in run-time loops, every output column a combination of
  row columns through `C` and `a` (`_term`): one small loop nest for every specialisation, whatever its blocks;
- reference pixels masked by the caller (`planar_step.MASKED`) get weight 0, as do warps whose 4×4 taps leave the
  image (branch-free: the accumulation loop has no ndarray store and no branch, so LLVM vectorises it);
- robust weight and statistics exactly as `kernels.planar_step` (Huber/Tukey with a caller-given σ, valid and inlier
  counts, Σ r², the histogram of |r| of `planar_step.hist_bin` whose median gives the next MAD scale, over every
  valid pixel).

Reduction as in PLATFORM-NOTES: each thread owns a band of rows, sums a row into registers and folds it into its
band's partial in the work array (adds, not atomics: no other thread writes there); a serial pass adds the
partials. A band walks each row in tiles of `ROW_TILE` columns: the accumulation loop keeps the tile's |r| in a
thread-local buffer, which a second, scalar loop bins into the histogram (its stores are indexed by data, which would
stop the first loop's vectorisation; re-sampling there instead cost as much as the accumulation).
Validity tests combine with `&`, never `and`: Taichi lowers `and` to a branch, and that one branch kept LLVM from
vectorising the accumulation loop (docs/performance.md).
Compile time: Taichi's store-to-load forwarding costs about (local-variable accesses) × (kernel size), so the
kernel keeps its unrolled part to the one pixel loop (the Jacobian row and the per-row sums, plain scalar variables,
not vectors indexed by `ti.static` constants) and keeps no large thread-local array: the band partials and the
histogram live in the work array (docs/performance.md). Even so, the pixel loop's per-row sums (up to 230 on a
4-column grid with a degree-3 ρ*) made that pass most of a cold compile; `general_step` compiles without it and
without Taichi's other IR optimisations (`kernels.backend.compile_settings`), LLVM promoting the locals to registers
and simplifying instead: a third of the CPU time cold, the same sums up to float32 rounding, launches within a few
per cent (docs/results/speed.md).
One float32 parameter array in (`PARAMS_*`), one float32 work array out (`work_size`).
"""

import taichi as ti

from kernels.planar_step import (
    HIST_BINS,
    INLIER_C,
    MAX_BANDS,
    N_STATS,
    SATURATED,
    column_tents,
    finish_sums,
    hist_bin,
    reference_taps,
    robust_weight,
    row_gains,
    triangle_index,
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
PARAMS_DOMAIN = 48  # 4: x_lo, y_lo, x_hi, y_hi: where samples may fall (level pixels; a B-spline window's exact part)
PARAMS_RHO = 52  # 16: monomial coefficients a_m of ρ*, m = i·(degree + 1) + j for x^i y^j
PARAMS_BASIS = 68  # n_rho × 16: basis coefficients B_km (same monomial order)
N_GEOMETRIC = 8
N_EPIPOLE = 3
N_FIXED = N_GEOMETRIC + N_EPIPOLE  # columns that need no fold
ROW_TILE = 128  # columns per tile of a band's row: the length of the thread-local |r| buffer


def _tri(i: int, j: int, n: int) -> int:
    """Position of `(min(i, j), max(i, j))` in the row-major upper triangle of an `n × n` matrix."""
    i, j = min(i, j), max(i, j)
    return i * n - i * (i - 1) // 2 + j - i


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
    """float32 work array size for `n` columns: final sums, per-band partials, per-band histograms (the layout
    `planar_step.finish_sums` reads)."""
    return n_acc(n) * (1 + MAX_BANDS) + HIST_BINS * MAX_BANDS


@ti.func
def _powers(t: ti.f32, degree: ti.template()):
    p = ti.Vector.zero(ti.f32, degree + 1)
    p[0] = 1.0
    for i in ti.static(range(1, degree + 1)):
        p[i] = p[i - 1] * t
    return p


# Cubic weights of taps −1, 0, 1, 2 at fraction t ∈ [0, 1) as polynomials `Σ_k c_k t^k`: row k holds the four taps'
# coefficients of t^k.
KEYS = ((0.0, 1.0, 0.0, 0.0), (-0.5, 0.0, 0.5, 0.0), (1.0, -2.5, 2.0, -0.5), (-0.5, 1.5, -1.5, 0.5))  # a = −½
BSPLINE = ((1 / 6, 2 / 3, 1 / 6, 0.0), (-0.5, 0.0, 0.5, 0.0), (0.5, -1.0, 0.5, 0.0), (-1 / 6, 0.5, -0.5, 1 / 6))


@ti.func
def _weights(t: ti.f32, spline: ti.i32):
    """Weights of taps −1, 0, 1, 2 at fraction `t` ∈ [0, 1) and their derivatives along `t` (Horner): the cubic
    B-spline's when `spline` ≠ 0, else Keys cubic convolution's (a = −½). A run-time choice of coefficients
    (loop-invariant selects, no branch), so that one compiled kernel samples either way and the pixel loop stays
    vectorised."""
    b = spline != 0
    c0 = ti.select(b, ti.Vector(BSPLINE[0]), ti.Vector(KEYS[0]))
    c1 = ti.select(b, ti.Vector(BSPLINE[1]), ti.Vector(KEYS[1]))
    c2 = ti.select(b, ti.Vector(BSPLINE[2]), ti.Vector(KEYS[2]))
    c3 = ti.select(b, ti.Vector(BSPLINE[3]), ti.Vector(KEYS[3]))
    return ((c3 * t + c2) * t + c1) * t + c0, (3.0 * c3 * t + 2.0 * c2) * t + c1


@ti.func
def cubic_sample(img: ti.template(), x: ti.f32, y: ti.f32, spline: ti.i32, domain: ti.template()):
    """Bicubic sample at column `x`, row `y` and its exact gradient (grey levels per pixel): Keys cubic convolution of
    the image `img`, or, when `spline` ≠ 0, the cubic B-spline whose coefficients `img` holds (`kernels.bspline`).

    Returns `(value, d/dx, d/dy, ok)`; `ok = 0` (zeros) unless the 4×4 taps lie inside, i.e. `1 ≤ x, y` and
    `x ≤ W − 2`, `y ≤ H − 2` (the same domain as a bilinear sample with ±1 px central differences), and the point
    lies in `domain = (x_lo, y_lo, x_hi, y_hi)` (where a windowed prefilter left exact coefficients). Branch-free:
    the taps are read at the clamped point (always in bounds) and the result is selected, so that a pixel loop
    calling it can be vectorised."""
    h = img.shape[0]
    w = img.shape[1]
    inside = ((x >= ti.max(1.0, domain[0])) & (y >= ti.max(1.0, domain[1])) & (x <= ti.min(w - 2.0, domain[2]))
              & (y <= ti.min(h - 2.0, domain[3])))
    xc = ti.min(ti.max(x, 1.0), w - 2.0)
    yc = ti.min(ti.max(y, 1.0), h - 2.0)
    x0 = ti.max(ti.min(ti.cast(ti.floor(xc), ti.i32), w - 3), 1)  # integer clamp too: NaN casts stay in bounds
    y0 = ti.max(ti.min(ti.cast(ti.floor(yc), ti.i32), h - 3), 1)
    wx, dx = _weights(xc - x0, spline)
    wy, dy = _weights(yc - y0, spline)
    val = 0.0
    gx = 0.0
    gy = 0.0
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
    return ti.select(inside, val, 0.0), ti.select(inside, gx, 0.0), ti.select(inside, gy, 0.0), ti.select(inside, 1, 0)


@ti.func
def parallax_at(rho_coeffs: ti.template(), xp: ti.template(), yp: ti.template(), degree: ti.template()):
    """`ρ(p*) = Σ a_ij x^i y^j` and its derivatives along the normalised basis coordinates `x`, `y`."""
    rho = 0.0
    rho_x = 0.0
    rho_y = 0.0
    for i in ti.static(range(degree + 1)):
        for j in ti.static(range(degree + 1)):
            a = rho_coeffs[i * (degree + 1) + j]
            rho += a * xp[i] * yp[j]
            if ti.static(i > 0):
                rho_x += a * i * xp[i - 1] * yp[j]
            if ti.static(j > 0):
                rho_y += a * j * xp[i] * yp[j - 1]
    return rho, rho_x, rho_y


@ti.func
def warp_point(G: ti.template(), e: ti.template(), u: ti.i32, v: ti.i32, rho: ti.f32):
    """`P = G p* + ρ e` dehomogenised: `(x, y, 1/Z, ok_z)`, `ok_z` false (and `1/Z` = 1) when `Z ≤ 1e-8`."""
    X, Y, Z = homography_apply(G, ti.cast(u, ti.f32), ti.cast(v, ti.f32))
    X += rho * e[0]
    Y += rho * e[1]
    Z += rho * e[2]
    ok_z = Z > 1e-8
    iz = 1.0 / ti.select(ok_z, Z, 1.0)
    return X * iz, Y * iz, iz, ok_z


@ti.func
def pixel_terms(ref: ti.template(), cur: ti.template(), G: ti.template(), e: ti.template(), rho_coeffs: ti.template(),
                span: ti.template(), h: ti.template(), v: ti.i32, u: ti.i32, yp: ti.template(), bcx: ti.f32,
                bs: ti.f32, beta: ti.f32, degree: ti.template(), grid_cols: ti.template(), spline: ti.i32,
                domain: ti.template()):
    """Everything one reference pixel `(u, v)` contributes, before the Jacobian: `(ok, r, I(w), ∂I/∂x, ∂I/∂y, x, y,
    1/Z, ρ, ∂ρ/∂u, ∂ρ/∂v, x-powers, ∂I*/∂u, ∂I*/∂v, S, b)` (`yp`: powers of the row's basis coordinate; `h`, `b`:
    the row's column gains and the column tents, `planar_step.row_gains` / `column_tents`).

    `ok` is false where a reference tap is masked, `Z ≤ 1e-8` or the 4×4 taps leave `cur` or the sample leaves
    `domain` (`cubic_sample`) or lies on the 8-bit ceiling (`planar_step.SATURATED`); the image values and
    gradients are then 0 (finite, so that a weight of 0 cancels them). Loads and selects only: vectorisable."""
    ir, gxr, gyr, ref_ok = reference_taps(ref, v, u)
    xp = _powers((u - bcx) / bs, degree)
    rho, rho_x, rho_y = parallax_at(rho_coeffs, xp, yp, degree)
    x, y, iz, ok_z = warp_point(G, e, u, v, rho)
    c0, cgx, cgy, inside = cubic_sample(cur, x, y, spline, domain)
    ok = ref_ok & ok_z & (inside == 1) & (c0 < SATURATED)
    gain, b = column_tents(span, h, ti.cast(u, ti.f32), grid_cols)
    r = gain * c0 + beta - ir
    return (ok, ti.select(ok, r, 0.0), ti.select(ok, c0, 0.0), ti.select(ok, cgx, 0.0), ti.select(ok, cgy, 0.0), x, y,
            iz, rho, rho_x / bs, rho_y / bs, xp, ti.select(ok, gxr, 0.0), ti.select(ok, gyr, 0.0), gain, b)


@ti.func
def _sym(i: ti.i32, j: ti.i32, n: ti.template()) -> ti.i32:
    """Upper-triangle index of entry `(i, j)` or `(j, i)` of a symmetric `n × n` matrix (`triangle_index`)."""
    return triangle_index(ti.min(i, j), ti.max(i, j), n)


@ti.func
def _add(work: ti.template(), k: ti.i32, value: ti.f32):
    """`work[k] += value` as a load and a store: Taichi makes `+=` on an ndarray an atomic add (a compare-and-swap
    loop for floats), and only this band's thread writes there."""
    work[k] = work[k] + value


@ti.func
def row_basis(cki: ti.template(), params: ti.template(), yb: ti.f32, n_rho: ti.template(), n_x: ti.template(),
              degree: ti.template()):
    """`cki[k·n_x + i] = C_ki = Σ_j B_kij y^j`: ρ* basis function k along the row whose basis coordinate is `yb`,
    `φ_k = Σ_i C_ki x^i` (`B`: `params[PARAMS_BASIS:]`)."""
    D1 = ti.static(degree + 1)
    for k in range(n_rho):
        for i in range(n_x):
            c = 0.0
            yj = 1.0
            for j in range(D1):
                c += params[PARAMS_BASIS + k * MAX_MONOMIALS + i * D1 + j] * yj
                yj *= yb
            cki[k * n_x + i] = c


@ti.func
def _terms(o: ti.i32, n_rho: ti.template(), n_x: ti.template()) -> ti.i32:
    """Number of row columns output column `o` combines (`_term`)."""
    return ti.select((o >= N_FIXED) & (o < N_FIXED + n_rho), n_x, 1)


@ti.func
def _term(o: ti.i32, t: ti.i32, cki: ti.template(), a_rows: ti.template(), n_rho: ti.template(), n_x: ti.template(),
          grid_rows: ti.template(), grid_cols: ti.template()):
    """`(row column, coefficient)` of term `t` of output column `o` on one row. Output layout: 11 geometric/epipole
    columns, `n_rho` ρ* columns, the R·C gain nodes row-major, the bias; per-row layout: 11, `n_x` columns
    `x^i ge`, one column `b_j I(w)` per gain-grid column, the bias. A geometric, epipole or bias column is its row
    column; gain node (i, j) is `a_i` × column j (`a_rows`: the row tents); ρ* column k is `Σ_i C_ki` × column
    `x^i ge` (`row_basis`). Selects, no branches (each branch would add nodes to Taichi's control-flow analysis)."""
    SO = ti.static(N_FIXED + n_rho)  # first gain node of the output
    gain = (o >= SO) & (o < SO + grid_rows * grid_cols)
    rho = (o >= N_FIXED) & (o < SO)
    node = ti.min(ti.max(o - SO, 0), grid_rows * grid_cols - 1)
    k = ti.min(ti.max((o - N_FIXED) * n_x + t, 0), ti.static(max(n_rho * n_x, 1) - 1))
    column = ti.select(gain, N_FIXED + n_x + node % grid_cols, ti.select(rho, N_FIXED + t, o))
    column = ti.select(o >= SO + grid_rows * grid_cols, N_FIXED + n_x + grid_cols, column)
    coef = ti.select(gain, a_rows[node // grid_cols], ti.select(rho, cki[k], 1.0))
    return column, coef


@ti.func
def _inner(row: ti.template(), column_o: ti.i32, coef_o: ti.f32, ko: ti.i32, count: ti.i32, cki: ti.template(),
           column: ti.i32, n_row: ti.template()) -> ti.f32:
    """`Σ_t T[o, t] R[·, column]` over the terms of output column `o` (first term `coef_o` × row column
    `column_o`, the others ρ* terms `cki[ko + t]` × `x^t ge`)."""
    total = coef_o * row[_sym(column_o, column, n_row)]
    for t in range(1, count):
        total += cki[ko + t] * row[_sym(N_FIXED + t, column, n_row)]
    return total


@ti.func
def fold_row(work: ti.template(), abase: ti.i32, row: ti.template(), cki: ti.template(), a_rows: ti.template(),
             firsts: ti.template(), first_coefs: ti.template(), n_rho: ti.template(), n_x: ti.template(),
             grid_rows: ti.template(), grid_cols: ti.template()):
    """Add one row's sums `row` (per-row layout, `_term`: upper triangle of the row's `JᵀWJ`, its `JᵀWr`, 3
    statistics) into the band partial at `work[abase:]` (output layout): with `T` the row's expansion (`_term`) as
    a matrix, `T R Tᵀ` and `T g`, entry by entry, in run-time loops over the entries' terms (one small loop nest
    for every specialisation; only ρ* columns have more than one term). `firsts`, `first_coefs`: scratch for the
    first term of every output column."""
    P = ti.static(N_FIXED + n_rho + grid_rows * grid_cols + 1)
    PR = ti.static(N_FIXED + n_x + grid_cols + 1)
    NT = ti.static(P * (P + 1) // 2)
    NTR = ti.static(PR * (PR + 1) // 2)
    for o in range(P):
        firsts[o], first_coefs[o] = _term(o, 0, cki, a_rows, n_rho, n_x, grid_rows, grid_cols)
    for o in range(P):
        count = _terms(o, n_rho, n_x)
        ko = (o - N_FIXED) * n_x
        column_o = firsts[o]
        coef_o = first_coefs[o]
        for f in range(o, P):
            total = first_coefs[f] * _inner(row, column_o, coef_o, ko, count, cki, firsts[f], PR)
            for t in range(1, _terms(f, n_rho, n_x)):
                total += cki[(f - N_FIXED) * n_x + t] * _inner(row, column_o, coef_o, ko, count, cki, N_FIXED + t, PR)
            _add(work, abase + triangle_index(o, f, P), total)
        g = coef_o * row[NTR + column_o]
        for t in range(1, count):
            g += cki[ko + t] * row[NTR + N_FIXED + t]
        _add(work, abase + NT + o, g)
    for k in range(N_STATS - 1):
        _add(work, abase + NT + P + k, row[NTR + PR + k])


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
    spline: ti.i32,
):
    """Residuals, robust weights and normal equations of eq. (5) under the warp (2) (module docstring); `cur` holds
    the current image's cubic B-spline coefficients when `spline` ≠ 0, else the image itself (Keys interpolation).
    `spline` is a run-time argument: Keys and B-spline sampling share one compiled kernel per (degree, ρ* columns,
    gain grid)."""
    NR = ti.static(n_rho if with_rho else 0)
    P = ti.static(N_FIXED + NR + grid_rows * grid_cols + 1)
    NT = ti.static(P * (P + 1) // 2)
    NACC = ti.static(NT + P + N_STATS)
    D1 = ti.static(degree + 1)
    NX = ti.static(D1 if with_rho else 0)  # per-row ρ* columns x^i ge (module docstring)
    PR = ti.static(N_FIXED + NX + grid_cols + 1)  # per-row layout
    NTR = ti.static(PR * (PR + 1) // 2)
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
    e = load_vector(params, PARAMS_E, 3)
    rho_coeffs = load_vector(params, PARAMS_RHO, D1 * D1)
    beta = params[PARAMS_BETA]
    sigma = params[PARAMS_SIGMA]
    kind = ti.cast(params[PARAMS_ROBUST], ti.i32)
    G = load_vector(params, PARAMS_G, 9)
    span = load_vector(params, PARAMS_SPAN, 4)
    gains = load_vector(params, PARAMS_GAINS, grid_rows * grid_cols)
    domain = load_vector(params, PARAMS_DOMAIN, 4)
    # The bands' partial sums and |r| histograms start at 0; each region is contiguous over the `nb` bands, so one
    # serial loop over a run-time count clears it (a loop of a constant count per band: LLVM unrolls it into
    # hundreds of stores to generate at every start).
    ti.loop_config(serialize=True)
    for k in range(nb * NACC):
        work[NACC + k] = 0.0
    ti.loop_config(serialize=True)
    for k in range(nb * HIST_BINS):
        work[NACC * (1 + MAX_BANDS) + k] = 0.0
    for it in range(nb * 512):  # one band per 512-iteration block (PLATFORM-NOTES)
        if it % 512 == 0:
            b = it // 512
            abase = (1 + b) * NACC  # this band's partial sums, then its |r| histogram
            hbase = NACC * (1 + MAX_BANDS) + b * HIST_BINS
            magnitude = ti.Vector.zero(ti.f32, ROW_TILE)  # |r| of the tile row being accumulated
            cki = ti.Vector.zero(ti.f32, max(NR * NX, 1))  # the ρ* basis along the row (`row_basis`)
            firsts = ti.Vector.zero(ti.i32, P)  # scratch of `fold_row`
            first_coefs = ti.Vector.zero(ti.f32, P)
            rows = v1 - v0 + 1
            first = v0 + b * rows // nb
            for v in range(first, v0 + (b + 1) * rows // nb):
                racc = [0.0] * (NTR + PR + N_STATS - 1)  # this row's sums, per-row layout: scalar variables
                yp = _powers((v - bcy) / bs, degree)
                a_rows, h = row_gains(span, gains, ti.cast(v, ti.f32), grid_rows, grid_cols)
                for tile in range((u1 - u0 + ROW_TILE) // ROW_TILE):
                    ut0 = u0 + tile * ROW_TILE
                    ut1 = ti.min(ut0 + ROW_TILE - 1, u1)
                    # Loads, register sums and stores into the thread-local `magnitude` only (no ndarray store,
                    # no branch): LLVM vectorises this loop.
                    for u in range(ut0, ut1 + 1):
                        ok, r, c0, cgx, cgy, x, y, iz, rho, rho_u, rho_v, xp, gxr, gyr, gain, bt = pixel_terms(
                            ref, cur, G, e, rho_coeffs, span, h, v, u, yp, bcx, bs, beta, degree, grid_cols, spline,
                            domain)
                        # A = ∂w/∂p*, columns from ∂P/∂u = G[:, 0] + ρ_u e and ∂P/∂v = G[:, 1] + ρ_v e
                        pxu = G[0] + rho_u * e[0]
                        pyu = G[3] + rho_u * e[1]
                        pzu = G[6] + rho_u * e[2]
                        pxv = G[1] + rho_v * e[0]
                        pyv = G[4] + rho_v * e[1]
                        pzv = G[7] + rho_v * e[2]
                        a00 = (pxu - x * pzu) * iz
                        a10 = (pyu - y * pzu) * iz
                        a01 = (pxv - x * pzv) * iz
                        a11 = (pyv - y * pzv) * iz
                        det = a00 * a11 - a01 * a10
                        invertible = ti.abs(det) > 1e-12
                        idet = 1.0 / ti.select(invertible, det, 1.0)
                        gx = gain * cgx
                        gy = gain * cgy
                        gx = ti.select(invertible, 0.5 * (gx + (gxr * a11 - gyr * a10) * idet), gx)
                        gy = ti.select(invertible, 0.5 * (gy + (gyr * a00 - gxr * a01) * idet), gy)
                        du = x - cx  # = s · q_u in the current image
                        dv = y - cy
                        radial = (gx * du + gy * dv) / s
                        ge = (gx * (e[0] - x * e[2]) + gy * (e[1] - y * e[2])) * iz  # image derivative along e
                        # The row's Jacobian columns (a list of scalars: a vector would cost compile time, above);
                        # sl(3), then the epipole: ∂w = (∂X − x ∂Z, ∂Y − y ∂Z) / Z.
                        J = ([s * gx, s * gy, gy * du - gx * dv, gx * du - gy * dv, 3.0 * s * radial,
                              gx * dv + gy * du, -du * radial, -dv * radial,
                              rho * s * gx * iz, rho * s * gy * iz, -rho * (gx * du + gy * dv) * iz]
                             + [xp[i] * ge for i in ti.static(range(NX))]
                             + [bt[j] * c0 for j in ti.static(range(grid_cols))] + [1.0])
                        valid = ti.select(ok, 1.0, 0.0)
                        w = valid * robust_weight(r, sigma, kind)
                        for i in ti.static(range(PR)):
                            wji = w * J[i]
                            for j in ti.static(range(i, PR)):
                                racc[ti.static(_tri(i, j, PR))] += wji * J[j]
                            racc[NTR + i] += wji * r
                        racc[NTR + PR + 0] += valid
                        racc[NTR + PR + 1] += ti.select(ti.abs(r) <= INLIER_C * sigma, valid, 0.0)
                        racc[NTR + PR + 2] += valid * r * r
                        magnitude[u - ut0] = ti.select(ok, ti.abs(r), -1.0)
                    # The |r| histogram stores into an array indexed by data, so it gets its own (scalar) loop,
                    # over the tile row's |r| kept above (-1: invalid pixel).
                    for k in range(ut1 - ut0 + 1):
                        a = magnitude[k]
                        if a >= 0.0:
                            _add(work, hbase + hist_bin(a), 1.0)
                # Fold the row's sums into the band's: φ_k = Σ_i C_ki x^i, φ_ij = a_i b_j on this row.
                row_basis(cki, params, (v - bcy) / bs, NR, NX, degree)
                row = ti.Vector(racc)  # the fold indexes it at run time; the pixel loop's sums stay in registers
                fold_row(work, abase, row, cki, a_rows, firsts, first_coefs, NR, NX, grid_rows, grid_cols)
    finish_sums(work, NACC, params, PARAMS_BANDS)
