"""General (non-planar) direct registration: `G`, the epipole `e` and the parallax field ρ* of eq. (2)
`p ∝ G p* + ρ*(p*) e`, with the gains `S` and bias `β` of (4), minimising the robust cost (5).

Parametrisation (chosen from shared/notes/plane-parallax-estimation.md and the measurements in the report):
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

Cold start: several starting epipole directions (a hemisphere of `N e`; `e` and `−e` are the same start), each
refined with ρ* free, and the lowest robust cost wins; `margin` is the relative cost gap to the best *different*
epipole direction, which the notes measured at 9 % at the paper's start and < 0.1 % near the equilibrium.

Update at pyramid level l (level pixels, `D_l` of `images`): `G_l ← M G_l`, `e_l ← M e_l + N⁻¹ δe'`,
`M = N⁻¹ exp(Σ xᵢ Aᵢ) N` (left increment, Jacobian from `kernels.general_step`), `c ← c + δc`, `S ← S + δS`,
`β ← β + δβ`; then `(G, e) ← (G, e) / det(G)^(1/3)`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.lie import sl3_exp
from ddvs_service.registration.config import ROBUST_CODES, RegistrationConfig
from ddvs_service.registration.general_basis import ParallaxBasis
from ddvs_service.registration.images import F32
from ddvs_service.registration.planar import (
    DEGENERATE_RCOND,
    MAD_TO_SIGMA,
    PlanarRegistration,
    Roi,
    remaining_motion,
    symmetric_index,
)
from ddvs_service.registration.spline_window import UNRESTRICTED, SplineWindow
from kernels.launch import Prepared

F64 = NDArray[np.float64]
# Starting directions of N e (normalised, one per ± pair): lateral, diagonal, forward and oblique translations.
START_DIRECTIONS = np.array(
    [[1, 0, 0], [0, 1, 0], [1, 1, 0], [1, -1, 0], [0, 0, 1], [1, 0, 1], [-1, 0, 1], [0, 1, 1], [0, -1, 1]],
    dtype=np.float64,
)

FLAG_NO_PARALLAX = "no_parallax"  # parallax below detection: planar target or too little translation; ρ* := 0
FLAG_AMBIGUOUS = "ambiguous_parallax"  # a different parallax field fits almost as well
FLAG_LOW_TEXTURE = "low_texture"  # degenerate normal equations
FLAG_OCCLUSION = "occlusion"  # too few inliers / too little of the ROI visible
FLAG_LOST = "lost"  # the tracker lost the target and will re-acquire on the next frame
FLAG_DIVERGED = "diverged"
SPLINE_MARGIN = 0.1  # B-spline window margin around the warped ROI, × the ROI's larger side (`spline_window`)


@dataclass(frozen=True)
class GeneralConfig:
    """Settings of the general registration.

    - `base`: the planar engine's settings (pyramid, iterations, gain grid, robust loss, tolerances), shared.
    - `rho_degree`: 2 (biquadratic, 6 coefficients) or 3 (bicubic, 13).
    - `estimate_levels`: pyramid levels (finest first) on which ρ* is estimated from the planar solution.
    - `min_parallax_px`: RMS parallax displacement over the ROI below which ρ* is declared unobserved (set to 0).
    - `min_parallax_snr`: the parallax must also exceed this many standard errors.
    - `min_margin`: relative cost gap to a different parallax solution below which the result is flagged ambiguous.
    - `distinct_epipole_deg`: two solutions whose epipole directions differ by more than this are different.
    - `lost_after`: consecutive failed frames after which the tracker declares LOST and re-acquires.
    - `interpolation`: how the full-resolution steps sample the current image, "bspline" (the interpolating cubic
      B-spline, `kernels.bspline`; coarser levels keep Keys) or "keys" (Keys' cubic convolution). Near the paper's
      equilibrium the warp must be right to ~0.002 px for the control error (16) to be within 1e-4; there Keys' own
      error dominates the residual. Worst error of (16) along the paper's trajectory, × the criterion's tolerance
      (benchmarks/general_accuracy.py): anti-aliased frames (texture blurred by 2 texels, 4×4 rays per pixel)
      0.80 with the B-spline vs 2.71 with Keys; frames with a 0.7 px optical blur 1.80 vs 5.0; point-sampled
      (aliased) frames 8.7 vs 13.3, but 1.05 vs 0.76 on their first 180 images. The B-spline's prefilter, only over
      a window around the warped ROI (`spline_window`; the whole 550×418 image took ~0.7 ms), brings a tracking
      frame from 1.3–1.8 ms (Keys) to 2.2 ms on 2 cores.
    """

    base: RegistrationConfig = field(default_factory=RegistrationConfig)
    rho_degree: int = 2
    estimate_levels: int = 2
    min_parallax_px: float = 0.05
    min_parallax_snr: float = 10.0
    min_margin: float = 0.002
    distinct_epipole_deg: float = 20.0
    lost_after: int = 3
    interpolation: Literal["keys", "bspline"] = "bspline"

    def __post_init__(self) -> None:
        if self.rho_degree not in (2, 3):
            raise ValueError(f"rho_degree must be 2 or 3, got {self.rho_degree}")
        if self.estimate_levels < 1:
            raise ValueError(f"estimate_levels must be ≥ 1, got {self.estimate_levels}")
        if not self.min_parallax_px >= 0.0 or not self.min_parallax_snr >= 0.0:
            raise ValueError("min_parallax_px and min_parallax_snr must be ≥ 0")
        if self.lost_after < 1:
            raise ValueError(f"lost_after must be ≥ 1, got {self.lost_after}")
        if self.interpolation not in ("keys", "bspline"):
            raise ValueError(f"interpolation must be 'keys' or 'bspline', got {self.interpolation!r}")


@dataclass
class GeneralResult:
    """Estimate of eq. (2)+(4) for one frame.

    - `G` (3×3, det 1) and `e` (3, same scale as `G`): reference pixels → current pixels, `p ∝ G p* + ρ*(p*) e`.
    - `rho_coeffs`: ρ* coefficients in `basis` (gauge of the module docstring); `rho_at(p)` evaluates ρ*.
    - `rho_information`: Fisher information of `rho_coeffs` given `e` (accumulated over the frames by the tracker),
      `(JᵀWJ)/σ²` with the other unknowns marginalised; `parallax_px`: RMS over the ROI of the displacement due to
      `ρ* e` in this frame; `margin`: relative cost gap to the best different parallax field (estimation frames).
    - `S`, `beta`, `iterations`, `residual_rms`, `inlier_ratio`, `scale` as the planar `RegistrationResult`.
    - `converged`, `reason` and `flags` (`FLAG_*`): what went wrong, never silent.
    """

    G: F64
    e: F64
    rho_coeffs: F64
    basis: ParallaxBasis
    S: F64
    beta: float
    rho_information: F64
    parallax_px: float = 0.0
    margin: float = float("nan")
    iterations: list[int] = field(default_factory=list)
    residual_rms: float = float("nan")
    inlier_ratio: float = 0.0
    scale: float = float("nan")
    converged: bool = False
    reason: str = ""
    flags: list[str] = field(default_factory=list)

    @property
    def H(self) -> F64:
        """`G` normalised so that `H[2, 2] = 1`."""
        return self.G / self.G[2, 2]

    def rho_at(self, p: ArrayLike) -> float:
        """ρ* at one reference pixel `p = (u, v)` (e.g. the control point), gauge units."""
        return float(self.basis.rho(self.rho_coeffs, np.asarray(p, dtype=np.float64).reshape(1, 2))[0])

    def warp(self, p: ArrayLike) -> F64:
        """Current pixels (N × 2) of reference pixels `p` (N × 2) under eq. (2)."""
        return warp_points(self.G, self.e, self.basis, self.rho_coeffs, p)

    def rho_std(self) -> F64:
        """Standard errors of `rho_coeffs` (inf where the information is singular)."""
        return _std_from_information(self.rho_information)

    def to_json_dict(self) -> dict[str, Any]:
        """Plain-JSON view of the estimate and its status."""
        return {
            "H": self.H.tolist(), "G": self.G.tolist(), "e": self.e.tolist(), "rho_coeffs": self.rho_coeffs.tolist(),
            "rho_degree": self.basis.degree, "rho_std": [float(x) for x in self.rho_std()],
            "parallax_px": float(self.parallax_px), "margin": float(self.margin),
            "S": np.asarray(self.S).tolist(), "beta": float(self.beta), "iterations": [int(i) for i in self.iterations],
            "residual_rms": float(self.residual_rms), "inlier_ratio": float(self.inlier_ratio),
            "scale": float(self.scale), "converged": bool(self.converged), "reason": self.reason, "flags": self.flags,
        }


def _std_from_information(info: F64) -> F64:
    w, V = np.linalg.eigh(info)
    inv_w = np.where(w > 1e-12 * max(float(w.max(initial=0.0)), 1e-300), 1.0 / np.maximum(w, 1e-300), np.inf)
    with np.errstate(invalid="ignore"):
        var = (V**2) @ inv_w
    return np.sqrt(np.where(np.isnan(var), np.inf, var))


def warp_points(G: F64, e: F64, basis: ParallaxBasis, coeffs: F64, p: ArrayLike) -> F64:
    """`π(G p* + ρ*(p*) e)` for reference pixels `p` (N × 2), full resolution."""
    q = np.asarray(p, dtype=np.float64).reshape(-1, 2)
    return _warp(np.c_[q, np.ones(len(q))], basis.rho(coeffs, q), G, e)


def _warp(p_h: F64, rho: F64, G: F64, e: F64) -> F64:
    """Eq. (2) dehomogenised, `π(G p* + ρ* e)`, for homogeneous reference pixels `p_h` (N × 3) and their ρ* (N)."""
    P = p_h @ G.T + np.outer(rho, e)
    return P[:, :2] / P[:, 2:3]


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


def _normalise(state: _State) -> None:
    """`det G = 1` with `e` on the same scale (the warp (2) is unchanged)."""
    k = float(np.cbrt(np.linalg.det(state.G)))
    state.G = state.G / k
    state.e = state.e / k


class GeneralRegistration:
    """The reference side prepared once (pyramid, ROI levels, parallax basis, buffers); `estimate` finds ρ* from
    scratch, `track` registers a frame with ρ* held fixed."""

    def __init__(
        self,
        reference: ArrayLike,
        roi: Roi | None = None,
        mask: ArrayLike | None = None,
        config: GeneralConfig = GeneralConfig(),
    ) -> None:
        from kernels.general_step import params_size

        self.config = config
        self.planar = PlanarRegistration(reference, roi=roi, mask=mask, config=config.base)
        self.roi = self.planar.roi
        self.levels = self.planar.levels
        self.reference = self.planar.reference
        self.grid = self.planar.grid
        self.basis = ParallaxBasis.over(self.roi, config.rho_degree)
        self._params = np.zeros(params_size(self.basis.size), dtype=np.float32)
        self._work: dict[int, NDArray[np.float32]] = {}
        self._sym: dict[int, NDArray[np.intp]] = {}
        self._steps: dict[tuple[int, bool], tuple[F32, Prepared]] = {}  # prepared launches, with their `cur`
        self._spline = (SplineWindow(self.planar.shape, SPLINE_MARGIN * max(self.roi[2], self.roi[3]))
                        if config.interpolation == "bspline" else None)
        x, y, w, h = self.roi
        u, v = np.meshgrid(np.linspace(x, x + w - 1, 16), np.linspace(y, y + h - 1, 12))
        # Points where steps and parallax are measured (homogeneous, full resolution), and the basis there.
        self._probe = np.c_[u.ravel(), v.ravel(), np.ones(u.size)]
        self._probe_phi = self.basis.values(self._probe[:, :2])
        self.N0 = self.levels[0].N

    # ----------------------------------------------------------------------------------------------- public

    def estimate(self, current: F32, G0: F64 | None) -> GeneralResult:
        """ρ* from scratch: planar registration from `G0` (its own cold start when None), then every starting
        epipole direction refined with ρ* free; the lowest cost wins (module docstring)."""
        planar = self.planar.run(current, G0=G0)
        if not planar.converged or not np.all(np.isfinite(planar.G)):
            return self._failed(_State(planar.G if np.all(np.isfinite(planar.G)) else np.eye(3), np.zeros(3),
                                       np.zeros(self.basis.size), planar.S, planar.beta, None),
                                f"planar stage failed: {planar.reason}", _flags_for(planar.reason))
        pyramid = self._load_current(current, len(self.levels))
        levels = list(reversed(self.levels[: self.config.estimate_levels]))
        solutions: list[tuple[_State, list[int], bool, str]] = []
        for direction in START_DIRECTIONS:
            state = _State(planar.G.copy(), np.linalg.solve(self.N0, direction / np.linalg.norm(direction)),
                           np.zeros(self.basis.size), planar.S.copy(), planar.beta, planar.scale)
            iterations, converged, reason, failed = [], False, "", False
            for level in levels:
                n1, _, reason, failed = self._solve(level, pyramid, state, free_e=False, free_rho=True)
                if failed:
                    break
                n2, converged, reason, failed = self._solve(level, pyramid, state, free_e=True, free_rho=True)
                iterations.append(n1 + n2)
                if failed:
                    break
            if not failed:
                solutions.append((state, iterations, converged, reason))
        if not solutions:
            return self._failed(_State(planar.G, np.zeros(3), np.zeros(self.basis.size), planar.S, planar.beta,
                                       planar.scale), "every parallax start failed", [FLAG_DIVERGED])
        solutions.sort(key=lambda s: s[0].cost)
        best, iterations, converged, reason = solutions[0]
        rival = next((s for s, *_ in solutions[1:] if self._epipole_angle(best, s) > self.config.distinct_epipole_deg),
                     None)
        margin = (rival.cost - best.cost) / best.cost if rival is not None else float("inf")
        H, _, _ = self._normal_equations(self.levels[0], pyramid[0], best, with_rho=True)
        info = self._rho_information(H, best.scale)
        result = self._result(best, [*planar.iterations, *iterations], converged, reason, info)
        result.margin = margin
        self._check_parallax(result, best)
        if margin < self.config.min_margin and FLAG_NO_PARALLAX not in result.flags:
            result.flags.append(FLAG_AMBIGUOUS)
        return result

    def track(
        self, current: F32, G0: F64, e0: F64, rho: F64, gains0: ArrayLike | float = 1.0, beta0: float = 0.0,
        scale0: float | None = None, first_level: int | None = None, tolerance_px: float | None = None,
    ) -> GeneralResult:
        """Register `current` with ρ* = `rho` (coefficients) fixed, from `G0`, `e0`, gains and bias; `e` stays 0
        when ρ* is 0 (planar). The result carries the information on ρ* (`_rho_information`) of the first
        finest-level evaluation (the start of that level, a fraction of a pixel from the solution: that one launch
        also carries the ρ* columns, dropped from the step), or 0 when the frame's parallax is below
        `min_parallax_px` at the start or at the solution (no usable information; no ρ* columns are evaluated).
        `first_level`: the coarsest pyramid level solved (0 = full resolution only; default the coarsest), as
        `PlanarRegistration.run`: a warm start with small predicted motion skips the coarse levels.
        `tolerance_px`: convergence tolerance at full resolution (`config.base.step_tolerance_px` by default; the
        tracker passes `tracking_step_tolerance_px`)."""
        levels = self.levels if first_level is None else self.levels[: max(0, first_level) + 1]
        pyramid = self._load_current(current, len(levels))
        gains = np.broadcast_to(np.asarray(gains0, dtype=np.float64), self.grid).astype(np.float64).copy()
        state = _State(np.asarray(G0, dtype=np.float64).copy(), np.asarray(e0, dtype=np.float64).copy(),
                       np.asarray(rho, dtype=np.float64).copy(), gains, float(beta0), scale0)
        _normalise(state)
        free_e = bool(np.any(state.c != 0.0))
        information = free_e and self._observed(state)
        iterations: list[int] = []
        converged, reason = False, ""
        for level in reversed(levels):
            n, converged, reason, failed = self._solve(level, pyramid, state, free_e=free_e, free_rho=False,
                                                       tolerance_px=tolerance_px, information=information)
            iterations.append(n)
            if failed:
                return self._failed(state, reason, _flags_for(reason), iterations)
        observed = state.information is not None and self._observed(state)
        info = state.information if observed else np.zeros((self.basis.size,) * 2)
        return self._result(state, iterations, converged, reason, info)

    # --------------------------------------------------------------------------------------------- internals

    def _fill(self, level: Any, G_l: F64, e_l: F64, state: _State) -> None:
        from kernels import general_step as k

        p = self._params
        p[k.PARAMS_G : k.PARAMS_G + 9] = G_l.reshape(9)
        p[k.PARAMS_E : k.PARAMS_E + 3] = e_l
        p[k.PARAMS_NORM : k.PARAMS_NORM + 3] = level.norm
        p[k.PARAMS_BNORM : k.PARAMS_BNORM + 3] = self.basis.level_norm(level.D)
        p[k.PARAMS_ROI : k.PARAMS_ROI + 4] = level.bounds
        spline = level.index == 0 and self._spline is not None and self._spline.domain is not None
        p[k.PARAMS_DOMAIN : k.PARAMS_DOMAIN + 4] = self._spline.domain if spline else UNRESTRICTED
        p[k.PARAMS_SPAN : k.PARAMS_SPAN + 4] = level.span
        p[k.PARAMS_BETA] = state.beta
        p[k.PARAMS_SIGMA] = 1e30 if state.scale is None else state.scale
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
        self, level: Any, cur: F32, state: _State, with_rho: bool
    ) -> tuple[F64, F64, NDArray[np.float64]]:
        """One kernel launch at the state on the current level image `cur`: (JᵀWJ, JᵀWr, [n_valid, n_inliers, Σr²,
        median |r|]). With `config.interpolation` "bspline", level 0 is sampled through the B-spline coefficients of
        `cur` over a window around the ROI warped by the state (`spline_window`; samples outside its exact domain
        count as invalid). The launch is prepared once per (level, `with_rho`, buffer) (`kernels.launch.Prepared`)."""
        from kernels.general_step import general_step, n_acc, n_columns, work_size

        n = n_columns(self.basis.size, with_rho, *self.grid)
        if n not in self._work:
            self._work[n] = np.zeros(work_size(n), dtype=np.float32)
            self._sym[n] = symmetric_index(n)
        key = (level.index, with_rho)
        window = self._spline if level.index == 0 else None
        spline = window is not None
        if window is not None:
            probe = self._probe_warp(state.G, state.e, state.c)
            lo, hi = probe.min(axis=0), probe.max(axis=0)
            cur = window.covering(cur, (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])))
        if key not in self._steps or self._steps[key][0] is not cur:
            self._steps[key] = (cur, Prepared(general_step, self.reference[level.index], cur, self._params,
                                              self._work[n], self.basis.degree, self.basis.size, with_rho,
                                              *self.grid, spline))
        self._fill(level, level.D @ state.G @ level.D_inv, level.D @ state.e, state)
        self._steps[key][1]()
        acc = self._work[n][: n_acc(n)].astype(np.float64)
        nt = n * (n + 1) // 2
        return acc[self._sym[n]], acc[nt : nt + n], acc[nt + n :]

    def _solve(
        self, level: Any, pyramid: list[F32], state: _State, free_e: bool, free_rho: bool,
        tolerance_px: float | None = None, information: bool = False,
    ) -> tuple[int, bool, str, bool]:
        """Gauss-Newton at one level; returns (iterations, converged, reason, fatal failure). Converged: the probe
        points' motion still to come (`planar.remaining_motion`: the geometric tail of the last contractions of the
        steps, as the planar engine) is below `tolerance_px` (full resolution; `step_tolerance_px` by default) at
        the finest level, below `coarse_step_tolerance_px` (level pixels) on a coarser one (they only feed the next
        level). `information` (ρ* fixed): the first finest-level launch also carries the ρ* columns; their
        information goes to `state.information`, and they are dropped from that step."""
        cfg = self.config.base
        fine = cfg.step_tolerance_px if tolerance_px is None else tolerance_px
        tolerance = fine if level.index == 0 else cfg.coarse_step_tolerance_px
        nr = self.basis.size if free_rho else 0
        ng = self.grid[0] * self.grid[1]
        D, D_inv, N, N_inv = level.D, level.D_inv, level.N, level.N_inv
        tracked = np.r_[0:11, 11 + self.basis.size : 11 + self.basis.size + ng + 1]  # columns without ρ*
        e_sl = slice(8, 11)
        steps: list[float] = []
        for it in range(1, cfg.max_iterations + 1):
            with_information = information and not free_rho and level.index == 0 and it == 1
            H, g, stats = self._normal_equations(level, pyramid[level.index], state, free_rho or with_information)
            n_valid, n_inliers, sum_r2, median = stats
            if n_valid < cfg.min_valid_ratio * level.n_pixels:
                return it, False, (f"diverged at level {level.index}: only {n_valid / level.n_pixels:.0%} of the ROI "
                                   f"maps inside the current image (min_valid_ratio {cfg.min_valid_ratio:.0%})"), True
            state.residual_rms = math.sqrt(sum_r2 / n_valid)
            state.cost = sum_r2 / n_valid
            state.inlier_ratio = min(1.0, n_inliers / level.n_pixels) if state.scale is not None else 1.0
            state.scale = max(MAD_TO_SIGMA * median, cfg.scale_floor)
            if with_information:
                state.information = self._rho_information(H, state.scale)
                H, g = H[np.ix_(tracked, tracked)], g[tracked]
            T = np.eye(len(g))
            if not free_e:
                T = np.delete(T, [8, 9, 10], axis=1)
            elif free_rho:  # scale gauge: δe' orthogonal to N e (module docstring)
                d = N @ D @ state.e
                basis = np.linalg.svd(d.reshape(1, 3))[2][1:].T  # 3×2, orthonormal complement of d
                E = np.zeros((len(g), 2))
                E[e_sl] = basis
                T = np.hstack([T[:, :8], E, T[:, 11:]])
            Hr = T.T @ H @ T
            gr = T.T @ g
            dg = np.diag(Hr)
            if not np.all(dg > 0):
                return it, False, f"degenerate normal equations at level {level.index} (textureless ROI?)", True
            Hn = Hr / np.sqrt(np.outer(dg, dg))
            eig = np.linalg.eigvalsh(Hn)
            if not eig[0] > DEGENERATE_RCOND * eig[-1]:
                return it, False, (f"degenerate normal equations at level {level.index} (textureless ROI?): "
                                   f"reciprocal condition {eig[0] / eig[-1]:.1e}"), True
            delta = T @ np.linalg.solve(Hr, -gr)
            if not np.all(np.isfinite(delta)):
                return it, False, f"non-finite update at level {level.index}", True
            before = self._probe_warp(state.G, state.e, state.c)
            new = self._apply(state, delta, D, D_inv, N, N_inv, nr, ng, 1.0)
            step_px = float(np.max(np.abs(self._probe_warp(new.G, new.e, new.c) - before)))
            step = step_px * D[0, 0]  # level pixels
            limit = cfg.max_step_fraction * level.size
            if not step <= limit:
                factor = limit / step if math.isfinite(step) else 0.0
                new = self._apply(state, delta, D, D_inv, N, N_inv, nr, ng, factor)
            state.G, state.e, state.c, state.gains, state.beta = new.G, new.e, new.c, new.gains, new.beta
            if free_rho and free_e:
                self._fix_scale(state)
            steps.append(step)
            remaining = remaining_motion(steps)
            if remaining < tolerance:
                return it, True, (f"converged: last step {step:.1e} px, at most {remaining:.1e} px left "
                                  f"< {tolerance:g} px"), False
        return cfg.max_iterations, False, f"max_iterations ({cfg.max_iterations}) reached at level {level.index}", False

    def _apply(
        self, state: _State, delta: F64, D: F64, D_inv: F64, N: F64, N_inv: F64, nr: int, ng: int, factor: float
    ) -> _State:
        """The state after the update `factor · delta` (module docstring), normalised to det G = 1."""
        d = factor * delta
        M = N_inv @ sl3_exp(d[:8]) @ N
        G_l = M @ D @ state.G @ D_inv
        e_l = M @ D @ state.e + N_inv @ d[8:11]
        c = state.c + d[11 : 11 + nr] if nr else state.c.copy()
        off = 11 + nr
        new = _State(D_inv @ G_l @ D, D_inv @ e_l, c, state.gains + d[off : off + ng].reshape(self.grid),
                     state.beta + float(d[off + ng]), state.scale)
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
        nr = self.basis.size
        rho = np.arange(11, 11 + nr)
        other = np.r_[np.arange(8), np.arange(11 + nr, H.shape[0])]
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
        return _warp(self._probe, self._probe_phi @ c, G, e)

    def _observed(self, state: _State) -> bool:
        """Whether the parallax `ρ* e` of `state` reaches `min_parallax_px` RMS (probe points)."""
        return _rms(self._parallax_px(state.G, state.e, state.c)) >= self.config.min_parallax_px

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
        flags: list[str] = []
        cfg = self.config.base
        if converged and state.inlier_ratio < cfg.min_inlier_ratio:
            converged = False
            reason = f"inlier ratio {state.inlier_ratio:.3f} below min_inlier_ratio {cfg.min_inlier_ratio} (occlusion?)"
            flags.append(FLAG_OCCLUSION)
        parallax = self._parallax_px(state.G, state.e, state.c)
        return GeneralResult(
            G=state.G, e=state.e, rho_coeffs=state.c.copy(), basis=self.basis, S=state.gains.copy(), beta=state.beta,
            rho_information=info, parallax_px=_rms(parallax), iterations=iterations,
            residual_rms=state.residual_rms, inlier_ratio=state.inlier_ratio,
            scale=float("nan") if state.scale is None else state.scale, converged=converged, reason=reason, flags=flags,
        )

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


def _flags_for(reason: str) -> list[str]:
    """Failure flags from a reason string of the planar or general solver."""
    if "degenerate" in reason:
        return [FLAG_LOW_TEXTURE]
    if "inlier" in reason:
        return [FLAG_OCCLUSION]
    if "diverged" in reason or "non-finite" in reason:
        return [FLAG_DIVERGED]
    return []
