"""Planar direct registration on SL(3) with an illumination model and robust weights (eqs. (4)–(5), `ρ* ≡ 0`).

Minimises `½ Σ ρ(S(p*) · I(w(G, p*)) + β − I*(p*))` over the ROI with an ESM Gauss-Newton iteration
(`kernels.planar_step` builds the robust normal equations in one Taichi launch per iteration), coarse to fine over a
pyramid. Updates: `G ← G · N⁻¹ exp(Σ xᵢ Aᵢ) N` at each level (`Aᵢ` = `lie.SL3_GENERATORS`, `N` the level's
normalisation `q = (p − c) / s` around the ROI centre, which keeps the 8 unknowns equally scaled; `N⁻¹ exp(·) N`
is itself in SL(3)), `S ← S + δS`, `β ← β + δβ`. The robust scale σ = 1.4826 · median |r| is taken from the
previous evaluation (the first one of a cold start uses plain least squares).

`G` maps reference pixels to current pixels, full-image 0-based pixel centres; `roi = (x, y, w, h)` in reference
pixels covers columns x … x + w − 1 and rows y … y + h − 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.lie import sl3_exp, sl3_normalize
from ddvs_service.registration.coarse_search import coarse_alignment
from ddvs_service.registration.config import ROBUST_CODES, RegistrationConfig
from ddvs_service.registration.images import F32, build_pyramid, checked_grey, irradiance, level_matrix
from ddvs_service.registration.layout import ParamLayout
from ddvs_service.registration.result import RegistrationResult
from kernels.launch import Prepared
from kernels.planar_step import (
    MASK_LIMIT,
    PARAMS_BANDS,
    PARAMS_BETA,
    PARAMS_G,
    PARAMS_GAINS,
    PARAMS_NORM,
    PARAMS_ROBUST,
    PARAMS_ROI,
    PARAMS_SIGMA,
    PARAMS_SPAN,
)

F64 = NDArray[np.float64]
Roi = tuple[int, int, int, int]
MAD_TO_SIGMA = 1.4826
DEGENERATE_RCOND = 1e-9
MAX_RATE = 0.8  # contraction above which the remaining-motion bound is not trusted
TRANSLATION = (0, 1)
SIMILARITY = (0, 1, 2, 4)  # sl(3) coordinates of translation, rotation and isotropic scale


@dataclass(frozen=True)
class _Level:
    """Fixed geometry of one pyramid level: ROI bounds (inclusive), gain-grid span, normalisation `N` (level pixels →
    `q = (p − c) / s`), `D` (full-resolution → level pixels), ROI corners."""

    index: int
    bounds: tuple[int, int, int, int]
    span: tuple[float, float, float, float]
    norm: tuple[float, float, float]
    n_pixels: int
    D: F64
    D_inv: F64
    N: F64
    N_inv: F64
    corners: F64  # homogeneous ROI corners (3×4), level pixels

    @property
    def size(self) -> float:
        u0, v0, u1, v1 = self.bounds
        return float(max(u1 - u0, v1 - v0))


@dataclass
class _State:
    G: F64
    gains: F64
    beta: float
    scale: float | None
    residual_rms: float = float("nan")
    inlier_ratio: float = 0.0


def project(G: F64, pts: F64) -> F64:
    """Dehomogenised `G · pts` for homogeneous points `pts` (3, n) and one warp `G` (3, 3) → (2, n), or a stack of
    warps (K, 3, 3) → (K, 2, n)."""
    q = G @ pts
    return q[..., :2, :] / q[..., 2:3, :]


def normalisation(bounds: tuple[int, int, int, int]) -> tuple[tuple[float, float, float], F64]:
    """`(cx, cy, s)` and the matrix `N` of the normalisation `q = (p − c) / s` about the centre of the inclusive
    pixel bounds `(u0, v0, u1, v1)`, `s` half the larger side: the sl(3) increments of every engine are taken in it."""
    u0, v0, u1, v1 = bounds
    cx, cy, s = 0.5 * (u0 + u1), 0.5 * (v0 + v1), 0.5 * max(u1 - u0, v1 - v0)
    return (cx, cy, s), np.array([[1.0 / s, 0.0, -cx / s], [0.0, 1.0 / s, -cy / s], [0.0, 0.0, 1.0]])


def symmetric_index(n: int) -> NDArray[np.intp]:
    """`idx[i, j]`: position of `H[min(i, j), max(i, j)]` in the kernel's row-major upper triangle."""
    i, j = np.minimum.outer(np.arange(n), np.arange(n)), np.maximum.outer(np.arange(n), np.arange(n))
    return i * n - i * (i - 1) // 2 + (j - i)


def _validate_roi(roi: Roi | None, shape: tuple[int, ...]) -> Roi:
    h, w = shape
    if roi is None:
        return 0, 0, w, h
    if len(roi) != 4:
        raise ValueError(f"roi must be (x, y, w, h), got {roi!r}")
    x, y, rw, rh = (int(v) for v in roi)
    if rw < 8 or rh < 8:
        raise ValueError(f"roi {roi} is {rw}×{rh} pixels, expected at least 8×8")
    if x < 0 or y < 0 or x + rw > w or y + rh > h:
        raise ValueError(f"roi (x={x}, y={y}, w={rw}, h={rh}) is not inside the {w}×{h} reference image")
    return x, y, rw, rh


class PlanarRegistration:
    """The reference side of eq. (5), prepared once: pyramid, masked ROI, levels, buffers. `run` registers an image."""

    def __init__(
        self,
        reference: ArrayLike,
        roi: Roi | None = None,
        mask: ArrayLike | None = None,
        config: RegistrationConfig = RegistrationConfig(),  # noqa: B008 - frozen, immutable default
    ) -> None:
        from kernels.backend import init
        from kernels.planar_step import MASKED, n_acc, n_params, work_size

        init()
        self.config = config
        ref = irradiance(checked_grey(reference, "reference"), config.gamma, config.defocus_px).copy()
        self.shape = ref.shape
        self.roi = _validate_roi(roi, ref.shape)
        if mask is not None:
            m = np.asarray(mask)
            if m.shape != ref.shape:
                raise ValueError(f"mask has shape {m.shape}, expected the reference's {ref.shape}")
            ref[~m.astype(bool)] = MASKED
        self.levels = self._make_levels(build_pyramid(ref, config.levels))
        self.reference = build_pyramid(ref, len(self.levels))
        self.grid = config.gain_grid
        self.layout = ParamLayout.planar(*self.grid)
        if self.layout.size != n_params(*self.grid):
            raise AssertionError("parameter layout and kernel column order disagree")
        self._n = self.layout.size
        self._nacc = n_acc(self._n)
        self._sym = symmetric_index(self._n)
        self._sl_G, self._sl_S, self._sl_b = self.layout.slice("G"), self.layout.slice("S"), self.layout.slice("beta")
        self._robust_code = ROBUST_CODES[config.robust]
        self._params = np.zeros(PARAMS_GAINS + self.grid[0] * self.grid[1], dtype=np.float32)
        self._work = np.zeros(work_size(self._n), dtype=np.float32)
        # The current image's pyramid lives in fixed buffers, so that each level's kernels are prepared once
        # (`kernels.launch.Prepared`, on first use) and every later launch skips Taichi's per-call argument set-up.
        self._current = [np.empty_like(level) for level in self.reference]
        self._steps: dict[int, Prepared] = {}
        self._downsamples: dict[int, Prepared] = {}
        self._linearise: Prepared | None = None

    def _make_levels(self, pyramid: list[F32]) -> list[_Level]:
        """Levels 0 … L − 1 whose ROI keeps at least `min_level_size` pixels per side; refuses an all-masked ROI."""
        x, y, w, h = self.roi
        levels = []
        for index, ref in enumerate(pyramid):
            k = 2**index
            u0, v0 = math.ceil(x / k), math.ceil(y / k)
            u1 = min(math.floor((x + w) / k) - 1, ref.shape[1] - 1)
            v1 = min(math.floor((y + h) / k) - 1, ref.shape[0] - 1)
            if index > 0 and min(u1 - u0 + 1, v1 - v0 + 1) < self.config.min_level_size:
                break
            n_pixels = int((ref[v0 : v1 + 1, u0 : u1 + 1] > MASK_LIMIT).sum())
            if n_pixels == 0:
                if index == 0:
                    raise ValueError("the mask excludes every pixel of the ROI; expected some pixels to register")
                break
            D = level_matrix(index)
            sx0, sx1 = D[0, 0] * np.array([x, x + w - 1]) + D[0, 2]
            sy0, sy1 = D[1, 1] * np.array([y, y + h - 1]) + D[1, 2]
            norm, N = normalisation((u0, v0, u1, v1))
            levels.append(
                _Level(
                    index=index,
                    bounds=(u0, v0, u1, v1),
                    span=(float(sx0), float(sy0), float(sx1), float(sy1)),
                    norm=norm,
                    n_pixels=n_pixels,
                    D=D,
                    D_inv=np.linalg.inv(D),
                    N=N,
                    N_inv=np.linalg.inv(N),
                    corners=np.array([[u0, u1, u1, u0], [v0, v0, v1, v1], [1.0, 1.0, 1.0, 1.0]]),
                )
            )
        return levels

    def run(
        self,
        current: ArrayLike,
        G0: ArrayLike | None = None,
        gains0: ArrayLike | float = 1.0,
        beta0: float = 0.0,
        scale0: float | None = None,
        first_level: int | None = None,
        tolerance_px: float | None = None,
    ) -> RegistrationResult:
        """Register `current` starting from `G0` (any scale, positive determinant; identity by default), gains and
        bias (eq. (4)) and robust scale σ (grey levels; `None`: estimated from a first least-squares evaluation).

        `first_level`: the coarsest pyramid level to solve (0 = full resolution only); the coarsest available by
        default. A warm start whose predicted motion is small starts finer and skips the coarse levels' cost.
        `tolerance_px`: convergence tolerance at full resolution (`config.step_tolerance_px` by default)."""
        cur = checked_grey(current, "current")
        if cur.shape != self.shape:
            raise ValueError(f"current image is {cur.shape[1]}×{cur.shape[0]}, expected the reference's "
                             f"{self.shape[1]}×{self.shape[0]}")
        levels = self.levels if first_level is None else self.levels[: max(0, first_level) + 1]
        G = np.eye(3) if G0 is None else sl3_normalize(np.asarray(G0, dtype=np.float64).reshape(3, 3))
        gains = np.broadcast_to(np.asarray(gains0, dtype=np.float64), self.grid).astype(np.float64).copy()
        state = _State(G=G, gains=gains, beta=float(beta0), scale=scale0)
        pyramid = self.load_current(cur, len(levels))
        iterations: list[int] = []
        converged, reason = False, ""
        for level in reversed(levels):
            fine = self.config.step_tolerance_px if tolerance_px is None else tolerance_px
            tolerance = fine if level.index == 0 else self.config.coarse_step_tolerance_px
            count = 0
            if level is levels[-1] and G0 is None:
                # Cold start: find the shift and a rough angle by correlation (`coarse_search`), match the photometric
                # moments, then settle the similarity part with the photometric unknowns frozen (a misaligned
                # least-squares gain shrinks towards 0 and erases the signal).
                start = coarse_alignment(self.reference[level.index], pyramid[level.index], level.bounds)
                if start is not None:
                    state.G = level.D_inv @ start @ level.D
                self._match_moments(level, self.reference[level.index], pyramid[level.index], state)
                failed = False
                for subset in (TRANSLATION, SIMILARITY):
                    more, _, reason, failed = self._solve_level(level, state, tolerance, subset, False)
                    count += more
                    if failed:
                        break
                if failed:
                    iterations.append(count)
                    break
            more, converged, reason, failed = self._solve_level(level, state, tolerance)
            count += more
            iterations.append(count)
            if failed:
                break
        if converged and state.inlier_ratio < self.config.min_inlier_ratio:
            converged = False
            reason = f"inlier ratio {state.inlier_ratio:.3f} below min_inlier_ratio {self.config.min_inlier_ratio}"
        return RegistrationResult(
            G=state.G, S=state.gains.copy(), beta=state.beta, iterations=iterations,
            residual_rms=state.residual_rms, inlier_ratio=state.inlier_ratio, converged=converged, reason=reason,
            scale=float("nan") if state.scale is None else state.scale,
        )

    def load_current(self, cur: F32, n_levels: int) -> list[F32]:
        """Copy `cur` (checked, reference-sized float32) into the fixed level-0 buffer, linearise it there when
        `config.gamma` ≠ 1 (`images.irradiance`; the reference's defocus is not applied to the current image) and
        downsample it into the next `n_levels − 1` buffers (`images.build_pyramid`'s filter); returns the buffers,
        which the next call overwrites. An engine sharing this object's buffers (the general model's) prepares its
        launches on them too."""
        from kernels.image_formation import linearise
        from kernels.pyramid import downsample2

        np.copyto(self._current[0], cur)
        if self.config.gamma != 1.0:
            if self._linearise is None:
                self._linearise = Prepared(linearise, self._current[0], self.config.gamma)
            self._linearise()
        for index in range(1, n_levels):
            if index not in self._downsamples:
                self._downsamples[index] = Prepared(downsample2, self._current[index - 1], self._current[index])
            self._downsamples[index]()
        return self._current

    def _step(self, index: int) -> Prepared:
        """`kernels.planar_step` bound to level `index`'s reference and current buffers and the shared parameter
        and work arrays."""
        from kernels.planar_step import planar_step

        if index not in self._steps:
            self._steps[index] = Prepared(planar_step, self.reference[index], self._current[index], self._params,
                                          self._work, self.grid[0], self.grid[1])
        return self._steps[index]

    def _fill_level(self, level: _Level) -> None:
        """The parameters fixed at one level: normalisation, ROI bounds, gain-grid span, band count."""
        p = self._params
        p[PARAMS_NORM : PARAMS_NORM + 3] = level.norm
        p[PARAMS_ROI : PARAMS_ROI + 4] = level.bounds
        p[PARAMS_SPAN : PARAMS_SPAN + 4] = level.span
        p[PARAMS_BANDS] = self.config.bands_for(level.n_pixels)

    def _fill_state(self, G_l: F64, state: _State) -> None:
        """The parameters that change every iteration: `G` (level pixels), bias, robust scale and loss, gains."""
        p = self._params
        p[PARAMS_G : PARAMS_G + 9] = G_l.reshape(9)
        p[PARAMS_BETA] = state.beta
        p[PARAMS_SIGMA] = 1e30 if state.scale is None else state.scale
        p[PARAMS_ROBUST] = 0 if state.scale is None else self._robust_code
        p[PARAMS_GAINS:] = state.gains.reshape(-1)

    def _match_moments(self, level: _Level, ref: F32, cur: F32, state: _State) -> None:
        """Set a uniform gain and the bias so that `S·I(w(G, p*)) + β` has the mean and spread of `I*` over the ROI."""
        from kernels.planar_step import render_compensated

        state.gains[:] = 1.0
        state.beta = 0.0
        self._fill_level(level)
        self._fill_state(level.D @ state.G @ level.D_inv, state)
        u0, v0, u1, v1 = level.bounds
        warped = np.empty((v1 - v0 + 1, u1 - u0 + 1), dtype=np.float32)
        render_compensated(cur, self._params, warped, self.grid[0], self.grid[1])
        both = np.isfinite(warped) & (ref[v0 : v1 + 1, u0 : u1 + 1] > MASK_LIMIT)
        a, b = ref[v0 : v1 + 1, u0 : u1 + 1][both], warped[both]
        if a.size > 1 and b.std() > 1e-3:
            gain = float(a.std() / b.std())
            state.gains[:] = gain
            state.beta = float(a.mean() - gain * b.mean())

    def _solve_level(
        self,
        level: _Level,
        state: _State,
        tolerance: float,
        geometric: tuple[int, ...] = tuple(range(8)),
        photometric: bool = True,
    ) -> tuple[int, bool, str, bool]:
        """Gauss-Newton at one level over the sl(3) coordinates `geometric` (and the photometric unknowns unless
        `photometric` is False) until the corner motion still to come (`remaining_motion` of the steps so far) is
        below `tolerance` level pixels; updates `state`; returns (iterations, converged, reason, fatal failure)."""
        cfg = self.config
        n, nt = self._n, self._n * (self._n + 1) // 2
        free = np.zeros(n, dtype=bool)
        free[self._sl_G][list(geometric)] = True
        free[self._sl_S] = free[self._sl_b] = photometric
        subset = None if free.all() else np.ix_(free, free)
        limit = cfg.max_step_fraction * level.size
        G_l = level.D @ state.G @ level.D_inv
        self._fill_level(level)
        step_kernel = self._step(level.index)
        outcome: tuple[int, bool, str, bool] = (cfg.max_iterations, False, (
            f"max_iterations ({cfg.max_iterations}) reached at level {level.index}"), False)
        steps: list[float] = []
        corners = project(G_l, level.corners)
        for it in range(1, cfg.max_iterations + 1):
            self._fill_state(G_l, state)
            step_kernel()
            acc = self._work[: self._nacc].astype(np.float64)
            n_valid, n_inliers, sum_r2, median = acc[nt + n :]
            valid_ratio = n_valid / level.n_pixels
            if valid_ratio < cfg.min_valid_ratio:
                outcome = (it, False, (f"diverged at level {level.index}: only {valid_ratio:.0%} of the ROI maps "
                                       f"inside the current image (min_valid_ratio {cfg.min_valid_ratio:.0%})"), True)
                break
            state.residual_rms = math.sqrt(sum_r2 / n_valid)
            state.inlier_ratio = min(1.0, n_inliers / level.n_pixels) if state.scale is not None else 1.0
            state.scale = max(MAD_TO_SIGMA * median, cfg.scale_floor)
            H = acc[self._sym]
            g = acc[nt : nt + n]
            if subset is not None:
                H, g = H[subset], g[free]
            if it == 1:
                degenerate = _degeneracy(H)
                if degenerate:
                    outcome = (it, False, f"degenerate normal equations at level {level.index} (textureless ROI?)"
                                          f"{degenerate}", True)
                    break
            delta = np.zeros(n)
            try:
                delta[free] = np.linalg.solve(H, -g)
            except np.linalg.LinAlgError:
                delta[:] = np.nan
            if not math.isfinite(float(delta.sum())):  # any NaN or infinite entry makes the sum non-finite
                outcome = (it, False, f"non-finite update at level {level.index}", True)
                break
            G_l_new = G_l @ level.N_inv @ sl3_exp(delta[self._sl_G]) @ level.N
            moved = project(G_l_new, level.corners)
            step = float(np.abs(moved - corners).max())
            if not step <= limit:  # also catches NaN
                delta = delta * (limit / step) if math.isfinite(step) else np.zeros_like(delta)
                G_l_new = G_l @ level.N_inv @ sl3_exp(delta[self._sl_G]) @ level.N
                moved = project(G_l_new, level.corners)
            G_l, corners = G_l_new, moved
            state.gains = state.gains + delta[self._sl_S].reshape(self.grid)
            state.beta = state.beta + float(delta[self._sl_b][0])
            steps.append(step)
            remaining = remaining_motion(steps)
            if remaining < tolerance:
                outcome = (it, True, f"converged: last step {step:.1e} px, at most {remaining:.1e} px left "
                                     f"< {tolerance:g} px", False)
                break
        state.G = sl3_normalize(level.D_inv @ G_l @ level.D)
        return outcome


def remaining_motion(steps: list[float]) -> float:
    """Bound on the corner motion (pixels) still to come after the updates that moved a corner by `steps` (in order):
    the tail `s · q / (1 − q)` of a geometric series from the last step `s`, with `q` the slower of the last two
    contractions `steps[k] / steps[k − 1]`. Gauss-Newton on bilinearly interpolated images converges linearly
    (q ≈ 0.2–0.5 measured), so the last step alone overstates the distance to the fixed point by `(1 − q) / q`.
    With fewer than three steps, or a contraction above `MAX_RATE`, the bound is the last step itself."""
    s = steps[-1]
    if len(steps) < 3 or not min(steps[-3:-1]) > 0.0:
        return s
    rate = max(steps[-1] / steps[-2], steps[-2] / steps[-3])
    return s * rate / (1.0 - rate) if rate < MAX_RATE else s


def _degeneracy(H: F64) -> str:
    """Why the normal matrix `H` is too ill-conditioned to solve (empty when it is fine): a non-positive diagonal
    or a reciprocal condition number of the diagonally scaled matrix below `DEGENERATE_RCOND`."""
    d = np.diag(H)
    if not np.all(d > 0):
        return ": a parameter has no effect on the residuals"
    eig = np.linalg.eigvalsh(H / np.sqrt(np.outer(d, d)))
    if not eig[0] > DEGENERATE_RCOND * eig[-1]:
        return f": reciprocal condition {eig[0] / eig[-1]:.1e}"
    return ""


def register(
    reference: ArrayLike,
    current: ArrayLike,
    roi: Roi | None = None,
    mask: ArrayLike | None = None,
    G0: ArrayLike | None = None,
    photometric0: tuple[ArrayLike | float, float] | None = None,
    config: RegistrationConfig = RegistrationConfig(),  # noqa: B008 - frozen, immutable default
) -> RegistrationResult:
    """Estimate `G` (reference → current pixels) and the gains `S` and bias `β` of eq. (4) over `roi`.

    `reference`, `current`: same-size grey images (uint8 or float, grey levels 0…255). `roi = (x, y, w, h)` in reference
    pixels (whole image when None); `mask`: boolean, True where reference pixels may be used. `G0`: initial homography
    (identity when None); `photometric0 = (S, β)`, S a scalar or an array of shape `config.gain_grid`.
    Raises ValueError on bad input (sizes, ROI, NaN/Inf, mask); a failed iteration is reported in the result.
    """
    problem = PlanarRegistration(reference, roi=roi, mask=mask, config=config)
    gains0, beta0 = (1.0, 0.0) if photometric0 is None else photometric0
    return problem.run(current, G0=G0, gains0=gains0, beta0=beta0)
