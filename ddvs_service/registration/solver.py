"""The Gauss-Newton/ESM skeleton shared by the planar and the general engines: the pyramid loop, the iterations at
one level, the robust scale, the degeneracy, step-limit and convergence tests, and the verdict.

An engine supplies only its model at one level (`LevelModel`): the normal equations at its current estimate (one
kernel launch), the unknowns it solves (a subset of its `ParamLayout`, or a gauge), and the update of its estimate
by a step. Each iteration (eq. (5), robust ESM):
1. `JᵀWJ`, `JᵀWr` and the residual statistics at the estimate; diverged when fewer than `min_valid_ratio` of the
   ROI's pixels map inside the current image;
2. the robust scale σ = 1.4826 · median |r| (never below `scale_floor`) for the next evaluation, the RMS residual
   and the inlier ratio;
3. the reduced normal equations; degenerate (textureless ROI) when a diagonal entry is not positive or the
   diagonally scaled matrix's reciprocal condition number is below `DEGENERATE_RCOND`;
4. the step `δ = −H⁻¹ g`, scaled down when it moves the model's probe points by more than `max_step_fraction` of
   the ROI size; the gain nodes' part of it projected onto `config.gain_range` by the engine's update
   (`bounded_gains`: a physical camera's gain is positive);
5. converged when the motion still to come (`remaining_motion` of the steps so far) is below the tolerance; after
   `max_iterations`, also when it is below an optional `slow_tolerance` (a slowly converging level whose estimate is
   already as close as a tracked frame's needs to be).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar, cast

import numpy as np
from numpy.typing import NDArray

from ddvs_service.registration.config import RegistrationConfig

F64 = NDArray[np.float64]
MAD_TO_SIGMA = 1.4826
DEGENERATE_RCOND = 1e-9
MAX_RATE = 0.8  # contraction above which the remaining-motion bound is not trusted
C = TypeVar("C")  # a model's candidate estimate
L = TypeVar("L")  # a pyramid level


@dataclass(slots=True)
class NormalEquations:
    """One evaluation at an estimate: `H = JᵀWJ`, `g = JᵀWr` over the model's columns, the count of valid and
    inlier ROI pixels, `Σ r²` over the valid ones and the median |r|."""

    H: F64
    g: F64
    n_valid: float
    n_inliers: float
    sum_r2: float
    median: float

    @classmethod
    def unpack(cls, accumulator: NDArray[np.float32], n: int, symmetric: NDArray[np.intp]) -> NormalEquations:
        """From a step kernel's accumulator: the row-major upper triangle of `H`, then `g` (n), then the four
        statistics; `symmetric` is `symmetric_index(n)`."""
        acc = accumulator.astype(np.float64)
        nt = n * (n + 1) // 2
        n_valid, n_inliers, sum_r2, median = acc[nt + n : nt + n + 4].tolist()  # plain floats: scalar arithmetic
        return cls(acc[symmetric], acc[nt : nt + n], n_valid, n_inliers, sum_r2, median)


def unchanged(x: F64) -> F64:
    """The `expand` of normal equations solved over every unknown."""
    return x


def symmetric_index(n: int) -> NDArray[np.intp]:
    """`idx[i, j]`: position of `H[min(i, j), max(i, j)]` in the kernel's row-major upper triangle."""
    i, j = np.minimum.outer(np.arange(n), np.arange(n)), np.maximum.outer(np.arange(n), np.arange(n))
    return i * n - i * (i - 1) // 2 + (j - i)


class Fit(Protocol):
    """The robust statistics of an estimate that the skeleton keeps up to date (grey levels)."""

    scale: float | None  # σ of the next evaluation; None: plain least squares
    residual_rms: float
    inlier_ratio: float
    cost: float  # mean squared residual over the valid pixels


@dataclass(slots=True)
class Reduced:
    """The normal equations over the unknowns actually solved (`H`, `g`), and the map `expand` of their solution to
    the model's full update vector."""

    H: F64
    g: F64
    expand: Callable[[F64], F64]


class LevelModel(Protocol[C]):
    """One engine's model at one pyramid level, bound to its estimate (which it updates)."""

    check_every_iteration: bool  # degeneracy tested on every iteration (else on the first only)

    def normal_equations(self, iteration: int) -> NormalEquations:
        """Evaluate at the current estimate (one kernel launch)."""
        ...

    def reduce(self, equations: NormalEquations, iteration: int) -> Reduced:
        """The unknowns solved this iteration (a subset of the layout's blocks, a gauge)."""
        ...

    def trial(self, delta: F64) -> tuple[C, float]:
        """The estimate after the update `delta` (full update vector) and the largest motion it causes (level
        pixels) at the model's probe points."""
        ...

    def accept(self, candidate: C) -> None:
        """Make `candidate` (from `trial`) the current estimate."""
        ...


@dataclass(frozen=True)
class LevelOutcome:
    """How a solve at one level ended: iterations run, converged, why, and `failed` (the estimate is unusable and
    the coarse-to-fine loop stops)."""

    iterations: int
    converged: bool
    reason: str
    failed: bool


@dataclass(frozen=True)
class Outcome:
    """How a coarse-to-fine solve ended: iterations per level (coarse → fine), the last level's verdict."""

    iterations: list[int]
    converged: bool
    reason: str
    failed: bool


def gauss_newton(
    model: LevelModel[C], fit: Fit, config: RegistrationConfig, level_index: int, n_pixels: int, size: float,
    tolerance: float, give_up_below: float | None = None, slow_tolerance: float | None = None,
) -> LevelOutcome:
    """Iterate at one level (module docstring) until the motion still to come is below `tolerance` (level pixels),
    at most `config.max_iterations` times. `n_pixels`: the level's ROI pixels; `size`: the ROI's larger side.

    `give_up_below` (the trackers' attempts, which a lost frame must not make slow: the inlier ratio their result
    needs): after `config.tracking_give_up_iterations` iterations without converging, the level has failed, which
    ends the coarse-to-fine solve, unless it is the finest and its inlier ratio is at least `give_up_below`. A frame
    within reach converges at a coarse level in a few iterations, and a slow one at the finest level (noise) keeps
    its support; on a lost frame (the target hidden or out of reach) every level would run `max_iterations`.
    `slow_tolerance` (level pixels, above `tolerance`): after `max_iterations`, a level with less motion than this
    still to come has converged, slowly (the verdict's reason says so)."""
    limit = config.max_step_fraction * size
    steps: list[float] = []
    for it in range(1, config.max_iterations + 1):
        eq = model.normal_equations(it)
        valid_ratio = eq.n_valid / n_pixels
        if valid_ratio < config.min_valid_ratio:
            return LevelOutcome(it, False, (f"diverged at level {level_index}: only {valid_ratio:.0%} of the ROI maps "
                                            f"inside the current image (min_valid_ratio {config.min_valid_ratio:.0%})"),
                                True)
        fit.residual_rms = math.sqrt(eq.sum_r2 / eq.n_valid)
        fit.cost = eq.sum_r2 / eq.n_valid
        fit.inlier_ratio = min(1.0, eq.n_inliers / n_pixels) if fit.scale is not None else 1.0
        fit.scale = max(MAD_TO_SIGMA * eq.median, config.scale_floor)
        reduced = model.reduce(eq, it)
        if it == 1 or model.check_every_iteration:
            degenerate = degeneracy(reduced.H)
            if degenerate:
                return LevelOutcome(it, False, f"degenerate normal equations at level {level_index} (textureless ROI?)"
                                               f"{degenerate}", True)
        try:
            delta = reduced.expand(cast(F64, np.linalg.solve(reduced.H, -reduced.g)))
        except np.linalg.LinAlgError:
            delta = reduced.expand(np.full(len(reduced.g), np.nan))
        if not math.isfinite(float(delta.sum())):  # any NaN or infinite entry makes the sum non-finite
            return LevelOutcome(it, False, f"non-finite update at level {level_index}", True)
        candidate, step = model.trial(delta)
        if not step <= limit:  # also catches NaN
            candidate, _ = model.trial(delta * (limit / step) if math.isfinite(step) else np.zeros_like(delta))
        model.accept(candidate)
        steps.append(step)
        remaining = remaining_motion(steps)
        if remaining < tolerance:
            return LevelOutcome(it, True, f"converged: last step {step:.1e} px, at most {remaining:.1e} px left "
                                          f"< {tolerance:g} px", False)
        if give_up_below is not None and it == config.tracking_give_up_iterations and (
                level_index > 0 or fit.inlier_ratio < give_up_below):
            why = "a coarse level" if level_index > 0 else f"inlier ratio {fit.inlier_ratio:.3f} < {give_up_below:g}"
            return LevelOutcome(it, False, f"given up at level {level_index} after {it} iterations ({why})", True)
    remaining = remaining_motion(steps)
    if slow_tolerance is not None and remaining < slow_tolerance:
        return LevelOutcome(config.max_iterations, True, (
            f"converged slowly: max_iterations ({config.max_iterations}) reached at level {level_index} with at most "
            f"{remaining:.1e} px left < {slow_tolerance:g} px"), False)
    return LevelOutcome(config.max_iterations, False,
                        f"max_iterations ({config.max_iterations}) reached at level {level_index}", False)


def bounded_gains(gains: F64, step: F64, config: RegistrationConfig) -> F64:
    """The gain nodes of eq. (4) after the update `step` (any shape with `gains.size` entries), projected onto
    `config.gain_range`: the update of both engines. A projected Gauss-Newton step: a node the data pull below the
    lowest gain (e.g. one under an occluder, whose pixels the robust weights mostly reject) stays there while the
    geometry and the other nodes are solved again at the next iteration."""
    low, high = config.gain_range
    return np.minimum(np.maximum(gains + np.reshape(step, gains.shape), low), high)  # np.clip without its wrappers


def in_sequence(*phases: Callable[[], LevelOutcome]) -> LevelOutcome:
    """Solve the phases of one level in order (e.g. a subset of the unknowns, then all) until one fails: their
    iterations add up, the verdict is the last phase's."""
    count, outcome = 0, LevelOutcome(0, False, "", False)
    for phase in phases:
        outcome = phase()
        count += outcome.iterations
        if outcome.failed:
            break
    return LevelOutcome(count, outcome.converged, outcome.reason, outcome.failed)


def coarse_to_fine(levels: Sequence[L], solve: Callable[[L], LevelOutcome]) -> Outcome:
    """`solve` each level from the coarsest (last) to the finest; stops at a failed one."""
    iterations: list[int] = []
    outcome = LevelOutcome(0, False, "", False)
    for level in reversed(levels):
        outcome = solve(level)
        iterations.append(outcome.iterations)
        if outcome.failed:
            break
    return Outcome(iterations, outcome.converged, outcome.reason, outcome.failed)


def with_inliers(converged: bool, reason: str, inlier_ratio: float, min_inlier_ratio: float) -> tuple[bool, str]:
    """The verdict once the inlier ratio is checked: a converged solve with fewer than `min_inlier_ratio` of the
    ROI's pixels within 4.685 σ is not converged."""
    if converged and inlier_ratio < min_inlier_ratio:
        return False, f"inlier ratio {inlier_ratio:.3f} below min_inlier_ratio {min_inlier_ratio}"
    return converged, reason


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


def degeneracy(H: F64) -> str:
    """Why the normal matrix `H` is too ill-conditioned to solve (empty when it is fine): a non-positive diagonal
    or a reciprocal condition number of the diagonally scaled matrix `S = D^-½ H D^-½` (D = diag H) below
    `DEGENERATE_RCOND`.

    Most matrices are settled by one Cholesky factorisation (cheaper than the eigenvalues): `S`'s largest
    eigenvalue is at most its trace n, so when `S − 2n·rcond·I` is positive definite — when `H − 2n·rcond·D` is,
    the same test by congruence, which Cholesky decides to within a few n·ε of `S`'s smallest eigenvalue, far
    inside the factor 2 — the reciprocal condition number exceeds `rcond` and the diagonal is positive. Otherwise,
    and for a matrix with NaN or infinite entries, the eigenvalues decide."""
    shifted = H * _diagonal_shift(len(H))
    try:  # numpy factors a matrix with NaN or infinite entries without complaint: its factor's diagonal is not finite
        if math.isfinite(float(np.trace(np.linalg.cholesky(shifted)))):
            return ""
    except np.linalg.LinAlgError:
        pass
    d = np.diag(H)
    if not np.all(d > 0):
        return ": a parameter has no effect on the residuals"
    eig = np.linalg.eigvalsh(H / np.sqrt(np.outer(d, d)))
    if not eig[0] > DEGENERATE_RCOND * eig[-1]:
        return f": reciprocal condition {eig[0] / eig[-1]:.1e}"
    return ""


@functools.lru_cache(maxsize=8)
def _diagonal_shift(n: int) -> F64:
    """`degeneracy`'s multiplier (read-only, one per size): 1 off the diagonal, 1 − 2n·rcond on it."""
    factors = np.ones((n, n))
    factors.flat[:: n + 1] = 1.0 - 2.0 * n * DEGENERATE_RCOND
    factors.setflags(write=False)
    return factors
