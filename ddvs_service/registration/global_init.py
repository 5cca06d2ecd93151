"""Global initialisation and re-acquisition from large displacements (issue 9).

`GlobalInitializer.initialize(reference, roi, current)`:
1. hypotheses: direct Fourier–Mellin search (`global_fourier_mellin.py`: any in-plane rotation, scale 0.6–1.6, ROI
   anywhere with part of it outside the image), plus, when `config.feature_source` is 'orb' or 'akaze', one RANSAC
   homography from features (`global_features.py`);
2. the `max_refined` best distinct hypotheses (by robust photometric cost, `global_cost.py`) are screened by a short
   refinement, and the `final_refined` best distinct screened ones are refined fully, by a `Refiner` – the planar
   direct engine (coarse to fine, eqs. (4)–(5) with ρ* ≡ 0) by default. A refiner returns one
   or several refinements per start (hook for the general model of eq. (2) started from several epipole
   directions) and the current image sampled at its own warp, so any model is scored the same way;
3. the refinements are ranked by the robust photometric cost; `margin` = cost of the best *different* solution (warp
   farther than `distinct_px` RMS over the ROI) minus the winner's (1 − winner's cost when there is none);
4. status "LOST" when the winner's cost exceeds `max_cost`, its visible ROI fraction is below `min_visible`, or the
   margin is below `min_margin` — never a confident wrong estimate.

`G` maps reference pixels to current pixels (full-image 0-based pixel centres), det 1.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from ddvs_service.registration.global_cost import PhotometricScore, photometric_score, sample_through
from ddvs_service.registration.global_features import feature_homography
from ddvs_service.registration.global_fourier_mellin import FourierMellinConfig, Hypothesis, fourier_mellin_hypotheses
from ddvs_service.registration.global_scenes import warp_rms
from kernels import backend

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
Roi = tuple[int, int, int, int]


@dataclass(frozen=True)
class Refinement:
    """One refined estimate: planar part `G`, the current image sampled at the model's warp of every ROI pixel
    (`sampled`, `valid`, shape (h, w)), the model's name and its own result object (`detail`)."""

    G: F64
    sampled: F32
    valid: F32
    model: str
    detail: Any = None


class Refiner(Protocol):
    """Refines a starting warp `G0` of a fixed reference ROI in `current`; may return several refinements
    (e.g. the general model started from several epipole directions). `quick` asks for a short screening run
    (few iterations) used to rank many starts before the full refinement of the best ones."""

    def __call__(self, current: F32, G0: F64, quick: bool = False) -> list[Refinement]: ...


RefinerFactory = Callable[[F32, Roi], Refiner]


class PlanarRefiner:
    """The planar direct engine (`registration.planar.PlanarRegistration`, coarse to fine) as a `Refiner`."""

    def __init__(self, reference: F32, roi: Roi, config: Any = None, screen_iterations: int = 4) -> None:
        from ddvs_service.registration.config import RegistrationConfig
        from ddvs_service.registration.planar import PlanarRegistration

        self.roi = roi
        full = config or RegistrationConfig()
        self.problem = PlanarRegistration(reference, roi=roi, config=full)
        quick = replace(full, max_iterations=screen_iterations)
        self.screen = PlanarRegistration(reference, roi=roi, config=quick)

    def __call__(self, current: F32, G0: F64, quick: bool = False) -> list[Refinement]:
        result = (self.screen if quick else self.problem).run(current, G0=G0)
        if not np.all(np.isfinite(result.G)):
            return []
        x, y, w, h = self.roi
        sampled, valid = sample_through(current, result.G, (h, w), (x, y))
        return [Refinement(G=result.G, sampled=sampled, valid=valid, model="planar", detail=result)]


@dataclass(frozen=True)
class GlobalInitConfig:
    """Hypothesis sources, refinement budget and the LOST criteria (costs are `global_cost` units in [0, 1])."""

    fourier_mellin: FourierMellinConfig = field(default_factory=FourierMellinConfig)
    feature_source: Literal["none", "orb", "akaze"] = "none"
    max_refined: int = 6  # distinct hypotheses screened by a short refinement
    final_refined: int = 2  # distinct screened candidates refined fully
    distinct_px: float = 3.0  # two warps closer than this (RMS over the ROI) are the same solution
    max_cost: float = 0.3  # winner's robust photometric cost above this → LOST
    min_margin: float = 0.1  # best different solution's cost minus the winner's below this → LOST
    min_visible: float = 0.5  # winner's visible ROI fraction below this → LOST


@dataclass(frozen=True)
class Candidate:
    """A refined hypothesis: where it started, what it became, and its score."""

    source: str
    start_cost: float
    refinement: Refinement
    score: PhotometricScore


@dataclass(frozen=True)
class InitResult:
    """Outcome of one global initialisation: `status` 'OK' or 'LOST', the winner's `G` (None when LOST), `cost`,
    `margin`, `reason`, every refined `candidates` (best first) and the count of raw `hypotheses`."""

    status: Literal["OK", "LOST"]
    G: F64 | None
    cost: float
    margin: float
    reason: str
    candidates: list[Candidate]
    hypotheses: int

    @property
    def winner(self) -> Candidate | None:
        return self.candidates[0] if self.candidates else None

    def to_json_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary (for `ddvs register --init global`)."""
        return {
            "status": self.status,
            "G": None if self.G is None else self.G.tolist(),
            "cost": self.cost,
            "margin": self.margin,
            "reason": self.reason,
            "hypotheses": self.hypotheses,
            "candidates": [
                {"source": c.source, "model": c.refinement.model, "start_cost": c.start_cost, "cost": c.score.cost,
                 "zncc": c.score.zncc, "visible": c.score.visible}
                for c in self.candidates
            ],
        }


def _check_inputs(reference: F32, roi: Roi, current: F32) -> tuple[F32, F32]:
    ref = np.ascontiguousarray(reference, dtype=np.float32)
    cur = np.ascontiguousarray(current, dtype=np.float32)
    if ref.ndim != 2 or cur.ndim != 2:
        raise ValueError(f"expected 2-D grey images, got reference {ref.shape} and current {cur.shape}")
    x, y, w, h = roi
    if w < 16 or h < 16 or x < 0 or y < 0 or x + w > ref.shape[1] or y + h > ref.shape[0]:
        raise ValueError(
            f"roi {roi} must be at least 16×16 and inside the reference image {ref.shape[1]}×{ref.shape[0]}"
        )
    if not (np.isfinite(ref).all() and np.isfinite(cur).all()):
        raise ValueError("images contain NaN or Inf; expected finite grey levels")
    return ref, cur


class GlobalInitializer:
    """Direct global initialiser; `refiner_factory(reference, roi)` builds the refiner (planar engine by default)."""

    def __init__(self, config: GlobalInitConfig | None = None, refiner_factory: RefinerFactory | None = None) -> None:
        backend.init()
        self.config = config or GlobalInitConfig()
        self.refiner_factory: RefinerFactory = refiner_factory or PlanarRefiner

    def hypotheses(self, reference: F32, roi: Roi, current: F32) -> list[Hypothesis]:
        """Raw hypotheses, lowest photometric cost first (direct ones, plus the feature one if configured)."""
        ref, cur = _check_inputs(reference, roi, current)
        found = fourier_mellin_hypotheses(ref, roi, cur, self.config.fourier_mellin)
        if self.config.feature_source != "none":
            G = feature_homography(ref, roi, cur, self.config.feature_source)
            if G is not None:
                x, y, w, h = roi
                sampled, valid = sample_through(cur, G, (h, w), (x, y))
                score = photometric_score(ref[y : y + h, x : x + w], sampled, valid)
                found.append(Hypothesis(G=G, source=self.config.feature_source, score=score))
        return sorted(found, key=lambda hyp: hyp.score.cost)

    def initialize(self, reference: F32, roi: Roi, current: F32) -> InitResult:
        """Hypotheses → refinement of the best distinct ones → winner by robust cost, margin, LOST decision."""
        cfg = self.config
        ref, cur = _check_inputs(reference, roi, current)
        raw = self.hypotheses(ref, roi, cur)
        starts: list[Hypothesis] = []
        for hyp in raw:
            if len(starts) == cfg.max_refined:
                break
            if all(warp_rms(hyp.G, s.G, roi) > cfg.distinct_px for s in starts):
                starts.append(hyp)
        x, y, w, h = roi
        template = ref[y : y + h, x : x + w]
        refine = self.refiner_factory(ref, roi)

        def scored(source: str, start_cost: float, G0: F64, quick: bool) -> list[Candidate]:
            return [
                Candidate(source, start_cost, r, photometric_score(template, r.sampled, r.valid))
                for r in refine(cur, G0, quick=quick)
            ]

        screened = sorted((c for hyp in starts for c in scored(hyp.source, hyp.score.cost, hyp.G, True)),
                          key=lambda c: c.score.cost)
        finalists: list[Candidate] = []
        for c in screened:
            if len(finalists) == cfg.final_refined:
                break
            if all(warp_rms(c.refinement.G, f.refinement.G, roi) > cfg.distinct_px for f in finalists):
                finalists.append(c)
        candidates = [full for c in finalists for full in scored(c.source, c.start_cost, c.refinement.G, False)]
        candidates.sort(key=lambda c: c.score.cost)
        return _decide(candidates, len(raw), roi, cfg)


def _decide(candidates: list[Candidate], n_raw: int, roi: Roi, cfg: GlobalInitConfig) -> InitResult:
    """Winner, margin to the best different solution, and the LOST criteria of the module docstring."""
    if not candidates:
        return InitResult("LOST", None, 1.0, 0.0, "no hypothesis could be refined", candidates, n_raw)
    best = candidates[0]
    different = (c for c in candidates[1:] if warp_rms(c.refinement.G, best.refinement.G, roi) > cfg.distinct_px)
    rival = next(different, None)
    margin = (rival.score.cost if rival else 1.0) - best.score.cost
    cost = best.score.cost
    if cost > cfg.max_cost:
        reason = f"best robust cost {cost:.3f} above the quality threshold {cfg.max_cost}"
    elif best.score.visible < cfg.min_visible:
        reason = f"only {best.score.visible:.0%} of the ROI visible (need {cfg.min_visible:.0%})"
    elif margin < cfg.min_margin:
        reason = f"ambiguous: margin {margin:.3f} to a different solution below {cfg.min_margin}"
    else:
        return InitResult("OK", best.refinement.G, cost, margin, "ok", candidates, n_raw)
    return InitResult("LOST", None, cost, margin, reason, candidates, n_raw)


def reacquire(
    initializer: GlobalInitializer,
    reference: F32,
    roi: Roi,
    current: F32,
    tracking_G: F64 | None = None,
    contradiction_px: float = 5.0,
) -> tuple[InitResult, bool]:
    """Global initialisation for a tracker (first frame after a reference, or after LOST). Returns the result and
    whether it strongly contradicts the tracker's own estimate `tracking_G` (both OK and their warps farther than
    `contradiction_px` RMS over the ROI)."""
    result = initializer.initialize(reference, roi, current)
    contradicts = (
        tracking_G is not None and result.G is not None and warp_rms(result.G, tracking_G, roi) > contradiction_px
    )
    return result, contradicts


def register_global(
    reference: F32, current: F32, roi: Roi, config: GlobalInitConfig | None = None
) -> InitResult:
    """Entry point for `ddvs register --init global`: one global initialisation with the planar engine."""
    return GlobalInitializer(config).initialize(reference, roi, current)
