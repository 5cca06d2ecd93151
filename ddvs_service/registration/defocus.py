"""The relative defocus of a pair, estimated with the registration: `register_defocus`.

A defocused lens blurs irradiance by a uniform disk (bikes img6 against img1: a disk of radius ~5.5 px, fitted by
least squares with the ground truth). Registering a sharp reference against a defocused current image biases the
optimum of eq. (5) and slows the ESM iteration (its Jacobian averages a sharp and a blurred gradient). The model
`RegistrationConfig.defocus_px` blurs the reference's irradiance by the disk instead; this module finds the radius:
it registers with radii 0, 1, 2, … pixels (each run started from the best estimate so far) and keeps the one whose
result explains the current image best — the lowest *relative* residual, the residual RMS over the standard deviation
of the blurred reference in the ROI (a plain residual would reward blurring everything away) — among the converged
runs; a parabola through the best radius and its neighbours gives a fractional radius, tried last. The search stops
once the relative residual has risen at two consecutive radii past the best.

The reference is taken to be the sharper image (a servo's reference is shot at the desired pose, in focus).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from ddvs_service.registration.config import RegistrationConfig
from ddvs_service.registration.planar import PlanarRegistration
from ddvs_service.registration.reference import Roi
from ddvs_service.registration.result import RegistrationResult
from kernels.planar_step import MASK_LIMIT

DEFAULT_RADII = (0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0)  # full-resolution pixels
RISES_TO_STOP = 2


@dataclass(frozen=True)
class DefocusFit:
    """The kept registration, its defocus radius (full-resolution pixels) and relative residual, and every run as
    `(radius, relative residual, converged)` in the order tried."""

    result: RegistrationResult
    defocus_px: float
    relative_residual: float
    trials: tuple[tuple[float, float, bool], ...]


@dataclass(frozen=True)
class _Run:
    """One registration of the search: its relative residual and result."""

    relative: float
    result: RegistrationResult

    @property
    def score(self) -> float:
        """The relative residual of a converged run; infinite otherwise (never kept)."""
        return self.relative if self.result.converged else math.inf


def _relative_residual(problem: PlanarRegistration, result: RegistrationResult) -> float:
    """`result.residual_rms` over the standard deviation of the problem's (blurred) reference over its ROI."""
    x, y, w, h = problem.roi
    ref = problem.reference[0][y : y + h, x : x + w]
    spread = float(ref[ref > MASK_LIMIT].std())
    return result.residual_rms / spread if spread > 0.0 else math.inf


def register_defocus(
    reference: ArrayLike,
    current: ArrayLike,
    roi: Roi | None = None,
    mask: ArrayLike | None = None,
    G0: ArrayLike | None = None,
    config: RegistrationConfig = RegistrationConfig(),  # noqa: B008 - frozen, immutable default
    radii: tuple[float, ...] = DEFAULT_RADII,
) -> DefocusFit:
    """`planar.register` of `current` against `reference` with the relative defocus estimated (module docstring).

    Arguments as `planar.register` (`config.defocus_px` is replaced by each radius tried); `radii`: increasing radii
    to try, full-resolution pixels. Raises ValueError on bad input, like `register`."""
    if not radii or any(b <= a for a, b in itertools.pairwise(radii)) or radii[0] < 0.0:
        raise ValueError(f"radii must be increasing and ≥ 0 pixels, got {radii}")
    runs: dict[float, _Run] = {}  # in the order tried
    start = None if G0 is None else np.asarray(G0, dtype=np.float64)

    def attempt(radius: float) -> float:
        problem = PlanarRegistration.prepare(reference, roi=roi, mask=mask, config=config.replaced(defocus_px=radius))
        best = _best(runs)
        if best is None:
            result = problem.run(current, G0=start)
        else:
            kept = runs[best].result
            result = problem.run(current, G0=kept.G, gains0=kept.S, beta0=kept.beta)
        runs[radius] = _Run(_relative_residual(problem, result), result)
        return runs[radius].score

    rises, best_score = 0, math.inf
    for radius in radii:
        score = attempt(radius)
        if score < best_score:
            best_score, rises = score, 0
        elif math.isfinite(best_score):
            rises += 1
            if rises >= RISES_TO_STOP:
                break
    vertex = _parabola_vertex(runs)
    if vertex is not None and vertex not in runs:
        attempt(vertex)
    best = _best(runs)
    radius = min(runs) if best is None else best  # nothing converged: the smallest radius's run, flagged as it is
    trials = tuple((r, run.relative, run.result.converged) for r, run in runs.items())
    return DefocusFit(runs[radius].result, radius, runs[radius].relative, trials)


def _best(runs: dict[float, _Run]) -> float | None:
    """The radius of the converged run with the lowest relative residual, None when none converged."""
    finite = [radius for radius, run in runs.items() if math.isfinite(run.score)]
    return min(finite, key=lambda radius: runs[radius].score) if finite else None


def _parabola_vertex(runs: dict[float, _Run]) -> float | None:
    """Vertex of the parabola through the best converged radius and its two tried neighbours, when both are
    converged and the best is a strict interior minimum; None otherwise."""
    tried = sorted(runs)
    scores = [runs[r].score for r in tried]
    if not any(math.isfinite(s) for s in scores):
        return None
    i = int(np.argmin(scores))
    if not 0 < i < len(tried) - 1 or not (math.isfinite(scores[i - 1]) and math.isfinite(scores[i + 1])):
        return None
    (x0, x1, x2), (y0, y1, y2) = tried[i - 1 : i + 2], scores[i - 1 : i + 2]
    denominator = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / denominator
    b = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / denominator
    if not a > 0.0:
        return None
    return round(float(min(max(-b / (2.0 * a), x0), x2)), 2)
