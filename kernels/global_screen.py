"""Normal equations of one robust ESM Gauss-Newton step for a batch of K planar warps of the same ROI, in one launch
(the global initialiser screens all its starting hypotheses at once at the search level).

For start `k` with homography `G_k` (level pixels, reference → current), gain `a_k`, bias `b_k` and robust scale
`σ_k`, every reference pixel `p* = (u, v)` of the ROI (inclusive bounds `u0…u1`, `v0…v1`, level pixels) gives
(paper eqs. (4)–(5) with `ρ* ≡ 0`, one global gain):
- residual `r = a · I(w(G, p*)) + b − I*(p*)`;
- Jacobian row over `[x_1..x_8 (sl(3)), a, b]`: geometric part `∇ · ∂w(N⁻¹ exp(Σ xᵢ Aᵢ) N, p*)/∂xᵢ` at `x = 0`
  with the ESM gradient `∇ = ½ (a ∇Iw + ∇I*)` (`Iw = I ∘ w(G, ·)`, central differences of the current image
  sampled at the four neighbours' warps; `∇I*` central differences of the reference), the generators `Aᵢ`
  (`GENERATORS`, the order of `ddvs_service.lie.SL3_GENERATORS`) and `N` the normalisation `q = (p − c) / s`
  (`frame`), so that `∂p/∂xᵢ = s · (mᵤ − q_u m_z, m_v − q_v m_z)` with `m = Aᵢ [q_u, q_v, 1]ᵀ`; photometric part
  `[Iw, 1]`;
- Huber weight `w(r / σ)` (k = 1.345; plain least squares when `σ ≤ 0`), 0 where a reference tap or a warped
  sample is missing.

Output row `out[k]` (one array, one launch argument): `N_SUMS` sums — the upper triangle (row-major) of `Jᵀ W J`
(55), `Jᵀ W r` (10), the valid pixel count and `Σ r²` over the valid pixels — then `out[k, N_SUMS + i]` = |r| of ROI
pixel `i` (row-major) or −1 where it is not valid (the caller
takes the median for the next robust scale).
"""

import warnings

import taichi as ti

from kernels.planar_step import reference_taps, robust_weight
from kernels.sampling import homography_apply, projected_sample

# The accumulators are unrolled on purpose (they live in registers); silence Taichi's compile-time-length warning.
warnings.filterwarnings("ignore", message="You are unrolling more than", category=SyntaxWarning)

N_GEOMETRIC = 8
N_UNKNOWNS = N_GEOMETRIC + 2  # sl(3), gain, bias
N_TRIANGLE = N_UNKNOWNS * (N_UNKNOWNS + 1) // 2
N_SUMS = N_TRIANGLE + N_UNKNOWNS + 2  # triangle, gradient, valid count, Σ r²
START_G = 0  # per-start parameters: G row-major (9), gain, bias, σ
START_GAIN = 9
START_BIAS = 10
START_SIGMA = 11
N_START = 12
FRAME_ROI = 0  # frame: u0, v0, u1, v1 (inclusive ROI bounds), cx, cy, s (normalisation)
FRAME_NORM = 4
N_FRAME = 7
HUBER = 1
ROW_TILE = 128  # pixels of a row accumulated before their |r| are stored (the thread-local buffer's length)
BLOCK = 512  # a CPU parallel loop hands out blocks of ≥ 512 iterations: one start per block spreads them over threads
# The sl(3) generators A_1…A_8 (row-major), in the order of `ddvs_service.lie.SL3_GENERATORS` (the caller checks
# that they agree); compile-time constants, so that their zeros fold away.
GENERATORS = (
    (0, 0, 1, 0, 0, 0, 0, 0, 0),  # translation along x
    (0, 0, 0, 0, 0, 1, 0, 0, 0),  # translation along y
    (0, -1, 0, 1, 0, 0, 0, 0, 0),  # in-plane rotation
    (1, 0, 0, 0, -1, 0, 0, 0, 0),  # anisotropic scale
    (1, 0, 0, 0, 1, 0, 0, 0, -2),  # isotropic scale (vs. z)
    (0, 1, 0, 1, 0, 0, 0, 0, 0),  # shear
    (0, 0, 0, 0, 0, 0, 1, 0, 0),  # projective x
    (0, 0, 0, 0, 0, 0, 0, 1, 0),  # projective y
)


@ti.func
def warped_sample(cur: ti.template(), G: ti.template(), u: ti.f32, v: ti.f32):
    """`I(w(G, (u, v)))` and whether it is inside `cur` (`sampling.projected_sample`)."""
    x, y, z = homography_apply(G, u, v)
    return projected_sample(cur, x, y, z)


@ti.func
def pixel_terms(ref: ti.template(), cur: ti.template(), G: ti.template(), gain: ti.f32, bias: ti.f32, u: ti.i32,
                v: ti.i32):
    """`(ok, r, gx, gy, c0)` of reference pixel `(u, v)`: validity, residual, ESM gradient and warped sample (the
    last four 0 where not `ok`). Loads and selects only."""
    ir, gxr, gyr, ref_ok = reference_taps(ref, v, u)
    fu = ti.cast(u, ti.f32)
    fv = ti.cast(v, ti.f32)
    c0, ok0 = warped_sample(cur, G, fu, fv)
    cl, okl = warped_sample(cur, G, fu - 1.0, fv)
    cr, okr = warped_sample(cur, G, fu + 1.0, fv)
    cu, oku = warped_sample(cur, G, fu, fv - 1.0)
    cd, okd = warped_sample(cur, G, fu, fv + 1.0)
    ok = ref_ok & (ok0 + okl + okr + oku + okd == 5)  # `and` would be a branch (docs/performance.md)
    r = gain * c0 + bias - ir
    gx = 0.5 * (gain * 0.5 * (cr - cl) + gxr)
    gy = 0.5 * (gain * 0.5 * (cd - cu) + gyr)
    return ok, ti.select(ok, r, 0.0), ti.select(ok, gx, 0.0), ti.select(ok, gy, 0.0), ti.select(ok, c0, 0.0)


@ti.kernel
def screen_step(
    ref: ti.types.ndarray(dtype=ti.f32, ndim=2),
    cur: ti.types.ndarray(dtype=ti.f32, ndim=2),
    starts: ti.types.ndarray(dtype=ti.f32, ndim=2),
    frame: ti.types.ndarray(dtype=ti.f32, ndim=1),
    out: ti.types.ndarray(dtype=ti.f32, ndim=2),
):
    """Fill `out[k]` for every start `k` of `starts` (K × `N_START`); see the module docstring.
    Each start is one thread's work; its accumulation loop over a tile of a row only loads, sums in registers and
    keeps |r| in a thread-local buffer (vectorised), and a second loop stores those |r| (computing them again there
    doubled the pixel terms LLVM compiles at every start)."""
    u0 = ti.cast(frame[FRAME_ROI + 0], ti.i32)
    v0 = ti.cast(frame[FRAME_ROI + 1], ti.i32)
    u1 = ti.cast(frame[FRAME_ROI + 2], ti.i32)
    v1 = ti.cast(frame[FRAME_ROI + 3], ti.i32)
    cx = frame[FRAME_NORM + 0]
    cy = frame[FRAME_NORM + 1]
    s = frame[FRAME_NORM + 2]
    width = u1 - u0 + 1
    for it in range(starts.shape[0] * BLOCK):
        if it % BLOCK == 0:
            k = it // BLOCK
            G = ti.Vector.zero(ti.f32, 9)
            for i in ti.static(range(9)):
                G[i] = starts[k, START_G + i]
            gain = starts[k, START_GAIN]
            bias = starts[k, START_BIAS]
            sigma = starts[k, START_SIGMA]
            kind = ti.select(sigma > 0.0, HUBER, 0)
            acc = ti.Vector.zero(ti.f32, N_SUMS)
            magnitude = ti.Vector.zero(ti.f32, ROW_TILE)  # |r| of the tile row being accumulated
            for v in range(v0, v1 + 1):
                qv = (v - cy) / s
                for tile in range((width + ROW_TILE - 1) // ROW_TILE):
                    ut0 = u0 + tile * ROW_TILE
                    ut1 = ti.min(ut0 + ROW_TILE - 1, u1)
                    # Loads, register sums and stores into the thread-local `magnitude` only: vectorised.
                    for u in range(ut0, ut1 + 1):
                        ok, r, gx, gy, c0 = pixel_terms(ref, cur, G, gain, bias, u, v)
                        valid = ti.select(ok, 1.0, 0.0)
                        qu = (u - cx) / s
                        J = ti.Vector.zero(ti.f32, N_UNKNOWNS)
                        for i in ti.static(range(N_GEOMETRIC)):
                            a = ti.static(GENERATORS[i])
                            mu = a[0] * qu + a[1] * qv + a[2]
                            mv = a[3] * qu + a[4] * qv + a[5]
                            mz = a[6] * qu + a[7] * qv + a[8]
                            J[i] = s * (gx * (mu - qu * mz) + gy * (mv - qv * mz))
                        J[N_GEOMETRIC] = c0
                        J[N_GEOMETRIC + 1] = valid
                        w = valid * robust_weight(r, sigma, kind)
                        for i in ti.static(range(N_UNKNOWNS)):
                            wi = w * J[i]
                            for j in ti.static(range(i, N_UNKNOWNS)):
                                acc[ti.static(i * N_UNKNOWNS - i * (i - 1) // 2 + j - i)] += wi * J[j]
                            acc[N_TRIANGLE + i] += wi * r
                        acc[N_TRIANGLE + N_UNKNOWNS] += valid
                        acc[N_TRIANGLE + N_UNKNOWNS + 1] += valid * r * r
                        magnitude[u - ut0] = ti.select(ok, ti.abs(r), -1.0)
                    for j in range(ut1 - ut0 + 1):
                        out[k, N_SUMS + (v - v0) * width + (ut0 - u0) + j] = magnitude[j]
            for i in ti.static(range(N_SUMS)):
                out[k, i] = acc[i]
