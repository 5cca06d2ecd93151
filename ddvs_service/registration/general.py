"""General (non-planar) direct registration: `G`, the epipole `e` and the parallax field ρ* of eq. (2)
`p ∝ G p* + ρ*(p*) e`, with the gains `S` and bias `β` of (4), minimising the robust cost (5).

Parametrisation (chosen from docs/plane-parallax-estimation.md and the measurements in docs/results/):
ρ* is a smooth polynomial field over the ROI (`general_basis.ParallaxBasis`, biquadratic by default: 6 coefficients),
estimated once, on the first frame (the largest displacement), then held fixed in the reference frame; each later
frame estimates only `G`, `e`, `S`, `β` (8 + 3 + gains + 1 unknowns). Re-estimating ρ* every frame drifts into a
second, self-consistent wrong solution near the equilibrium where `e → 0` (notes, warning 2).

Gauge (the freedoms of (2), fixed explicitly):
- plane: ρ* has zero mean and zero first moments over the ROI (by construction of the basis), which picks the
  reference plane;
- scale: `(e, ρ*) ~ (s e, ρ*/s)` is fixed on the frame where ρ* is estimated by `‖N e‖ = 1`, `N` the ROI
  normalisation `q = (p − c)/s` (c the ROI centre, s half its larger side, pixels): ρ* is then a dimensionless
  parallax in units of that frame's epipole. During that estimation the update of `e` is restricted to the tangent
  space of the constraint and `(e, c)` are rescaled exactly after each step (the warp is unchanged). Later frames
  need no constraint: with ρ* fixed `e` shrinks smoothly to 0 at the equilibrium.
- `det G = 1` (SL(3)); `e` carries the same scale as `G`.
The control error (16) uses the product `ρ*(m*) e'`, invariant to the scale gauge; the plane gauge changes
`ε̄_v` by a factor `det(·)^(1/3)` that tends to 1 at the equilibrium (EQUATIONS.md).

Held epipole (`track`, with `config.hold_epipole_px` > 0): near the equilibrium the parallax `ρ* e` falls below what a
noisy frame can measure, and a free `e` then trades image noise against `G` along the tilt that keeps the control
point still (results/robustness: twice the control error's noise under JPEG on a dimmed scene). A tracked frame
whose warm start's parallax is below `hold_epipole_px` RMS holds `e` at 0 (the equilibrium's epipole: the planar fit,
with the same fixed point, biased by the parallax it ignores) and frees it again, solving that frame once more, when
the frame's own Gauss-Newton step on `e` (profiled over the other unknowns) is significant or would move the probe
points by `FREE_EPIPOLE_FACTOR` × `hold_epipole_px` or more, or when the held fit fails. Significance: the statistic
`êᵀ S ê / σ²` of `e` = 0 (S the Schur complement of the finest normal equations on `e`, σ the robust scale, `ê`
the held frame's step on `e` or a free frame's estimate, in the level's normalised coordinates; χ²₃ on independent
noise), `GeneralResult.epipole_wald`, reaching `FREE_EPIPOLE_WALD` on the frame, or `FREE_EPIPOLE_MEAN_WALD` on
average over a tracker's last `EPIPOLE_EVIDENCE_FRAMES` frames (`GeneralTracker`; then `e` starts free): a parallax
that every frame sees, however faintly, is not noise, which changes from frame to frame. So `e` stays free on clean
frames down to a few thousandths of a pixel of parallax, where holding it would bias the control error (16), and
is held where the frames' noise hides the parallax.

Cold start: several starting epipole directions (a hemisphere of `N e`; `e` and `−e` are the same start), each
refined with ρ* free, and the lowest robust cost wins; `margin` is the relative cost gap to the best *different*
epipole direction, which the notes measured at 9 % at the paper's start and < 0.1 % near the equilibrium. With ρ*
and `e` free the finest level can converge slowly (linearly, a step a fifth smaller each iteration); a start still
moving by less than `tracking_step_tolerance_px` after `max_iterations` has converged (`solver.gauss_newton`'s slow
verdict): the frames that follow are tracked to that tolerance.

Update at pyramid level l (level pixels, `D_l` of `images`): `G_l ← M G_l`, `e_l ← M e_l + N⁻¹ δe'`,
`M = N⁻¹ exp(Σ xᵢ Aᵢ) N` (left increment, Jacobian from `kernels.general_step`), `c ← c + δc`, `S ← S + δS`
within `config.base.gain_range` (`solver.bounded_gains`), `β ← β + δβ`; then `(G, e) ← (G, e) / det(G)^(1/3)`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.lie import SL3_GENERATORS, sl3_exp
from ddvs_service.registration.config import ROBUST_CODES
from ddvs_service.registration.general_basis import ParallaxBasis
from ddvs_service.registration.general_config import (
    FLAG_AMBIGUOUS,
    FLAG_DIVERGED,
    FLAG_NO_PARALLAX,
    FLAG_OCCLUSION,
    GeneralConfig,
)
from ddvs_service.registration.general_result import GeneralResult, flags_for, warp_homogeneous
from ddvs_service.registration.images import F32
from ddvs_service.registration.layout import ParamLayout
from ddvs_service.registration.planar import PlanarRegistration, in_full_resolution, in_level
from ddvs_service.registration.reference import CurrentPyramid, Level, PreparedReference, Roi
from ddvs_service.registration.solver import (
    LevelOutcome,
    NormalEquations,
    Outcome,
    Reduced,
    bounded_gains,
    coarse_to_fine,
    gauss_newton,
    in_sequence,
    symmetric_index,
    with_inliers,
)
from ddvs_service.registration.spline_window import UNRESTRICTED, SplineWindow
from kernels.launch import Prepared

F64 = NDArray[np.float64]
# Starting directions of N e (normalised, one per ± pair): lateral, diagonal, forward and oblique translations.
START_DIRECTIONS = np.array(
    [[1, 0, 0], [0, 1, 0], [1, 1, 0], [1, -1, 0], [0, 0, 1], [1, 0, 1], [-1, 0, 1], [0, 1, 1], [0, -1, 1]],
    dtype=np.float64,
)
FREE_EPIPOLE_FACTOR = 2.0  # hysteresis of the held epipole (module docstring): freed at 2 × hold_epipole_px
FREE_EPIPOLE_WALD = 100.0  # e ≠ 0 this significant on one frame frees e (module docstring; χ²₃ is 16 at 1e-3)
FREE_EPIPOLE_MEAN_WALD = 25.0  # ... or on average over the tracker's last EPIPOLE_EVIDENCE_FRAMES frames
EPIPOLE_EVIDENCE_FRAMES = 10
SPLINE_MARGIN = 0.1  # B-spline window margin around the warped ROI, × the ROI's larger side (`spline_window`)


@dataclass
class _State:
    G: F64
    e: F64
    c: F64
    gains: F64
    beta: float
    scale: float | None
    residual_rms: float = float("nan")
    inlier_ratio: float = 0.0
    cost: float = float("inf")
    information: F64 | None = None  # on ρ*, from the first finest-level evaluation of a tracked frame
    normal: tuple[ParamLayout, F64, F64] | None = None  # the last finest-level step's layout, T and TᵀHT (`reduce`)
    equations: tuple[F64, F64] | None = None  # the last finest-level step's H and g over its layout (`reduce`)
    scale_cap: float = float("inf")  # the largest σ the weights and the inlier count use (`registration.integrity`)


def _normalise(state: _State) -> None:
    """`det G = 1` with `e` on the same scale (the warp (2) is unchanged)."""
    k = float(np.cbrt(np.linalg.det(state.G)))
    state.G = state.G / k
    state.e = state.e / k


class GeneralRegistration:
    """The general engine on a prepared reference (its planar engine, on the same reference and workspace, is the
    first stage of `estimate`): `estimate` finds ρ* from scratch, `track` registers a frame with ρ* held fixed.
    `config.base` must agree with the reference's preparation (`PreparedReference.check_config`); `current`: the
    current image's workspace, shared with engines that run in turn on the same reference."""

    def __init__(
        self,
        prepared: PreparedReference,
        config: GeneralConfig = GeneralConfig(),  # noqa: B008 - frozen, immutable default
        current: CurrentPyramid | None = None,
    ) -> None:
        from kernels.general_step import n_columns, params_size

        self.config = config
        self.planar = PlanarRegistration(prepared, config.base, current)
        self.prepared = prepared
        self.current = self.planar.current
        self.roi = prepared.roi
        self.levels = prepared.levels
        self.reference = prepared.pyramid
        self.grid = self.planar.grid
        self.basis = ParallaxBasis.over(self.roi, config.rho_degree)
        self.layouts = {with_rho: ParamLayout.general(*self.grid, self.basis.size if with_rho else 0)
                        for with_rho in (False, True)}
        if any(layout.size != n_columns(self.basis.size, with_rho, *self.grid)
               for with_rho, layout in self.layouts.items()):
            raise AssertionError("parameter layout and kernel column order disagree")
        self._params = np.zeros(params_size(self.basis.size), dtype=np.float32)
        self._work: dict[int, NDArray[np.float32]] = {}
        self._sym: dict[int, NDArray[np.intp]] = {}
        self._steps: dict[tuple[int, bool], tuple[F32, Prepared]] = {}  # prepared launches, with their `cur`
        self._spline = (SplineWindow(prepared.shape, SPLINE_MARGIN * max(self.roi[2], self.roi[3]))
                        if config.interpolation == "bspline" else None)
        x, y, w, h = self.roi
        u, v = np.meshgrid(np.linspace(x, x + w - 1, 16), np.linspace(y, y + h - 1, 12))
        # Points where steps and parallax are measured (homogeneous, full resolution), and the basis there.
        self._probe = np.c_[u.ravel(), v.ravel(), np.ones(u.size)]
        self._probe_phi = self.basis.values(self._probe[:, :2])
        self.N0 = self.levels[0].N

    @classmethod
    def prepare(
        cls,
        reference: ArrayLike,
        roi: Roi | None = None,
        mask: ArrayLike | None = None,
        config: GeneralConfig = GeneralConfig(),  # noqa: B008 - frozen, immutable default
    ) -> GeneralRegistration:
        """An engine on its own `PreparedReference.prepare(reference, roi, mask, config.base)`."""
        return cls(PreparedReference.prepare(reference, roi=roi, mask=mask, config=config.base), config)

    # ----------------------------------------------------------------------------------------------- public

    def estimate(self, current: F32, G0: F64 | None) -> GeneralResult:
        """ρ* from scratch: planar registration from `G0` (its own cold start when None), then every starting
        epipole direction refined with ρ* free; the lowest cost wins (module docstring). The planar stage is a
        start, not a verdict: on a non-planar scene the best homography leaves a parallax residual that keeps the
        finest level from converging (or its inliers from reaching `min_inlier_ratio`) although it brings the
        general stage into its basin, so only a failed planar stage (`RegistrationResult.failed`) ends here; the
        general stage's convergence, inliers and margin decide."""
        planar = self.planar.run(current, G0=G0)
        if planar.failed or not np.all(np.isfinite(planar.G)):
            return self._failed(_State(planar.G if np.all(np.isfinite(planar.G)) else np.eye(3), np.zeros(3),
                                       np.zeros(self.basis.size), planar.S, planar.beta, None),
                                f"planar stage failed: {planar.reason}", flags_for(planar.reason))
        pyramid = self._load_current(current, len(self.levels))
        levels = self.levels[: self.config.estimate_levels]
        solutions: list[tuple[_State, list[int], bool, str]] = []
        for direction in START_DIRECTIONS:
            state = _State(planar.G.copy(), np.linalg.solve(self.N0, direction / np.linalg.norm(direction)),
                           np.zeros(self.basis.size), planar.S.copy(), planar.beta, planar.scale)

            def solve(level: Level, state: _State = state) -> LevelOutcome:
                return in_sequence(lambda: self._solve(level, pyramid, state, free_e=False, free_rho=True),
                                   lambda: self._solve(level, pyramid, state, free_e=True, free_rho=True,
                                                       slow_tolerance_px=self.config.base.tracking_step_tolerance_px))

            outcome = coarse_to_fine(levels, solve)
            if not outcome.failed:
                solutions.append((state, outcome.iterations, outcome.converged, outcome.reason))
        if not solutions:
            return self._failed(_State(planar.G, np.zeros(3), np.zeros(self.basis.size), planar.S, planar.beta,
                                       planar.scale), "every parallax start failed", [FLAG_DIVERGED])
        solutions.sort(key=lambda s: s[0].cost)
        best, iterations, converged, reason = solutions[0]
        rival = next((s for s, *_ in solutions[1:] if self._epipole_angle(best, s) > self.config.distinct_epipole_deg),
                     None)
        margin = (rival.cost - best.cost) / best.cost if rival is not None else float("inf")
        equations = self._normal_equations(self.levels[0], pyramid[0], best, with_rho=True)
        info = self._rho_information(equations.H, best.scale)
        result = self._result(best, [*planar.iterations, *iterations], converged, reason, info)
        result.margin = margin
        self._check_parallax(result, best)
        if margin < self.config.min_margin and FLAG_NO_PARALLAX not in result.flags:
            result.flags.append(FLAG_AMBIGUOUS)
        return result

    def track(
        self, current: F32, G0: F64, e0: F64, rho: F64, gains0: ArrayLike | float = 1.0, beta0: float = 0.0,
        scale0: float | None = None, first_level: int | None = None, tolerance_px: float | None = None,
        scale_cap: float | None = None, give_up: bool = False, may_hold_epipole: bool = True,
    ) -> GeneralResult:
        """Register `current` with ρ* = `rho` (coefficients) fixed, from `G0`, `e0`, gains and bias; `e` stays 0
        when ρ* is 0 (planar). The result carries the information on ρ* (`_rho_information`) of the first
        finest-level evaluation (the start of that level, a fraction of a pixel from the solution: that one launch
        also carries the ρ* columns, dropped from the step), or 0 when the frame's parallax is below
        `min_parallax_px` at the start or at the solution (no usable information; no ρ* columns are evaluated).
        `first_level`: the coarsest pyramid level solved (0 = full resolution only; default the coarsest), as
        `PlanarRegistration.run`: a warm start with small predicted motion skips the coarse levels.
        `tolerance_px`: convergence tolerance at full resolution (`config.base.step_tolerance_px` by default; the
        tracker passes `tracking_step_tolerance_px`). `scale_cap`: the largest robust scale used, and `give_up`: a
        tracker's attempt, which ends early on a hopeless frame (`solver.gauss_newton`, below
        `config.base.min_inlier_ratio`), as
        `PlanarRegistration.run`. `may_hold_epipole` False: `e` is free whatever the parallax (module docstring, held
        epipole: the tracker's last frames found it significant)."""
        levels = self.levels if first_level is None else self.levels[: max(0, first_level) + 1]
        pyramid = self._load_current(current, len(levels))
        gains = np.broadcast_to(np.asarray(gains0, dtype=np.float64), self.grid).astype(np.float64).copy()
        state = _State(np.asarray(G0, dtype=np.float64).copy(), np.asarray(e0, dtype=np.float64).copy(),
                       np.asarray(rho, dtype=np.float64).copy(), gains, float(beta0), scale0,
                       scale_cap=float("inf") if scale_cap is None else float(scale_cap))
        _normalise(state)
        give_up_below = self.config.base.min_inlier_ratio if give_up else None

        def solve(free_e: bool) -> Outcome:
            information = free_e and self._observed(state)
            return coarse_to_fine(levels, lambda level: self._solve(
                level, pyramid, state, free_e=free_e, free_rho=False, tolerance_px=tolerance_px,
                information=information, give_up_below=give_up_below))

        parallax = bool(np.any(state.c != 0.0))
        hold_px = self.config.hold_epipole_px
        held_e = (parallax and may_hold_epipole and hold_px > 0.0
                  and self.parallax_rms(state.G, state.e, state.c) < hold_px)
        if not held_e:
            outcome = solve(parallax)
        else:  # module docstring, held epipole
            start = replace(state)
            state.e = np.zeros(3)
            held = solve(False)
            wald, step = self._epipole_statistic(state, held=True)
            held_e = not held.failed and not self._epipole_seen(state, wald, step)
            if held_e:
                outcome = held
            else:  # the frame sees an epipole (`state.e` its step), or the held fit failed: from the start again
                if held.failed:
                    state = start
                outcome = solve(True)
                outcome = replace(outcome, iterations=[n + (held.iterations[i] if i < len(held.iterations) else 0)
                                                       for i, n in enumerate(outcome.iterations)])
        if outcome.failed:
            return self._failed(state, outcome.reason, flags_for(outcome.reason), outcome.iterations)
        observed = state.information is not None and self._observed(state)
        info = state.information if observed and state.information is not None else np.zeros((self.basis.size,) * 2)
        result = self._result(state, outcome.iterations, outcome.converged, outcome.reason, info)
        if parallax:
            result.epipole_wald = wald if held_e else self._epipole_statistic(state, held=False)[0]
        return result

    # --------------------------------------------------------------------------------------------- internals

    def _fill(self, level: Level, G_l: F64, e_l: F64, state: _State) -> None:
        from kernels import general_step as k

        p = self._params
        p[k.PARAMS_G : k.PARAMS_G + 9] = G_l.reshape(9)
        p[k.PARAMS_E : k.PARAMS_E + 3] = e_l
        p[k.PARAMS_NORM : k.PARAMS_NORM + 3] = level.norm
        p[k.PARAMS_BNORM : k.PARAMS_BNORM + 3] = self.basis.level_norm(level.D)
        p[k.PARAMS_ROI : k.PARAMS_ROI + 4] = level.bounds
        domain = self._spline.domain if level.index == 0 and self._spline is not None else None
        p[k.PARAMS_DOMAIN : k.PARAMS_DOMAIN + 4] = UNRESTRICTED if domain is None else domain
        p[k.PARAMS_SPAN : k.PARAMS_SPAN + 4] = level.span
        p[k.PARAMS_BETA] = state.beta
        p[k.PARAMS_SIGMA] = 1e30 if state.scale is None else min(state.scale, state.scale_cap)
        p[k.PARAMS_ROBUST] = 0 if state.scale is None else ROBUST_CODES[self.config.base.robust]
        p[k.PARAMS_BANDS] = self.config.base.bands_for(level.n_pixels)
        p[k.PARAMS_GAINS : k.PARAMS_GAINS + state.gains.size] = state.gains.reshape(-1)
        n_mono = (self.basis.degree + 1) ** 2
        p[k.PARAMS_RHO : k.PARAMS_RHO + n_mono] = self.basis.monomial_coefficients(state.c)
        for i, row in enumerate(self.basis.B):
            p[k.PARAMS_BASIS + i * k.MAX_MONOMIALS : k.PARAMS_BASIS + i * k.MAX_MONOMIALS + n_mono] = row

    def _load_current(self, current: F32, n_levels: int) -> list[F32]:
        """The first `n_levels` levels of the current image's pyramid, in the planar engine's fixed buffers (this
        object runs the planar stage on the same buffers), so that the step launches can be prepared once. With
        `config.interpolation` "bspline", level 0 is sampled through B-spline coefficients prefiltered around the
        warped ROI when a launch needs them (`_normal_equations`, `spline_window`)."""
        if self._spline is not None:
            self._spline.invalidate()
        return self.planar.load_current(current, n_levels)

    def _normal_equations(
        self, level: Level, cur: F32, state: _State, with_rho: bool
    ) -> NormalEquations:
        """One kernel launch at the state on the current level image `cur`: JᵀWJ, JᵀWr and the residual statistics
        over the columns of `layouts[with_rho]`. With `config.interpolation` "bspline", level 0 is sampled through
        the B-spline coefficients of `cur` over a window around the ROI warped by the state (`spline_window`; samples
        outside its exact domain count as invalid). The launch is prepared once per (level, `with_rho`, buffer)
        (`kernels.launch.Prepared`)."""
        from kernels.backend import compile_settings
        from kernels.general_step import general_step, n_acc, work_size

        n = self.layouts[with_rho].size
        if n not in self._work:
            self._work[n] = np.zeros(work_size(n), dtype=np.float32)
            self._sym[n] = symmetric_index(n)
        key = (level.index, with_rho)
        window = self._spline if level.index == 0 else None
        spline = int(window is not None)  # a run-time argument: one compiled kernel samples both ways
        if window is not None:
            probe = self._probe_warp(state.G, state.e, state.c)
            lo, hi = probe.min(axis=0), probe.max(axis=0)
            cur = window.covering(cur, (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])))
        if key not in self._steps or self._steps[key][0] is not cur:
            with compile_settings():  # a new specialisation (degree, `with_rho`, grid) compiles here
                self._steps[key] = (cur, Prepared(general_step, self.reference[level.index], cur, self._params,
                                                  self._work[n], self.basis.degree, self.basis.size, with_rho,
                                                  *self.grid, spline))
        self._fill(level, in_level(level, state.G), level.D @ state.e, state)
        self._steps[key][1]()
        return NormalEquations.unpack(self._work[n][: n_acc(n)], n, self._sym[n])

    def _solve(
        self, level: Level, pyramid: list[F32], state: _State, free_e: bool, free_rho: bool,
        tolerance_px: float | None = None, information: bool = False,
        give_up_below: float | None = None, slow_tolerance_px: float | None = None,
    ) -> LevelOutcome:
        """Gauss-Newton (`solver.gauss_newton`) at one level. Converged: the probe points' motion still to come is
        below `tolerance_px` (full resolution; `step_tolerance_px` by default) at the finest level, below
        `coarse_step_tolerance_px` (level pixels) on a coarser one (they only feed the next level). `information`
        (ρ* fixed): the first finest-level launch also carries the ρ* columns; their information goes to
        `state.information`, and they are dropped from that step. `give_up_below`: as `solver.gauss_newton`'s.
        `slow_tolerance_px`: at the finest level, `solver.gauss_newton`'s `slow_tolerance` (full resolution)."""
        cfg = self.config.base
        fine = cfg.step_tolerance_px if tolerance_px is None else tolerance_px
        tolerance = fine if level.index == 0 else cfg.coarse_step_tolerance_px
        slow = slow_tolerance_px if level.index == 0 else None
        model = _GeneralLevel(self, level, pyramid[level.index], state, free_e, free_rho, information)
        return gauss_newton(model, state, cfg, level.index, level.n_pixels, level.size, tolerance, give_up_below,
                            slow)

    def _apply(self, state: _State, delta: F64, level: Level, layout: ParamLayout) -> _State:
        """The state after the update `delta` (in `layout`; module docstring), normalised to det G = 1."""
        d = layout.split(delta)
        M = level.N_inv @ sl3_exp(d["G"]) @ level.N
        G_l = M @ level.D @ state.G @ level.D_inv
        e_l = M @ level.D @ state.e + level.N_inv @ d["e"]
        c = state.c + d["rho"] if d["rho"].size else state.c.copy()
        new = _State(in_full_resolution(level, G_l), level.D_inv @ e_l, c,
                     bounded_gains(state.gains, d["S"], self.config.base),
                     state.beta + float(d["beta"][0]), state.scale)
        _normalise(new)
        return new

    def _fix_scale(self, state: _State) -> None:
        """`‖N₀ e‖ = 1` by the exact rescaling `(e, c) → (e/k, k c)`."""
        k = float(np.linalg.norm(self.N0 @ state.e))
        if k > 0.0:
            state.e = state.e / k
            state.c = state.c * k

    def _rho_information(self, H: F64, sigma: float | None) -> F64:
        """Information on the ρ* coefficients given `e`, from the normal equations `H` of a launch with the ρ*
        columns: Schur complement of `H` over the other unknowns except `e`, divided by σ²."""
        layout = self.layouts[True]
        nr = self.basis.size
        rho, other = layout.indices("rho"), layout.indices("G", "S", "beta")
        Hoo = H[np.ix_(other, other)]
        Hro = H[np.ix_(rho, other)]
        try:
            schur = H[np.ix_(rho, rho)] - Hro @ np.linalg.solve(Hoo, Hro.T)
        except np.linalg.LinAlgError:
            return np.zeros((nr, nr))
        sigma = sigma if sigma else 1.0
        return 0.5 * (schur + schur.T) / sigma**2

    def _probe_warp(self, G: F64, e: F64, c: F64) -> F64:
        """`warp_points` at the probe points (full resolution), with the basis values there precomputed."""
        return warp_homogeneous(self._probe, self._probe_phi @ c, G, e)

    def _observed(self, state: _State) -> bool:
        """Whether the parallax `ρ* e` of `state` reaches `min_parallax_px` RMS (probe points)."""
        return self.parallax_rms(state.G, state.e, state.c) >= self.config.min_parallax_px

    def parallax_rms(self, G: F64, e: F64, c: F64) -> float:
        """RMS over the probe points of the displacement (full-resolution px) due to `ρ* e` at the warp of `G`, the
        epipole `e` (full-resolution pixels) and the ρ* coefficients `c`."""
        return _rms(self._parallax_px(G, e, c))

    def _epipole_seen(self, state: _State, wald: float, step: F64) -> bool:
        """Whether `state`, solved with `e` held at 0, sees an epipole: its step on `e` (`_epipole_statistic`:
        `wald`, `step`) is significant (`FREE_EPIPOLE_WALD`) or moves the probe points by at least
        `FREE_EPIPOLE_FACTOR` × `hold_epipole_px` RMS; that step is then `state.e`. Not without a statistic (nan:
        singular equations)."""
        if math.isnan(wald) or (wald < FREE_EPIPOLE_WALD and self.parallax_rms(state.G, step, state.c)
                                < FREE_EPIPOLE_FACTOR * self.config.hold_epipole_px):
            return False
        state.e = step
        return True

    def _epipole_statistic(self, state: _State, held: bool) -> tuple[float, F64]:
        """The significance `êᵀ S ê / σ²` of `e` ≠ 0 in `state` (module docstring, held epipole) from its last
        finest-level normal equations (S: their Schur complement on `e`, the other unknowns solved with it), and `ê`
        as a full-resolution epipole. `held`: `ê` is the Gauss-Newton step on `e` from 0 (the score of a frame solved
        with `e` held), else the estimate `state.e` (a free frame's). (nan, 0) without those equations or scale."""
        nothing = (float("nan"), np.zeros(3))
        if state.equations is None or state.scale is None:
            return nothing
        H, g = state.equations
        layout, level = self.layouts[False], self.levels[0]
        e, other = layout.indices("e"), layout.indices("G", "S", "beta")
        try:
            Heo_Hoo = np.linalg.solve(H[np.ix_(other, other)], H[np.ix_(other, e)]).T
            schur = H[np.ix_(e, e)] - Heo_Hoo @ H[np.ix_(other, e)]
            e_hat = np.linalg.solve(schur, Heo_Hoo @ g[other] - g[e]) if held else level.N @ level.D @ state.e
        except np.linalg.LinAlgError:
            return nothing
        return float(e_hat @ schur @ e_hat) / state.scale**2, level.D_inv @ level.N_inv @ e_hat

    def _parallax_px(self, G: F64, e: F64, c: F64) -> F64:
        """Displacement (px) due to `ρ* e` at the probe points."""
        return np.linalg.norm(self._probe_warp(G, e, c) - self._probe_warp(G, np.zeros(3), c), axis=1)

    def _epipole_angle(self, a: _State, b: _State) -> float:
        """Angle (degrees, sign-free) between two solutions' normalised epipoles `N₀ e`."""
        da, db = self.N0 @ a.e, self.N0 @ b.e
        cos = abs(float(da @ db)) / max(float(np.linalg.norm(da) * np.linalg.norm(db)), 1e-300)
        return math.degrees(math.acos(min(cos, 1.0)))

    def _check_parallax(self, result: GeneralResult, state: _State) -> None:
        """Declare ρ* unobserved (and set it to 0, `e` to 0) when its parallax is too small or too uncertain."""
        parallax = result.parallax_px
        std = result.rho_std()
        c_norm = float(np.linalg.norm(state.c))
        snr = c_norm / float(np.sqrt(np.mean(std**2))) if c_norm > 0 and np.all(np.isfinite(std)) else 0.0
        if parallax < self.config.min_parallax_px or snr < self.config.min_parallax_snr:
            result.flags.append(FLAG_NO_PARALLAX)
            result.reason += (f"; parallax {parallax:.3f} px RMS (SNR {snr:.1f}) below detection "
                              f"({self.config.min_parallax_px} px, SNR {self.config.min_parallax_snr}): planar "
                              "target or too little translation, ρ* set to 0")
            result.rho_coeffs = np.zeros_like(result.rho_coeffs)
            result.e = np.zeros(3)

    def _result(
        self, state: _State, iterations: list[int], converged: bool, reason: str, info: F64
    ) -> GeneralResult:
        checked, reason = with_inliers(converged, reason, state.inlier_ratio, self.config.base.min_inlier_ratio)
        flags = [FLAG_OCCLUSION] if converged and not checked else []
        converged = checked
        parallax = self._parallax_px(state.G, state.e, state.c)
        return GeneralResult(
            G=state.G, e=state.e, rho_coeffs=state.c.copy(), basis=self.basis, S=state.gains.copy(), beta=state.beta,
            rho_information=info, parallax_px=_rms(parallax), iterations=iterations,
            residual_rms=state.residual_rms, inlier_ratio=state.inlier_ratio,
            scale=float("nan") if state.scale is None else state.scale, converged=converged, reason=reason, flags=flags,
            covariance=self._covariance(state),
        )

    def _covariance(self, state: _State) -> F64 | None:
        """`RegistrationResult.covariance` over [vec(G), e]: σ² J T (TᵀHT)⁻¹ Tᵀ Jᵀ from the last finest-level step
        (T: the unknowns it solved, `reduce`), J = ∂[vec(G), e]/∂[x_G, δe] of the update `_apply` at level 0."""
        if state.normal is None or state.scale is None:
            return None
        layout, T, reduced = state.normal
        try:
            full = T @ np.linalg.inv(reduced) @ T.T
        except np.linalg.LinAlgError:
            return None
        ge = layout.indices("G", "e")
        level = self.levels[0]
        M = np.linalg.inv(level.N @ level.D)
        J = np.zeros((12, 11))
        for i, A in enumerate(SL3_GENERATORS):
            dM = M @ A @ np.linalg.inv(M)  # D⁻¹ N⁻¹ A N D
            J[:9, i] = (dM @ state.G).reshape(9)
            J[9:, i] = dM @ state.e
        J[9:, 8:] = M
        return state.scale**2 * (J @ full[np.ix_(ge, ge)] @ J.T)

    def _failed(
        self, state: _State, reason: str, flags: list[str], iterations: list[int] | None = None
    ) -> GeneralResult:
        return GeneralResult(
            G=state.G, e=state.e, rho_coeffs=state.c.copy(), basis=self.basis, S=np.asarray(state.gains, dtype=float),
            beta=float(state.beta), rho_information=np.zeros((self.basis.size,) * 2), iterations=iterations or [],
            converged=False, reason=reason, flags=flags,
        )


def _rms(x: F64) -> float:
    return float(np.sqrt(np.mean(x**2)))


class _GeneralLevel:
    """The general model at one level (`solver.LevelModel`): `G`, `e` (and ρ* when `free_rho`) in full-resolution
    pixels; the step is the largest motion of the probe points (level pixels)."""

    check_every_iteration = True

    def __init__(self, engine: GeneralRegistration, level: Level, cur: F32, state: _State, free_e: bool,
                 free_rho: bool, information: bool) -> None:
        self.engine, self.level, self.cur, self.state = engine, level, cur, state
        self.free_e, self.free_rho, self.information = free_e, free_rho, information
        self.layout = engine.layouts[free_rho]
        self._with_information = False

    def normal_equations(self, iteration: int) -> NormalEquations:
        self._with_information = (self.information and not self.free_rho and self.level.index == 0
                                  and iteration == 1)
        return self.engine._normal_equations(self.level, self.cur, self.state,
                                             self.free_rho or self._with_information)

    def reduce(self, equations: NormalEquations, iteration: int) -> Reduced:
        """The columns of `layout` (the ρ* columns of an information launch dropped after their information is
        kept), with `e` fixed (`free_e` False) or, with ρ* free, `δe'` orthogonal to `N e` (scale gauge, module
        docstring)."""
        H, g = equations.H, equations.g
        if self._with_information:
            self.state.information = self.engine._rho_information(H, self.state.scale)
            tracked = self.engine.layouts[True].indices("G", "e", "S", "beta")
            H, g = H[np.ix_(tracked, tracked)], g[tracked]
        e = self.layout.slice("e")
        T = np.eye(len(g))
        if not self.free_e:
            T = np.delete(T, np.arange(e.start, e.stop), axis=1)
        elif self.free_rho:
            d = self.level.N @ self.level.D @ self.state.e
            basis = np.linalg.svd(d.reshape(1, 3))[2][1:].T  # 3×2, orthonormal complement of d
            E = np.zeros((len(g), 2))
            E[e] = basis
            T = np.hstack([T[:, : e.start], E, T[:, e.stop :]])
        reduced = T.T @ H @ T
        if self.level.index == 0:
            self.state.normal = (self.layout, T, reduced)
            self.state.equations = (H, g)
        return Reduced(reduced, T.T @ g, lambda x: T @ x)

    def trial(self, delta: F64) -> tuple[_State, float]:
        engine, state = self.engine, self.state
        before = engine._probe_warp(state.G, state.e, state.c)
        new = engine._apply(state, delta, self.level, self.layout)
        step_px = float(np.max(np.abs(engine._probe_warp(new.G, new.e, new.c) - before)))
        return new, step_px * self.level.D[0, 0]

    def accept(self, candidate: _State) -> None:
        state = self.state
        state.G, state.e, state.c, state.gains, state.beta = (candidate.G, candidate.e, candidate.c, candidate.gains,
                                                              candidate.beta)
        if self.free_rho and self.free_e:
            self.engine._fix_scale(state)
