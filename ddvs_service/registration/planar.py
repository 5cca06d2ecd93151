"""Planar direct registration on SL(3) with an illumination model and robust weights (eqs. (4)–(5), `ρ* ≡ 0`).

Minimises `½ Σ ρ(S(p*) · I(w(G, p*)) + β − I*(p*))` over the ROI with the Gauss-Newton/ESM skeleton of
`registration.solver` (`kernels.planar_step` builds the robust normal equations in one Taichi launch per iteration),
coarse to fine over the pyramid of a `PreparedReference`. The model: unknowns `ParamLayout.planar` (8 sl(3)
coordinates, the gains, the bias); updates `G ← G · N⁻¹ exp(Σ xᵢ Aᵢ) N` at each level (`Aᵢ` = `lie.SL3_GENERATORS`,
`N` the level's normalisation `q = (p − c) / s` around the ROI centre, which keeps the 8 unknowns equally scaled;
`N⁻¹ exp(·) N` is itself in SL(3)), `S ← S + δS` within `config.gain_range` (`solver.bounded_gains`), `β ← β + δβ`;
the step is the motion of the ROI corners. The robust scale σ = 1.4826 · median |r| is taken from the previous
evaluation (the first one of a cold start uses plain least squares); a caller may cap the σ the weights and the
inlier count use (`run(scale_cap=…)`: the tracker anchors it at its last good frames, `registration.integrity`),
while the result reports the σ measured on the frame.

`G` maps reference pixels to current pixels, full-image 0-based pixel centres; `roi = (x, y, w, h)` in reference
pixels covers columns x … x + w − 1 and rows y … y + h − 1.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.lie import SL3_GENERATORS, sl3_exp, sl3_normalize
from ddvs_service.registration import lockstep
from ddvs_service.registration.coarse_search import coarse_alignment, usable_pixels
from ddvs_service.registration.config import ROBUST_CODES, RegistrationConfig
from ddvs_service.registration.images import F32, checked_image
from ddvs_service.registration.layout import ParamLayout
from ddvs_service.registration.reference import CurrentPyramid, Level, PreparedReference, Roi
from ddvs_service.registration.result import RegistrationResult
from ddvs_service.registration.solver import (
    LevelOutcome,
    NormalEquations,
    Reduced,
    bounded_gains,
    coarse_to_fine,
    gauss_newton,
    in_sequence,
    symmetric_index,
    unchanged,
    with_inliers,
)
from kernels.launch import Prepared
from kernels.planar_step import (
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
TRANSLATION = (0, 1)
SIMILARITY = (0, 1, 2, 4)  # sl(3) coordinates of translation, rotation and isotropic scale


@dataclass
class _State:
    G: F64
    gains: F64
    beta: float
    scale: float | None
    residual_rms: float = float("nan")
    inlier_ratio: float = 0.0
    cost: float = float("inf")
    scale_cap: float = float("inf")
    information: F64 | None = None  # JᵀWJ of the last full-resolution evaluation over all the unknowns


def in_level(level: Level, G: F64) -> F64:
    """`G` (full-resolution pixels) in level pixels, `D G D⁻¹`; `G` itself at level 0, where `D` is the identity
    (`images.level_matrix`: no product to pay on every tracked frame, which solves level 0 only)."""
    return G if level.index == 0 else level.D @ G @ level.D_inv


def in_full_resolution(level: Level, G_l: F64) -> F64:
    """The inverse of `in_level`: `D⁻¹ G_l D`, `G_l` itself at level 0."""
    return G_l if level.index == 0 else level.D_inv @ G_l @ level.D


def project(G: F64, pts: F64) -> F64:
    """Dehomogenised `G · pts` for homogeneous points `pts` (3, n) and one warp `G` (3, 3) → (2, n), or a stack of
    warps (K, 3, 3) → (K, 2, n)."""
    q = G @ pts
    return q[..., :2, :] / q[..., 2:3, :]


class PlanarRegistration:
    """The planar engine on a prepared reference: `run` registers an image. `config`: the solver's settings (the
    reference's own by default; those that shape the reference must agree with it, `PreparedReference.check_config`);
    `current`: the current image's workspace, shared with engines that run in turn on the same reference (a new one
    by default)."""

    def __init__(
        self,
        prepared: PreparedReference,
        config: RegistrationConfig | None = None,
        current: CurrentPyramid | None = None,
    ) -> None:
        from kernels.planar_step import n_acc, n_params, work_size

        self.prepared = prepared
        self.config = prepared.config if config is None else config
        prepared.check_config(self.config)
        self.current = CurrentPyramid(prepared) if current is None else current
        if self.current.reference is not prepared:
            raise ValueError("the current-image workspace belongs to another prepared reference")
        self.grid = self.config.gain_grid
        self.layout = ParamLayout.planar(*self.grid)
        if self.layout.size != n_params(*self.grid):
            raise AssertionError("parameter layout and kernel column order disagree")
        self._nacc = n_acc(self.layout.size)
        self._sym = symmetric_index(self.layout.size)
        self._robust_code = ROBUST_CODES[self.config.robust]
        self._params = np.zeros(PARAMS_GAINS + self.grid[0] * self.grid[1], dtype=np.float32)
        self._work = np.zeros(work_size(self.layout.size), dtype=np.float32)
        level = self.levels[0]
        T = level.N @ level.D
        # the sl(3) generators of level 0's update in full-resolution pixels, T⁻¹ Aᵢ T (`_covariance`)
        self._generators = np.linalg.inv(T) @ SL3_GENERATORS @ T
        # Each level's kernel is prepared once on the workspace's fixed buffers (`kernels.launch.Prepared`, on first
        # use), so that every later launch skips Taichi's per-call argument set-up.
        self._steps: dict[int, Prepared] = {}
        self._unknowns: dict[tuple[tuple[int, ...] | None, bool], tuple[NDArray[np.bool_], Any]] = {}
        self._filled: Level | None = None  # the level whose fixed parameters `_params` holds (`_fill_level`)

    @classmethod
    def prepare(
        cls,
        reference: ArrayLike,
        roi: Roi | None = None,
        mask: ArrayLike | None = None,
        config: RegistrationConfig = RegistrationConfig(),  # noqa: B008 - frozen, immutable default
    ) -> PlanarRegistration:
        """An engine on its own `PreparedReference.prepare(reference, roi, mask, config)`."""
        return cls(PreparedReference.prepare(reference, roi=roi, mask=mask, config=config))

    @property
    def roi(self) -> Roi:
        return self.prepared.roi

    @property
    def shape(self) -> tuple[int, int]:
        return self.prepared.shape

    @property
    def levels(self) -> tuple[Level, ...]:
        return self.prepared.levels

    @property
    def reference(self) -> tuple[F32, ...]:
        """The reference's pyramid, level 0 at full resolution."""
        return self.prepared.pyramid

    def run(
        self,
        current: ArrayLike,
        G0: ArrayLike | None = None,
        gains0: ArrayLike | float = 1.0,
        beta0: float = 0.0,
        scale0: float | None = None,
        first_level: int | None = None,
        tolerance_px: float | None = None,
        scale_cap: float | None = None,
        give_up: bool = False,
        min_inlier_ratio: float | None = None,
    ) -> RegistrationResult:
        """Register `current` starting from `G0` (any scale, positive determinant; identity by default), gains and
        bias (eq. (4)) and robust scale σ (grey levels; `None`: estimated from a first least-squares evaluation).
        `scale_cap` (grey levels): the largest σ the robust weights and the inlier count may use (none when None);
        the result's `scale` is the σ measured on the frame, uncapped.

        `first_level`: the coarsest pyramid level to solve (0 = full resolution only); the coarsest available by
        default. A warm start whose predicted motion is small starts finer and skips the coarse levels' cost.
        `tolerance_px`: convergence tolerance at full resolution (`config.step_tolerance_px` by default).
        `give_up`: a tracker's attempt from `G0`, which ends early on a hopeless frame (`solver.gauss_newton`, below
        the inlier ratio the result needs).
        `min_inlier_ratio`: the inlier ratio this call's result needs (`config.min_inlier_ratio` by default; a
        tracker lowers it while an occluder slides over the template, `integrity.Integrity.inlier_floor`)."""
        cur = checked_image(current, "current")
        if cur.shape != self.shape:
            raise ValueError(f"current image is {cur.shape[1]}×{cur.shape[0]}, expected the reference's "
                             f"{self.shape[1]}×{self.shape[0]}")
        levels = self.levels if first_level is None else self.levels[: max(0, first_level) + 1]
        G = np.eye(3) if G0 is None else sl3_normalize(np.asarray(G0, dtype=np.float64).reshape(3, 3))
        gains = np.empty(self.grid)
        gains[...] = gains0  # a scalar or the grid's node values, copied
        state = _State(G=G, gains=gains, beta=float(beta0), scale=scale0,
                       scale_cap=float("inf") if scale_cap is None else float(scale_cap))
        pyramid = self.load_current(cur, len(levels))
        fine = self.config.step_tolerance_px if tolerance_px is None else tolerance_px
        needed = self.config.min_inlier_ratio if min_inlier_ratio is None else min_inlier_ratio
        give_up_below = needed if give_up else None

        def solve(level: Level) -> LevelOutcome:
            tolerance = fine if level.index == 0 else self.config.coarse_step_tolerance_px
            if level is not levels[-1] or G0 is not None:
                return self._solve_level(level, state, tolerance, give_up_below=give_up_below)
            # Cold start: find the shift and a rough angle by correlation (`coarse_search`), match the photometric
            # moments, then settle the similarity part with the photometric unknowns frozen (a misaligned
            # least-squares gain shrinks towards 0 and erases the signal).
            start = coarse_alignment(self.reference[level.index], pyramid[level.index], level.bounds)
            if start is not None:
                state.G = level.D_inv @ start @ level.D
            self._match_moments(level, self.reference[level.index], pyramid[level.index], state)
            return in_sequence(lambda: self._solve_level(level, state, tolerance, TRANSLATION, False),
                               lambda: self._solve_level(level, state, tolerance, SIMILARITY, False),
                               lambda: self._solve_level(level, state, tolerance))

        outcome = coarse_to_fine(levels, solve)
        converged, reason = with_inliers(outcome.converged, outcome.reason, state.inlier_ratio, needed)
        return RegistrationResult(
            G=state.G, S=state.gains.copy(), beta=state.beta, iterations=outcome.iterations,
            residual_rms=state.residual_rms, inlier_ratio=state.inlier_ratio, converged=converged, reason=reason,
            failed=outcome.failed, scale=float("nan") if state.scale is None else state.scale,
            covariance=self._covariance(state),
        )

    def _covariance(self, state: _State) -> F64 | None:
        """`RegistrationResult.covariance`: σ² J (JᵀWJ)⁻¹_GG Jᵀ, the sl(3) block of the inverse (marginal over the
        photometric unknowns), J = ∂[vec(G), e]/∂x at the estimate, the update `G ← D⁻¹ G_l N⁻¹ exp(x) N D` of level
        0."""
        if state.information is None or state.scale is None:
            return None
        try:
            inverse = np.linalg.inv(state.information)[self.layout.slice("G"), self.layout.slice("G")]
        except np.linalg.LinAlgError:
            return None
        J = np.zeros((12, 8))  # e ≡ 0 is not estimated: its rows stay zero
        J[:9] = (state.G @ self._generators).reshape(8, 9).T
        return state.scale**2 * (J @ inverse @ J.T)

    def load_current(self, cur: NDArray[Any], n_levels: int) -> list[F32]:
        """The first `n_levels` levels of `cur`'s pyramid in the workspace's buffers (`CurrentPyramid.load`)."""
        return self.current.load(cur, n_levels)

    def unknowns(self, geometric: tuple[int, ...] | None, photometric: bool) -> tuple[NDArray[np.bool_], Any]:
        """The mask of the unknowns a level solves (`_PlanarLevel`: the sl(3) coordinates `geometric`, all when None,
        and the photometric ones when `photometric`) and its `np.ix_` index of `H`'s rows and columns (None when
        every unknown is free); built once per combination, read-only."""
        key = (geometric, photometric)
        if key not in self._unknowns:
            layout = self.layout
            free = np.zeros(layout.size, dtype=bool)
            sl_G = layout.slice("G")
            sl3 = np.arange(sl_G.start, sl_G.stop)
            free[sl3 if geometric is None else sl3[list(geometric)]] = True
            free[layout.slice("S")] = free[layout.slice("beta")] = photometric
            free.setflags(write=False)
            self._unknowns[key] = (free, None if free.all() else np.ix_(free, free))
        return self._unknowns[key]

    def _step(self, index: int) -> Prepared:
        """`kernels.planar_step` bound to level `index`'s reference and current buffers and this engine's parameter
        and work arrays."""
        from kernels.backend import compile_settings
        from kernels.planar_step import planar_step

        if index not in self._steps:
            with compile_settings():  # a new specialisation compiles here (kernels.backend.compile_settings)
                # a stack of one robot: views, no copies (`kernels.planar_step`, the robot axis)
                self._steps[index] = Prepared(planar_step, self.reference[index][None],
                                              self.current.buffers[index][None], self._params[None],
                                              self._work[None], self.grid[0], self.grid[1])
        return self._steps[index]

    def step_inputs(self, index: int) -> lockstep.StepInputs:
        """What level `index`'s step reads and writes, for a lock-step launch of several robots' steps
        (`registration.lockstep`)."""
        return lockstep.StepInputs(self.reference[index], self.current, index, self._params, self._work, self._nacc,
                                   self.grid)

    def _fill_level(self, level: Level) -> None:
        """The parameters fixed at one level: normalisation, ROI bounds, gain-grid span, band count (written only
        when another level's are there: a tracked frame solves the same level frame after frame)."""
        if level is self._filled:
            return
        self._filled = level
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
        p[PARAMS_SIGMA] = 1e30 if state.scale is None else min(state.scale, state.scale_cap)
        p[PARAMS_ROBUST] = 0 if state.scale is None else self._robust_code
        p[PARAMS_GAINS:] = state.gains.reshape(-1)

    def _match_moments(self, level: Level, ref: F32, cur: F32, state: _State) -> None:
        """Set a uniform gain and the bias so that `S·I(w(G, p*)) + β` has the mean and spread of `I*` over the ROI
        (the gain within `config.gain_range`, the bias then matching the means), from the reference pixels whose
        neighbourhood is unmasked (`coarse_search.usable_pixels`: a coarse level's pixel next to a masked one can hold
        a mixture with the masked value, −78 000 grey levels measured at level 3, which made the gain 479)."""
        from kernels.planar_step import render_compensated

        state.gains[:] = 1.0
        state.beta = 0.0
        self._fill_level(level)
        self._fill_state(in_level(level, state.G), state)
        u0, v0, u1, v1 = level.bounds
        warped = np.empty((v1 - v0 + 1, u1 - u0 + 1), dtype=np.float32)
        render_compensated(cur, self._params, warped, self.grid[0], self.grid[1])
        both = np.isfinite(warped) & (usable_pixels(ref, level.bounds)[v0 : v1 + 1, u0 : u1 + 1] > 0.0)
        a, b = ref[v0 : v1 + 1, u0 : u1 + 1][both], warped[both]
        if a.size > 1 and b.std() > 1e-3:
            gain = float(np.clip(a.std() / b.std(), *self.config.gain_range))
            state.gains[:] = gain
            state.beta = float(a.mean() - gain * b.mean())

    def _solve_level(
        self,
        level: Level,
        state: _State,
        tolerance: float,
        geometric: tuple[int, ...] | None = None,
        photometric: bool = True,
        give_up_below: float | None = None,
    ) -> LevelOutcome:
        """Gauss-Newton (`solver.gauss_newton`, with its `give_up_below`) at one level over the sl(3) coordinates
        `geometric` (all of them when None) and the photometric unknowns unless `photometric` is False, until the
        corner motion still to come is below `tolerance` level pixels; updates `state`."""
        model = _PlanarLevel(self, level, state, geometric, photometric)
        outcome = gauss_newton(model, state, self.config, level.index, level.n_pixels, level.size, tolerance,
                               give_up_below)
        state.G = sl3_normalize(in_full_resolution(level, model.G_l))
        return outcome


class _PlanarLevel:
    """The planar model at one level (`solver.LevelModel`): `G` held in level pixels (`G_l`) while it iterates;
    the step is the largest motion of the ROI corners (level pixels)."""

    check_every_iteration = False

    def __init__(self, engine: PlanarRegistration, level: Level, state: _State, geometric: tuple[int, ...] | None,
                 photometric: bool) -> None:
        self.engine, self.level, self.state = engine, level, state
        layout = engine.layout
        self._sl_G, self._sl_S, self._sl_b = layout.slice("G"), layout.slice("S"), layout.slice("beta")
        self.free, self._subset = engine.unknowns(geometric, photometric)
        self.G_l = in_level(level, state.G)
        self.corners = project(self.G_l, level.corners)
        engine._fill_level(level)
        self._launch = engine._step(level.index)

    def normal_equations(self, iteration: int) -> NormalEquations:
        self.engine._fill_state(self.G_l, self.state)
        batch = lockstep.current()
        if batch is None:
            self._launch()
        else:  # with the other robots' steps of a lock-step run, in one launch
            batch.evaluate(self.engine.step_inputs(self.level.index))
        engine = self.engine
        equations = NormalEquations.unpack(engine._work[: engine._nacc], len(self.free), engine._sym)
        if self.level.index == 0 and self._subset is None:
            self.state.information = equations.H
        return equations

    def reduce(self, equations: NormalEquations, iteration: int) -> Reduced:
        if self._subset is None:
            return Reduced(equations.H, equations.g, unchanged)

        def expand(x: F64) -> F64:
            delta = np.zeros(len(self.free))
            delta[self.free] = x
            return delta

        return Reduced(equations.H[self._subset], equations.g[self.free], expand)

    def trial(self, delta: F64) -> tuple[tuple[F64, F64, F64], float]:
        level = self.level
        G_l = self.G_l @ level.N_inv @ sl3_exp(delta[self._sl_G]) @ level.N
        moved = project(G_l, level.corners)
        return (G_l, moved, delta), float(np.abs(moved - self.corners).max())

    def accept(self, candidate: tuple[F64, F64, F64]) -> None:
        self.G_l, self.corners, delta = candidate
        self.state.gains = bounded_gains(self.state.gains, delta[self._sl_S], self.engine.config)
        self.state.beta = self.state.beta + float(delta[self._sl_b][0])


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
    problem = PlanarRegistration.prepare(reference, roi=roi, mask=mask, config=config)
    gains0, beta0 = (1.0, 0.0) if photometric0 is None else photometric0
    return problem.run(current, G0=G0, gains0=gains0, beta0=beta0)
