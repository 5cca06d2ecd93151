"""One robust ESM Gauss-Newton step of planar direct registration (paper eqs. (4)–(5) with `ρ* ≡ 0`), fused.

For every reference pixel `p*` of the region of interest (level pixels, `u` = column, `v` = row, pixel centres):
- residual (eq. (4) vs (5)): `r = S(p*) · I(w(G, p*)) + β − I*(p*)`, `w(G, p*)` the dehomogenised `G · [u, v, 1]`;
- Jacobian row over the parameter layout `[x_1..x_8 (sl(3)), gain nodes s_00..s_{R−1,C−1}, β]`:
  - geometric block, ESM: `½ (S ∇Iw + ∇I*) · ∂w(N⁻¹ exp(Σ xᵢ Aᵢ) N, p*)/∂x` at `x = 0`, where `Iw = I ∘ w(G, ·)`
    is the warped current image (central differences of five warped samples), `∇I*` the reference's central
    differences, `Aᵢ` = `ddvs_service.lie.SL3_GENERATORS` and `N` the normalisation `q = (p − c) / s`;
  - gain block: `φ_k(p*) · Iw` with `φ_k` the bilinear (tent) basis of the R×C gain grid;
  - bias: 1;
- robust weight `w(r / σ)` (0 none, 1 Huber k = 1.345, 2 Tukey c = 4.685), σ supplied by the caller;
- sums: upper triangle of `Jᵀ W J` (built per row from 12 moments, see `accumulate_row`), `Jᵀ W r`, statistics (valid
  and inlier counts, Σ r²), and a histogram of `|r|` binned on its float32 bits (16 bins per octave, no logarithm)
  whose median gives the next MAD scale — over every other pixel of every other row, valid where the pixel's own
  reference and warped values are (a quarter of the ROI sets the scale as well, at a fraction of the cost).

Pixels whose reference value or reference neighbours are masked (set to `MASKED`, ≤ `MASK_LIMIT` after
filtering) or whose five warped samples are not all inside the current image get weight 0. Reductions follow
PLATFORM-NOTES: each thread owns a band of rows, warps them (and copies the reference's) into thread-local rolling
buffers, accumulates in registers row by row and writes one partial; a serial tail adds the partials. The warp and
accumulation loops store only into thread-local arrays and have no data-dependent branch, so LLVM vectorises them
(docs/performance.md).
Parameters come in one float32 array (`PARAMS_*` offsets) and every result goes to one float32 work array
(`work_size`).

Robot axis: `planar_step` takes stacks — images `[k, row, col]`, parameters and work `[k, i]` — and evaluates every
robot `k` whose band count `params[k, PARAMS_BANDS]` is positive in the same launch (its bands are threads beside
the other robots'; a robot with 0 bands is skipped and its work row left as it was). One robot's evaluation is a
stack of one: the same source, the same arithmetic in the same order, so a robot's sums do not depend on which
other robots share its launch (`registration.lockstep` batches the fleet's robots with it).
"""


import functools
import warnings

import taichi as ti

from kernels.sampling import (
    entry,
    grid_coordinate,
    homography_apply,
    image_size,
    load_vector,
    projected_sample,
    put_entry,
    stack_size,
    tent,
    texel,
)

# The accumulators are unrolled on purpose (they live in registers); silence Taichi's compile-time-length warning.
warnings.filterwarnings("ignore", message="You are unrolling more than", category=SyntaxWarning)

# Offsets in the float32 parameter array.
PARAMS_G = 0  # 9: G row-major, level pixels of the reference → level pixels of the current image
PARAMS_NORM = 9  # 3: cx, cy, s of the normalisation q = (p − c) / s used by the sl(3) increment
PARAMS_ROI = 12  # 4: u0, v0, u1, v1 (inclusive integer bounds of the ROI at this level)
PARAMS_SPAN = 16  # 4: x0, y0, x1, y1 of the gain-grid node span (level pixels)
PARAMS_BETA = 20  # 1: bias β (grey levels)
PARAMS_SIGMA = 21  # 1: robust scale σ (grey levels)
PARAMS_ROBUST = 22  # 1: 0 none, 1 Huber, 2 Tukey
PARAMS_BANDS = 23  # 1: number of row bands (≤ MAX_BANDS)
PARAMS_GAINS = 24  # R·C gain node values, row-major

MASKED = -1.0e7  # reference value of excluded pixels (NaN tests are unreliable under Taichi's fast math)
MASK_LIMIT = -1.0e5  # any pyramid tap on a MASKED pixel keeps the value below this
N_GEOMETRIC = 8
N_STATS = 4  # n_valid, n_inliers, Σ r², median |r| (the last one only in the final sums)
MAX_BANDS = 32
HIST_LOG2_MIN = -8  # |r| histogram of planar_step: octaves 2^-8 … 2^12 grey levels, HIST_SUB linear bins each
HIST_SUB_BITS = 4
HIST_SUB = 1 << HIST_SUB_BITS
HIST_BINS = 20 * HIST_SUB
OUTSIDE = MASKED  # warped-current value where the warp leaves the current image
# A warped-current sample at least this high lies on the 8-bit ceiling (all its taps at 255, in grey levels or in
# irradiance 255 (I/255)^γ alike): the sensor clipped it, eq. (4) does not hold there, and it counts as invalid.
SATURATED = 254.5
HUBER_K = 1.345
TUKEY_C = 4.685
INLIER_C = TUKEY_C  # |r| ≤ 4.685 σ counts as an inlier whatever the loss


def n_params(grid_rows: int, grid_cols: int) -> int:
    """Number of unknowns: 8 sl(3) coordinates, one gain per grid node, one bias."""
    return N_GEOMETRIC + grid_rows * grid_cols + 1


def n_acc(n: int) -> int:
    """Length of one accumulator: upper triangle of `JᵀWJ`, `JᵀWr`, statistics."""
    return n * (n + 1) // 2 + n + N_STATS


def work_size(n: int) -> int:
    """Size of the float32 work array for `n` unknowns: final sums, per-band partials, per-band histograms."""
    return n_acc(n) * (1 + MAX_BANDS) + HIST_BINS * MAX_BANDS


@ti.func
def robust_weight(r: ti.f32, sigma: ti.f32, kind: ti.i32) -> ti.f32:
    """IRLS weight `w(r)` of the M-estimator `kind` (0 none, 1 Huber, 2 Tukey) with scale `sigma` (grey levels).

    Branch-free (selects only), so that a pixel loop calling it can be vectorised."""
    a = ti.abs(r)
    k = HUBER_K * sigma
    huber = ti.select(a > k, k / ti.max(a, 1e-30), 1.0)
    c = TUKEY_C * sigma
    t = 1.0 - (r / c) ** 2
    tukey = ti.select(a < c, t * t, 0.0)
    return ti.select(kind == 1, huber, ti.select(kind == 2, tukey, 1.0))


@ti.func
def gain_at(span: ti.template(), gains: ti.template(), u: ti.f32, v: ti.f32, grid_rows: ti.template(),
            grid_cols: ti.template()):
    """Bilinear gain surface `S(u, v)` and the node weights `φ` (row-major vector of length R·C), from the node span
    `params[PARAMS_SPAN:+4]` and the node values `params[PARAMS_GAINS:+R·C]` (both read with `load_vector`)."""
    tc = grid_coordinate(u, span[0], span[2], grid_cols)
    tr = grid_coordinate(v, span[1], span[3], grid_rows)
    phi = ti.Vector.zero(ti.f32, grid_rows * grid_cols)
    gain = 0.0
    for i in ti.static(range(grid_rows)):
        for j in ti.static(range(grid_cols)):
            f = tent(tr, i) * tent(tc, j)
            phi[i * grid_cols + j] = f
            gain += f * gains[i * grid_cols + j]
    return gain, phi


@ti.func
def row_gains(span: ti.template(), gains: ti.template(), v: ti.f32, grid_rows: ti.template(),
              grid_cols: ti.template()):
    """The gain surface along reference row `v`, factored: the row tents `a_i = tent(t_r(v), i)` and the column gains
    `h_j = Σ_i a_i s_ij`, so that `S(u, v) = Σ_j b_j(u) h_j` and `φ_ij(u, v) = a_i b_j(u)` (`column_tents`)."""
    tr = grid_coordinate(v, span[1], span[3], grid_rows)
    a = ti.Vector.zero(ti.f32, grid_rows)
    h = ti.Vector.zero(ti.f32, grid_cols)
    for i in ti.static(range(grid_rows)):
        a[i] = tent(tr, i)
        for j in ti.static(range(grid_cols)):
            h[j] += a[i] * gains[i * grid_cols + j]
    return a, h


@ti.func
def column_tents(span: ti.template(), h: ti.template(), u: ti.f32, grid_cols: ti.template()):
    """`(S(u, v), b)`: the gain at column `u` of the row whose column gains are `h` (`row_gains`) and the column
    tents `b_j = tent(t_c(u), j)`."""
    tc = grid_coordinate(u, span[0], span[2], grid_cols)
    b = ti.Vector.zero(ti.f32, grid_cols)
    gain = 0.0
    for j in ti.static(range(grid_cols)):
        b[j] = tent(tc, j)
        gain += b[j] * h[j]
    return gain, b


def _triangle_index(e: int, f: int, n: int) -> int:
    """Index of entry `(e, f)`, `e ≤ f`, in the row-major upper triangle of an `n × n` matrix."""
    return e * n - e * (e - 1) // 2 + f - e


# In a row (`dv = v − cy` fixed) the geometric Jacobian is `J_geo = C(dv) · b`, `b = [gx, gy, gx du, gy du, gx du²]`
# (`du = u − cx`; rows of `C`: the `J[0…7]` of the module docstring). `C` is sparse: row a lists (basis index q,
# coefficient index into `row_coefficients`).
C_SPARSE = (
    ((0, 0),),  # s gx
    ((1, 0),),  # s gy
    ((0, 1), (3, 2)),  # gy du − dv gx
    ((1, 1), (2, 2)),  # gx du − dv gy
    ((1, 3), (2, 4)),  # 3 (gx du + dv gy)
    ((0, 5), (3, 2)),  # dv gx + gy du
    ((3, 6), (4, 7)),  # −(gx du² + dv gy du) / s
    ((1, 8), (2, 6)),  # −(dv gx du + dv² gy) / s
)
B_GY = (0, 1, 0, 1, 0)  # basis term b_q is gx·du^k (0) or gy·du^k (1) …
B_POW = (0, 0, 1, 1, 2)  # … with k = B_POW[q]
MOMENT_OFFSET = (0, 5, 9)  # moments: Σ w gx² du^k (k ≤ 4), Σ w gx gy du^k (k ≤ 3), Σ w gy² du^k (k ≤ 2)
N_MOMENTS = 12


def _moment_index(p: int, q: int) -> int:
    """Index of `Σ w b_p b_q` in the 12 row moments."""
    return MOMENT_OFFSET[B_GY[p] + B_GY[q]] + B_POW[p] + B_POW[q]


@functools.cache
def _geometric_entries(n: int) -> tuple[tuple[tuple[int, tuple[tuple[int, int, int], ...]], ...], ...]:
    """The geometric block of the upper triangle of `JᵀWJ` for `n` unknowns, row `g` by row: each entry `(g, c ≥ g)`
    as its index and the terms `(i, j, m)` whose `coef[i] · coef[j] · moments[m]` it sums (`accumulate_row`:
    `C (Σ w b bᵀ) Cᵀ` over the pairs of `C_SPARSE[g]` and `C_SPARSE[c]`). Tabulated in Python so that Taichi's front
    end, which unrolls these sums at every compile (every start, offline cache or not), walks one statement per term
    and calls no function there."""
    return tuple(tuple((_triangle_index(g, c, n),
                        tuple((i, j, _moment_index(p, q)) for p, i in C_SPARSE[g] for q, j in C_SPARSE[c]))
                       for c in range(g, N_GEOMETRIC))
                 for g in range(N_GEOMETRIC))


@ti.func
def triangle_index(e: ti.i32, f: ti.i32, n: ti.template()) -> ti.i32:
    """`_triangle_index` at run time."""
    return e * n - e * (e - 1) // 2 + f - e


@ti.func
def accumulate_row(acc: ti.template(), moments, cross_c, photo_c, photo_cb, cross_b, w_sum: ti.f32, gb, ge_c,
                   r_sum: ti.f32, stats, a, dv: ti.f32, s: ti.f32, grid_rows: ti.template(),
                   grid_cols: ti.template()):
    """Add one row's contribution to the accumulator `acc` (upper triangle of `JᵀWJ`, `JᵀWr`, statistics) from the
    row's sums.

    Geometric block: `J_geo = C(dv) · b` (see `C_SPARSE`), so `C (Σ w b bᵀ) Cᵀ` needs only the 12 moments of
    `Σ w b bᵀ`, and `JᵀWr` the 5 sums `gb = Σ w r b` (a third of the per-pixel multiply-adds of the full outer
    product). Photometric columns `E = [φ_00 Iw … φ_{R−1,C−1} Iw, 1]` with `φ_ij = a_i b_j` and `a` constant along the
    row (`row_gains`): `Σ w E_ij b_q = a_i Σ w b_j Iw b_q` (`cross_c`), `Σ w E_ij E_kl = a_i a_k Σ w b_j b_l Iw²`
    (`photo_c`, upper triangle over the columns), `Σ w E_ij = a_i Σ w b_j Iw` (`photo_cb`), `Σ w r E_ij =
    a_i Σ w r b_j Iw` (`ge_c`); the bias column's `Σ w b_q` (`cross_b`), `Σ w`, `Σ w r`. The pixel loop thus carries
    sums for one row of grid nodes, and the gain nodes are expanded here in a loop, not unrolled: the compiled
    code does not grow with the grid (a 4×4 grid's unrolled expansion took minutes to compile)."""
    C = ti.static(grid_cols)
    M = ti.static(grid_rows * grid_cols + 1)
    P = ti.static(N_GEOMETRIC + M)
    NT = ti.static(P * (P + 1) // 2)
    si = 1.0 / s
    coef = ti.Vector([s, -dv, 1.0, 3.0 * dv, 3.0, dv, -dv * si, -si, -dv * dv * si])
    for g, entries in ti.static(enumerate(_geometric_entries(P))):
        for t, terms in ti.static(entries):
            total = 0.0
            for i, j, m in ti.static(terms):
                total += coef[i] * coef[j] * moments[m]
            acc[t] += total
        bias_total = 0.0
        g_total = 0.0
        for p, i in ti.static(C_SPARSE[g]):
            bias_total += coef[i] * cross_b[p]
            g_total += coef[i] * gb[p]
        acc[ti.static(_triangle_index(g, P - 1, P))] += bias_total
        acc[NT + g] += g_total
    for e in range(M - 1):  # the gain nodes, row-major (i, j)
        ai = a[e // C]
        j = e % C
        node = N_GEOMETRIC + e
        for g in ti.static(range(N_GEOMETRIC)):
            total = 0.0
            for p, i in ti.static(C_SPARSE[g]):
                total += coef[i] * cross_c[j, p]
            acc[triangle_index(g, node, P)] += ai * total
        for f in range(e, M - 1):
            l = f % C
            jl = triangle_index(ti.min(j, l), ti.max(j, l), C)
            acc[triangle_index(node, N_GEOMETRIC + f, P)] += ai * a[f // C] * photo_c[jl]
        acc[triangle_index(node, P - 1, P)] += ai * photo_cb[j]
        acc[NT + node] += ai * ge_c[j]
    acc[ti.static(_triangle_index(P - 1, P - 1, P))] += w_sum
    acc[NT + P - 1] += r_sum
    for k in ti.static(range(3)):
        acc[NT + P + k] += stats[k]


@ti.func
def reference_taps(ref: ti.template(), v: ti.i32, u: ti.i32):
    """`I*(p*)` and its central differences `(∂u, ∂v)` at reference pixel `(u, v)` (one-sided at the image border);
    `ok` is false when one of the five taps is masked (≤ `MASK_LIMIT`). Loads and selects only."""
    ul, ur, vu, vd = tap_bounds(ref, v, u)
    return tap_differences(ref[v, u], ref[v, ul], ref[v, ur], ref[vu, u], ref[vd, u], ul, ur, vu, vd)


@ti.func
def tap_bounds(ref: ti.template(), v: ti.i32, u: ti.i32):
    """Columns `ul`, `ur` and rows `vu`, `vd` of the neighbours of reference pixel `(u, v)`, clamped to the image."""
    hr, wr = image_size(ref)
    return ti.max(u - 1, 0), ti.min(u + 1, wr - 1), ti.max(v - 1, 0), ti.min(v + 1, hr - 1)


@ti.func
def tap_differences(ir: ti.f32, rl: ti.f32, rr: ti.f32, ru: ti.f32, rd: ti.f32, ul: ti.i32, ur: ti.i32, vu: ti.i32,
                    vd: ti.i32):
    """`reference_taps` from the five taps (centre, left, right, up, down) read at the bounds of `tap_bounds`."""
    ok = ti.min(ti.min(ir, rl), ti.min(rr, ti.min(ru, rd))) > MASK_LIMIT
    return ir, (rr - rl) / (ur - ul), (rd - ru) / (vd - vu), ok


@ti.func
def hist_bin(a: ti.f32) -> ti.i32:
    """Histogram bin of `a = |r| ≥ 0` read from its float32 bits (no logarithm): `HIST_SUB` linear bins per octave
    from `2^HIST_LOG2_MIN`; smaller values fall in bin 0, larger ones in the last bin."""
    bits = ti.bit_cast(ti.max(a, 2.0**HIST_LOG2_MIN), ti.i32)
    return ti.min((bits >> (23 - HIST_SUB_BITS)) - ((127 + HIST_LOG2_MIN) << HIST_SUB_BITS), HIST_BINS - 1)


@ti.func
def hist_value(k: ti.i32, frac: ti.f32) -> ti.f32:
    """|r| at fraction `frac` ∈ [0, 1] across bin `k` of `hist_bin` (linear inside the bin, as the bins are)."""
    octave = k >> HIST_SUB_BITS
    sub = k & (HIST_SUB - 1)
    return 2.0 ** ti.cast(HIST_LOG2_MIN + octave, ti.f32) * (1.0 + (sub + frac) / HIST_SUB)


@ti.func
def store_band(work: ti.template(), acc: ti.template(), hist: ti.template(), b: ti.i32, robot: ti.i32):
    """Write band `b`'s partial sums `acc` and its |r| histogram `hist` to their places in `work` (`work_size`; row
    `robot` of a stack, `sampling.put_entry`).

    The loops run to `max(b, n)`, which is `n` (`b < MAX_BANDS ≤ n`) but not a constant to LLVM: with constant trip
    counts it unrolled them 23- and 64-fold into long blocks of loads and stores (each store reloads the ndarray's
    base pointer), a quarter of the band task's LLVM IR, whose code generation a warm-cache first launch repeats at
    every start (docs/performance.md, Start-up)."""
    nacc = ti.static(acc.n)
    ti.static_assert(min(nacc, HIST_BINS) >= MAX_BANDS)
    for k in range(ti.max(b, nacc)):
        put_entry(work, robot, (1 + b) * nacc + k, acc[k])
    for k in range(ti.max(b, HIST_BINS)):
        put_entry(work, robot, nacc * (1 + MAX_BANDS) + b * HIST_BINS + k, hist[k])


@ti.func
def finish_sums(work: ti.template(), nacc: ti.template(), params: ti.template(), bands_at: ti.template()):
    """Tail of a step kernel, one thread per robot (`work` and `params` of one robot, or stacks: `sampling.entry`):
    add the robot's `nb = params[bands_at]` band partials (float64) into `work[:nacc]`, then write the median of |r|
    read from the band histograms (over the pixels they counted) into the last statistic, `work[nacc − 1]`; a robot
    with `nb = 0` (not evaluated in this launch) is left as it was.

    The histograms are added band by band over each band's contiguous bins into band 0's histogram in `work`
    (integers: any order gives the same counts): LLVM compiles that to a fraction of the machine code of a loop over
    a run-time number of bands per bin (vectorised with its run-time checks and remainders), a first launch's code
    generation on every start. The sums keep their loop over the bands per entry: a local float64 array of all
    `nacc` sums instead made Taichi's IR passes, and so a cold compile, grow with the grid (docs/results/speed.md,
    start-up). No local array here at all: Taichi 1.7's SPIR-V code generation (Vulkan) fails on a kernel whose
    parallel loop and tail both initialise a local array ("Value … does not yet exist": the element offsets
    of the second array refer to constants of the first task; docs/gpu.md)."""
    hist0 = ti.static(nacc * (1 + MAX_BANDS))
    for robot in range(stack_size(params)):
        nb = ti.cast(entry(params, robot, bands_at), ti.i32)
        if nb > 0:
            for k in range(nacc):
                total = ti.cast(0.0, ti.f64)
                for b in range(nb):
                    total += ti.cast(entry(work, robot, (1 + b) * nacc + k), ti.f64)
                put_entry(work, robot, k, ti.cast(total, ti.f32))
            for b in range(1, nb):
                for k in range(HIST_BINS):
                    put_entry(work, robot, hist0 + k,
                              entry(work, robot, hist0 + k) + entry(work, robot, hist0 + b * HIST_BINS + k))
            counted = 0.0
            for k in range(HIST_BINS):
                counted += entry(work, robot, hist0 + k)
            half = 0.5 * counted
            cum = 0.0
            median = 0.0
            found = 0
            for k in range(HIST_BINS):
                count = entry(work, robot, hist0 + k)
                if found == 0 and count > 0.0 and cum + count >= half:
                    median = hist_value(k, (half - cum) / count)
                    found = 1
                cum += count
            put_entry(work, robot, nacc - 1, median)


TILE = 128  # columns per tile of the thread-local rolling buffer of warped rows
TILE_STRIDE = TILE + 2


@ti.func
def warp_row(cur: ti.template(), ref: ti.template(), G: ti.template(), buf: ti.template(), rbuf: ti.template(),
             slot: ti.i32, v: ti.i32, ut0: ti.i32, n: ti.i32, robot: ti.i32):
    """Warp `n` pixels of reference row `v` (robot `robot`'s images of the stacks) from column `ut0 − 1` into slot
    `slot` of the rolling buffer `buf`:
    `I(w(G, p*))`, or `OUTSIDE` where the warp leaves `cur` or the sample is clipped (`SATURATED`); copy the same
    pixels of the reference, row and columns clamped to the image, into the same slot of `rbuf`. Stores go to
    thread-local arrays only, so LLVM keeps the ndarray pointers in registers and vectorises the loop (gathers for
    the bilinear taps). The clamped reference reads happen here once per pixel rather than in the pixel loop,
    which then reads all its taps from consecutive elements: the clamped left and right taps made LLVM scalarise
    them there, lane by lane, a fifth of that loop's code to generate at every start (docs/performance.md)."""
    hr, wr = image_size(ref)
    vr = ti.min(ti.max(v, 0), hr - 1)
    for j in range(n):
        x, y, z = homography_apply(G, ti.cast(ut0 - 1 + j, ti.f32), ti.cast(v, ti.f32))
        val, ok = projected_sample(cur, x, y, z, robot)
        buf[slot * TILE_STRIDE + j] = ti.select((ok == 1) & (val < SATURATED), val, OUTSIDE)
        rbuf[slot * TILE_STRIDE + j] = texel(ref, robot, vr, ti.min(ti.max(ut0 - 1 + j, 0), wr - 1))


@ti.func
def pixel_terms(ref: ti.template(), rbuf: ti.template(), buf: ti.template(), span: ti.template(),
                h: ti.template(), v: ti.i32, u: ti.i32, su: ti.i32, sc: ti.i32, sd: ti.i32, beta: ti.f32,
                grid_cols: ti.template()):
    """Residual and ESM gradient of reference pixel `(u, v)` from the rolling buffers of reference rows (`rbuf`) and
    of warped rows (`buf[sc + u]` is the warped sample at `(u, v)`, `su`/`sd` the rows above/below; `warp_row`),
    with the row's column gains `h` (`row_gains`); `ref` gives the image's bounds only.

    Returns `(ok, r, gx, gy, c0, b)`, `b` the column tents: `ok` is false where a reference tap is masked or a
    warped tap is `OUTSIDE`; `r`, `gx`, `gy`, `c0` are then 0 (finite, so that a weight of 0 cancels them). Loads
    only, no branches: the pixel loop that accumulates the normal equations stays vectorisable."""
    ul, ur, vu, vd = tap_bounds(ref, v, u)
    ir, gxr, gyr, ref_ok = tap_differences(rbuf[sc + u], rbuf[sc + u - 1], rbuf[sc + u + 1], rbuf[su + u],
                                           rbuf[sd + u], ul, ur, vu, vd)
    c0 = buf[sc + u]
    cl = buf[sc + u - 1]
    cr = buf[sc + u + 1]
    cu = buf[su + u]
    cd = buf[sd + u]
    ok = ref_ok & (ti.min(ti.min(c0, cl), ti.min(cr, ti.min(cu, cd))) > MASK_LIMIT)
    gain, b = column_tents(span, h, ti.cast(u, ti.f32), grid_cols)
    r = gain * c0 + beta - ir
    gx = 0.5 * (gain * 0.5 * (cr - cl) + gxr)
    gy = 0.5 * (gain * 0.5 * (cd - cu) + gyr)
    return ok, ti.select(ok, r, 0.0), ti.select(ok, gx, 0.0), ti.select(ok, gy, 0.0), ti.select(ok, c0, 0.0), b


@ti.kernel
def planar_step(
    ref: ti.types.ndarray(dtype=ti.f32, ndim=3),
    cur: ti.types.ndarray(dtype=ti.f32, ndim=3),
    params: ti.types.ndarray(dtype=ti.f32, ndim=2),
    work: ti.types.ndarray(dtype=ti.f32, ndim=2),
    grid_rows: ti.template(),
    grid_cols: ti.template(),
):
    """Evaluate residuals, robust weights and normal equations at the parameters in `params[k]` for every robot `k`
    of the stacks with bands to run (module docstring: the robot axis).

    Each band walks its rows in column tiles of `TILE` pixels, warping the current image one row ahead into a
    thread-local rolling buffer of three rows (the ROI grown by one pixel on each side, `OUTSIDE` where the warp
    leaves `cur`), so that the five warped samples of a pixel's ESM gradient are read, not re-interpolated.
    """
    M = ti.static(grid_rows * grid_cols + 1)
    C = ti.static(grid_cols)
    P = ti.static(N_GEOMETRIC + M)
    NT = ti.static(P * (P + 1) // 2)
    NACC = ti.static(NT + P + N_STATS)
    # The most bands of one robot: each robot gets that many 512-iteration blocks, its own bands in the first ones.
    most = 0
    ti.loop_config(serialize=True)
    for robot in range(params.shape[0]):
        most = ti.max(most, ti.cast(params[robot, PARAMS_BANDS], ti.i32))
    # A CPU parallel loop hands out blocks of ≥ 512 iterations: one band per block spreads bands over threads.
    for it in range(params.shape[0] * most * 512):
        if it % 512 == 0:
            robot = it // (most * 512)
            b = it // 512 % most
            nb = ti.cast(params[robot, PARAMS_BANDS], ti.i32)
            if b < nb:
                u0 = ti.cast(params[robot, PARAMS_ROI + 0], ti.i32)
                v0 = ti.cast(params[robot, PARAMS_ROI + 1], ti.i32)
                u1 = ti.cast(params[robot, PARAMS_ROI + 2], ti.i32)
                v1 = ti.cast(params[robot, PARAMS_ROI + 3], ti.i32)
                cx = params[robot, PARAMS_NORM + 0]
                cy = params[robot, PARAMS_NORM + 1]
                s = params[robot, PARAMS_NORM + 2]
                beta = params[robot, PARAMS_BETA]
                sigma = params[robot, PARAMS_SIGMA]
                kind = ti.cast(params[robot, PARAMS_ROBUST], ti.i32)
                G = load_vector(params, PARAMS_G, 9, robot)
                span = load_vector(params, PARAMS_SPAN, 4, robot)
                gains = load_vector(params, PARAMS_GAINS, grid_rows * grid_cols, robot)
                # Local arrays (their stores alias no ndarray), zeroed as `ti.Vector([0.0] * n)`: `ti.Vector.zero` is
                # a Taichi function whose list comprehension the front end walks element by element at every start.
                hist = ti.Vector([0.0] * HIST_BINS, ti.f32)
                rows = v1 - v0 + 1
                first = v0 + b * rows // nb
                last = v0 + (b + 1) * rows // nb  # exclusive
                acc = ti.Vector([0.0] * NACC, ti.f32)
                buf = ti.Vector([0.0] * (3 * TILE_STRIDE), ti.f32)  # rows v − 1, v, v + 1 of the warped current image
                rbuf = ti.Vector([0.0] * (3 * TILE_STRIDE), ti.f32)  # the same rows of the reference
                for tile in range((u1 - u0 + TILE) // TILE):
                    ut0 = u0 + tile * TILE
                    ut1 = ti.min(ut0 + TILE - 1, u1)
                    n = ut1 - ut0 + 3
                    # Warp row t into its slot; once rows v − 1, v, v + 1 are there, process row v = t − 1.
                    for t in range(first - 1, last + 1):
                        warp_row(cur, ref, G, buf, rbuf, (t - first + 1) % 3, t, ut0, n, robot)
                        if t > first:
                            v = t - 1
                            su = ((v - first) % 3) * TILE_STRIDE - ut0 + 1
                            sc = ((v - first + 1) % 3) * TILE_STRIDE - ut0 + 1
                            sd = ((v - first + 2) % 3) * TILE_STRIDE - ut0 + 1
                            a, h = row_gains(span, gains, ti.cast(v, ti.f32), grid_rows, grid_cols)
                            moments = ti.Vector.zero(ti.f32, N_MOMENTS)  # see MOMENT_OFFSET
                            cross_c = ti.Matrix.zero(ti.f32, C, 5)  # Σ w b_j Iw b_q (photometric_row)
                            photo_c = ti.Vector.zero(ti.f32, C * (C + 1) // 2)  # Σ w b_j b_l Iw², upper triangle
                            photo_cb = ti.Vector.zero(ti.f32, C)  # Σ w b_j Iw
                            cross_b = ti.Vector.zero(ti.f32, 5)  # Σ w b_q
                            w_sum = 0.0
                            gb = ti.Vector.zero(ti.f32, 5)  # Σ w r b
                            ge_c = ti.Vector.zero(ti.f32, C)  # Σ w r b_j Iw
                            r_sum = 0.0
                            stats = ti.Vector.zero(ti.f32, 3)
                            # Loads and register sums only (no store, no branch): LLVM vectorises this loop.
                            for u in range(ut0, ut1 + 1):
                                ok, r, gx, gy, c0, bt = pixel_terms(ref, rbuf, buf, span, h, v, u, su, sc, sd, beta, C)
                                valid = ti.select(ok, 1.0, 0.0)
                                w = valid * robust_weight(r, sigma, kind)
                                du = u - cx
                                du2 = du * du
                                wxx = w * gx * gx
                                wxy = w * gx * gy
                                wyy = w * gy * gy
                                du3 = du2 * du
                                moments += ti.Vector([wxx, wxx * du, wxx * du2, wxx * du3, wxx * du2 * du2,
                                                      wxy, wxy * du, wxy * du2, wxy * du3, wyy, wyy * du, wyy * du2])
                                basis = ti.Vector([gx, gy, gx * du, gy * du, gx * du2])
                                E = bt * c0  # the gain columns' photometric Jacobian entries, over the row's a_i
                                for j in ti.static(range(C)):
                                    we = w * E[j]
                                    for q in ti.static(range(5)):
                                        cross_c[j, q] += we * basis[q]
                                    for l in ti.static(range(j, C)):
                                        photo_c[ti.static(_triangle_index(j, l, C))] += we * E[l]
                                    photo_cb[j] += we
                                cross_b += w * basis
                                w_sum += w
                                w_r = w * r
                                gb += w_r * basis
                                ge_c += w_r * E
                                r_sum += w_r
                                inlier = ti.select(ti.abs(r) <= INLIER_C * sigma, valid, 0.0)
                                stats += ti.Vector([valid, inlier, valid * r * r])
                            accumulate_row(acc, moments, cross_c, photo_c, photo_cb, cross_b, w_sum, gb, ge_c, r_sum,
                                           stats, a, v - cy, s, grid_rows, grid_cols)
                            # The |r| histogram stores (into a thread-local array), so it gets its own scalar loop,
                            # over every other pixel of every other row, from the residual alone (valid where the
                            # pixel's own reference and warped values are): it only has to give the median's scale.
                            # It leaves by a `break` at the tile's end: LLVM does not unroll a loop with two exits (with
                            # its run-time trip count alone it made eight copies of the body to generate at each start).
                            if v % 2 == 0:
                                for k in range((TILE + 1) // 2):
                                    u = ut0 + 2 * k
                                    if u > ut1:
                                        break
                                    ir = rbuf[sc + u]
                                    c0 = buf[sc + u]
                                    gain, _b = column_tents(span, h, ti.cast(u, ti.f32), C)
                                    if ti.min(ir, c0) > MASK_LIMIT:
                                        hist[hist_bin(ti.abs(gain * c0 + beta - ir))] += 1.0
                store_band(work, acc, hist, b, robot)
    finish_sums(work, NACC, params, PARAMS_BANDS)


@ti.kernel
def render_compensated(
    cur: ti.types.ndarray(dtype=ti.f32, ndim=2),
    params: ti.types.ndarray(dtype=ti.f32, ndim=1),
    out: ti.types.ndarray(dtype=ti.f32, ndim=2),
    grid_rows: ti.template(),
    grid_cols: ti.template(),
):
    """`out[v − v0, u − u0] = S(p*) · I(w(G, p*)) + β` over the ROI (eq. (4)); NaN where the warp leaves `cur`."""
    u0 = ti.cast(params[PARAMS_ROI + 0], ti.i32)
    v0 = ti.cast(params[PARAMS_ROI + 1], ti.i32)
    for r, c in ti.ndrange(out.shape[0], out.shape[1]):
        u = ti.cast(u0 + c, ti.f32)
        v = ti.cast(v0 + r, ti.f32)
        x, y, z = homography_apply(load_vector(params, PARAMS_G, 9), u, v)
        val, ok = projected_sample(cur, x, y, z)
        gain, _phi = gain_at(load_vector(params, PARAMS_SPAN, 4),
                             load_vector(params, PARAMS_GAINS, grid_rows * grid_cols), u, v, grid_rows, grid_cols)
        out[r, c] = gain * val + params[PARAMS_BETA] if ok == 1 else ti.math.nan

