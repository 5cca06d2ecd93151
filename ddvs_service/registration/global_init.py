"""Global initialisation and re-acquisition from large displacements.

`GlobalInitializer.initialize(reference, roi, current)`, stage by stage (1. log-polar peaks and the feature
hypothesis; 2. the uniform rotation/scale grid, searched only when stage 1 gave no clear winner; 3. foreshortened
variants of the best screened warps — an oblique view compresses the ROI along one direction, which no similarity
start reproduces — searched only when stages 1–2 ended LOST, and its winner held to the stricter `tilt_max_cost`):
1. hypotheses: direct Fourier–Mellin search on a coarse pyramid level (`global_fourier_mellin.py`: any in-plane
   rotation, scale 0.6–1.6, ROI anywhere with part of it outside the image), plus, when `config.feature_source` is
   'orb' or 'sift', one RANSAC homography from features (`global_features.py`); ranked by the robust photometric
   cost (`global_cost.py`) at that level;
2. the `max_screened` (`max_screened_later` after stage 1) best distinct new hypotheses are screened by a planar
   refinement at the search level only (`global_screen.py`, all of them at once),
   and the `final_refined` best distinct screened ones (winner and runner-up) are refined at full resolution by a
   `Refiner` – the planar direct engine (eqs. (4)–(5) with ρ* ≡ 0) by default, started one level above the search
   level. A refiner returns one or several refinements per start (hook for the general model of eq. (2) started
   from several epipole directions) and the current image sampled at its own warp, so any model is scored the same.
   Only the best screened one gets the full budget; the others are *rivals*, refined on a smaller budget
   (`PlanarRefiner`: `rival_iterations` per level) that suffices to tell whether they reach a good solution (a
   wrong match otherwise wanders for the engine's whole budget), and a rival that comes out best is refined again
   with the full budget;
3. the refinements are ranked by their robust cost over the visible pixels (those keeping `min_visible` of the ROI
   in view first); `margin` = visible cost of the best *good* different solution (warp farther than `distinct_px`
   RMS over the ROI, visible cost ≤ `max_cost`) minus the winner's (1 − the winner's when there is none);
4. status "LOST" when the winner's visible cost at the search level exceeds `max_cost`, its visible ROI fraction is
   below `min_visible`, or the margin is below `min_margin` — never a confident wrong estimate;
5. a planar winner LOST only for its cost, with a search-level visible cost up to `general_max_cost`, or only for
   its margin, is refined by the general model of eq. (2) (`GeneralRefiner`): on a curved target a correct planar
   fit keeps the parallax as residual (0.3–0.35 on the saddle seen 38° obliquely), which the general model removes
   (0.15–0.17 there), and planar fits of the curved patch a few pixels apart score alike (an ambiguity eq. (2)
   resolves), while it does not converge from a wrong match. When it converges, the decision of 3–4 is taken again
   with the general refinement in the winner's place, its quality being its own visible cost at full resolution; an
   OK result's `G` is then the planar part `G` of eq. (2);
6. an OK winner is LOST after all when a different refined solution kept in view fits the best-matching
   `trimmed_kept` share of the ROI better (`global_cost.trimmed_score`) by more than `trimmed_tolerance`: a foreign
   object over part of the ROI inflates every solution's cost alike and can let a warp that pushes the ROI off it
   rank first (measured: OK 14 px from the truth under a 35 % occluder, while the right solution fitted the rest of
   the ROI better).

`G` maps reference pixels to current pixels (full-image 0-based pixel centres), det 1.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any, Literal, Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray

from ddvs_service.registration.config import RegistrationConfig
from ddvs_service.registration.general import GeneralRegistration
from ddvs_service.registration.general_config import GeneralConfig
from ddvs_service.registration.global_cost import (
    PhotometricScore,
    photometric_score,
    sample_at,
    sample_through,
    trimmed_score,
)
from ddvs_service.registration.global_features import feature_homography
from ddvs_service.registration.global_fourier_mellin import (
    FourierMellinConfig,
    Hypothesis,
    SearchPair,
    SearchReference,
    TranslationSearch,
    fourier_mellin_hypotheses,
    rotation_scale_stages,
    translation_hypotheses,
)
from ddvs_service.registration.global_screen import BatchScreen
from ddvs_service.registration.planar import PlanarRegistration
from ddvs_service.registration.warp_distance import rms_distance, roi_grid, roi_samples, warp_rms
from kernels import backend
from kernels.exclusive import GATE

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
Roi = tuple[int, int, int, int]
T = TypeVar("T")
FORESHORTENED = "foreshortened"  # source of the stage-3 starts


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
    """Refines a starting warp `G0` (full-resolution pixels) of a fixed reference ROI in `current`; may return several
    refinements (e.g. the general model started from several epipole directions). `first_level`: the coarsest
    pyramid level worth solving (the start is already within about a pixel there). `rival`: the start is refined only
    to be compared with a better-ranked one, so a smaller budget may be spent on it."""

    def __call__(self, current: F32, G0: F64, first_level: int, rival: bool = False) -> list[Refinement]: ...


RefinerFactory = Callable[[PlanarRegistration], Refiner]


class PlanarRefiner:
    """The planar direct engine (`registration.planar.PlanarRegistration`, coarse to fine) as a `Refiner`; a rival
    gets at most `rival_iterations` Gauss-Newton iterations per level (a correct start from the screening converges
    in about 5), on the same prepared reference and workspace."""

    def __init__(self, engine: PlanarRegistration, rival_iterations: int = 10) -> None:
        self.roi = engine.roi
        config = engine.config
        self.problem = engine
        self.rival_problem = PlanarRegistration(
            engine.prepared, config.replaced(max_iterations=min(rival_iterations, config.max_iterations)),
            engine.current)

    def __call__(self, current: F32, G0: F64, first_level: int, rival: bool = False) -> list[Refinement]:
        problem = self.rival_problem if rival else self.problem
        result = problem.run(current, G0=G0, first_level=first_level)
        if not np.all(np.isfinite(result.G)):
            return []
        x, y, w, h = self.roi
        sampled, valid = sample_through(current, result.G, (h, w), (x, y))
        return [Refinement(G=result.G, sampled=sampled, valid=valid, model="planar", detail=result)]


class GeneralRefiner:
    """The general model of eq. (2) (`registration.general.GeneralRegistration.estimate`: planar refinement from
    `G0`, then ρ* and e from several epipole directions) as a `Refiner`: `engine`, or one built on first use on the
    planar engine's prepared reference and workspace (`GeneralConfig` with the planar engine's settings). It solves
    its own `estimate_levels` (`first_level` and `rival` are not used) and returns nothing unless it converged."""

    def __init__(self, planar: PlanarRegistration, engine: GeneralRegistration | None = None) -> None:
        self.planar, self.roi = planar, planar.roi
        self._problem = engine

    def __call__(self, current: F32, G0: F64, first_level: int, rival: bool = False) -> list[Refinement]:
        if self._problem is None:
            self._problem = GeneralRegistration(self.planar.prepared, GeneralConfig(base=self.planar.config),
                                                self.planar.current)
        result = self._problem.estimate(current, G0)
        if not result.converged or not np.all(np.isfinite(result.G)):
            return []
        sampled, valid = sample_at(current, result.warp(roi_grid(self.roi)), (self.roi[3], self.roi[2]))
        return [Refinement(G=result.G, sampled=sampled, valid=valid, model="general", detail=result)]


@dataclass(frozen=True)
class GlobalInitConfig:
    """Hypothesis sources, refinement budget and the LOST criteria (costs are `global_cost` units in [0, 1])."""

    fourier_mellin: FourierMellinConfig = field(default_factory=FourierMellinConfig)
    feature_source: Literal["none", "orb", "sift"] = "none"
    max_screened: int = 6  # distinct new hypotheses of stage 1 screened by a planar refinement at the search level
    max_screened_later: int = 8  # the same for stages 2 and 3 (searched only when stage 1 has no clear winner)
    screen_iterations: int = 8  # Gauss-Newton iterations per level of a screening
    final_refined: int = 2  # distinct screened candidates refined fully (winner and runner-up)
    distinct_px: float = 3.0  # two warps closer than this (RMS over the ROI) are the same solution
    max_cost: float = 0.25  # winner's robust cost over its visible pixels at the search level above this → LOST
    min_margin: float = 0.1  # a good different solution's cost minus the winner's below this → LOST
    min_visible: float = 0.5  # winner's visible ROI fraction below this → LOST
    early_accept_cost: float = 0.1  # an OK winner of the first stage with a visible cost below this ends the search
    tilt_seeds: int = 3  # stage 3: best distinct screened warps that seed foreshortened starts (0: no stage 3)
    tilt_factor: float = 0.75  # stage 3: compression (≈ cos 41°) of the ROI along 0°, 45°, 90°, 135° about its centre
    tilt_max_cost: float = 0.15  # max_cost for a winner started from stage 3 (more freedom, more chance fits)
    general_max_cost: float = 0.4  # step 5: a planar winner LOST for a cost up to this is tried with eq. (2)
    trimmed_kept: float = 0.6  # step 6: the share of the ROI a partial-occlusion check scores (`trimmed_score`)
    trimmed_tolerance: float = 0.005  # step 6: a different solution this much better on that share → LOST


@dataclass(frozen=True)
class Candidate:
    """A refined hypothesis: where it started, what it became, its score, and whether it was refined as a `rival`
    (on the smaller budget)."""

    source: str
    start_cost: float
    refinement: Refinement
    score: PhotometricScore
    rival: bool = False


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
    if ref.ndim != 2 or cur.ndim != 2 or ref.shape != cur.shape:
        raise ValueError(f"expected 2-D grey images of the same size, got reference {ref.shape} and current "
                         f"{cur.shape}")
    x, y, w, h = roi
    if w < 16 or h < 16 or x < 0 or y < 0 or x + w > ref.shape[1] or y + h > ref.shape[0]:
        raise ValueError(
            f"roi {roi} must be at least 16×16 and inside the reference image {ref.shape[1]}×{ref.shape[0]}"
        )
    if not (np.isfinite(ref).all() and np.isfinite(cur).all()):
        raise ValueError("images contain NaN or Inf; expected finite grey levels")
    return ref, cur


@dataclass(frozen=True)
class ReferenceSide:
    """Everything an initialisation derives from the reference image and the ROI alone, kept across calls with the
    same reference (a tracker re-initialises against it after LOST): the search level's reference pyramid, template
    and log-polar spectrum (`search`), the screening's geometry (`screen`), the full-resolution `refine`r and
    `template`, and the points over which warp distances are measured (`points`, `warp_distance.roi_samples`)."""

    reference: F32  # a private copy: a later call is served from this side only if its reference is equal
    roi: Roi
    search: SearchReference
    screen: BatchScreen
    refine: Refiner
    template: F32
    points: F64
    general: Refiner

    def serves(self, reference: F32, roi: Roi) -> bool:
        return tuple(roi) == self.roi and np.array_equal(reference, self.reference)


class GlobalInitializer:
    """Direct global initialiser; `refiner_factory(engine)` builds the refiner on a planar engine (`PlanarRefiner`
    by default). The reference side of the last reference and ROI (`ReferenceSide`) is kept for the next call.
    `engine` (and `general`): a tracker's engines, whose prepared reference serves the initialisations against its
    reference and ROI; any other reference gets an engine of its own with the default `RegistrationConfig`."""

    def __init__(
        self,
        config: GlobalInitConfig | None = None,
        refiner_factory: RefinerFactory | None = None,
        engine: PlanarRegistration | None = None,
        general: GeneralRegistration | None = None,
    ) -> None:
        backend.init()
        self.config = config or GlobalInitConfig()
        self.refiner_factory: RefinerFactory = refiner_factory or PlanarRefiner
        self._engine, self._general = engine, general
        self._side: ReferenceSide | None = None

    def reference_side(self, ref: F32, roi: Roi) -> ReferenceSide:
        """The prepared reference side for this reference and ROI (the kept one when they are the same)."""
        if self._side is None or not self._side.serves(ref, roi):
            x, y, w, h = roi
            engine, general = self._engine, self._general
            if engine is None or tuple(roi) != engine.roi or not np.array_equal(ref, engine.prepared.image):
                engine, general = PlanarRegistration.prepare(ref, roi, config=RegistrationConfig()), None
            search = SearchReference.build(ref, roi, self.config.fourier_mellin)
            self._side = ReferenceSide(
                reference=ref.copy(), roi=(x, y, w, h), search=search,
                screen=BatchScreen(search, roi, self.config.screen_iterations), refine=self.refiner_factory(engine),
                template=ref[y : y + h, x : x + w].copy(), points=roi_samples(roi),
                general=GeneralRefiner(engine, general))
        return self._side

    def hypotheses(self, reference: F32, roi: Roi, current: F32) -> list[Hypothesis]:
        """Raw hypotheses of every stage, lowest photometric cost first (direct ones, plus the feature one if
        configured)."""
        ref, cur = _check_inputs(reference, roi, current)
        search = SearchPair.build(self.reference_side(ref, roi).search, cur)
        found = fourier_mellin_hypotheses(search, self.config.fourier_mellin) + self._features(search, ref, roi, cur)
        return sorted(found, key=lambda hyp: hyp.score.cost)

    def _features(self, search: SearchPair, ref: F32, roi: Roi, cur: F32) -> list[Hypothesis]:
        if self.config.feature_source == "none":
            return []
        G = feature_homography(ref, roi, cur, self.config.feature_source)
        return [] if G is None else [Hypothesis(G=G, source=self.config.feature_source, score=search.scores([G])[0])]

    def initialize(self, reference: F32, roi: Roi, current: F32) -> InitResult:
        """Stage by stage (log-polar peaks and features, then the rotation/scale grid): hypotheses → screening of the
        best distinct new ones at the search level → full refinement of the best distinct screened ones → winner by
        robust cost, margin, LOST decision. Stops after the first stage when its winner is OK with a visible cost
        below `early_accept_cost`."""
        cfg, fm = self.config, self.config.fourier_mellin
        ref, cur = _check_inputs(reference, roi, current)
        side = self.reference_side(ref, roi)
        search = SearchPair.build(side.search, cur)
        translation = TranslationSearch(search.current, search.template, fm.max_scale)
        GATE.checkpoint()  # between steps too, a frame waiting for Taichi goes first (`kernels.exclusive`)
        first_level = max(0, side.search.level - 1)
        extra = self._features(search, ref, roi, cur)
        screened: list[tuple[float, F64, Hypothesis]] = []  # (screened cost, screened G, start)
        refined: dict[int, list[Candidate]] = {}  # by position in `screened`
        n_raw = 0
        stages: list[Callable[[], list[Hypothesis]]] = [
            partial(translation_hypotheses, search, translation, stage, fm)
            for stage in rotation_scale_stages(search, fm)
        ]
        stages.append(lambda: foreshortened(search, side, [(c, G) for c, G, _ in screened], cfg))
        result = InitResult("LOST", None, 1.0, 0.0, "no stage ran", [], 0)
        for index, stage_hypotheses in enumerate(stages):
            if index == len(stages) - 1 and (result.status == "OK" or cfg.tilt_seeds == 0):
                break  # stage 3 only rescues a search that stages 1–2 lost
            GATE.checkpoint()  # between stages, a frame waiting for Taichi goes first (`kernels.exclusive`)
            raw = sorted(stage_hypotheses() + extra, key=lambda h: h.score.cost)
            extra, n_raw = [], n_raw + len(raw)
            GATE.checkpoint()
            seen = [G for _, G, _ in screened]
            fresh = [hyp for hyp in raw if all(rms_distance(hyp.G, G, side.points) > cfg.distinct_px for G in seen)]
            limit = cfg.max_screened if index == 0 else cfg.max_screened_later
            starts = _distinct([(hyp.G, hyp) for hyp in fresh], limit, side.points, cfg.distinct_px)
            Gs = side.screen.run(search, [hyp.G for hyp in starts])
            screened += [(_rank(score, cfg), G, hyp) for score, G, hyp in zip(search.scores(Gs), Gs, starts,
                                                                              strict=True)]
            order = sorted(range(len(screened)), key=lambda i: screened[i][0])
            best = _distinct([(screened[i][1], i) for i in order], cfg.final_refined, side.points, cfg.distinct_px)
            for rank, i in enumerate(best):
                GATE.checkpoint()
                if i not in refined:
                    _, G, hyp = screened[i]
                    refined[i] = _refine(side, cur, G, hyp, first_level, rival=rank > 0)
            candidates = _ranked(refined, cfg)
            if candidates and candidates[0].rival:  # a rival came out best: give it the full budget
                i = next(i for i, cs in refined.items() if any(c is candidates[0] for c in cs))
                refined[i] = _refine(side, cur, candidates[0].refinement.G, screened[i][2], first_level, rival=False)
                candidates = _ranked(refined, cfg)
            quality = search.scores([candidates[0].refinement.G])[0].cost_visible if candidates else 1.0
            result = _decide(candidates, quality, n_raw, side.points, cfg)
            if result.status == "OK" and result.cost <= cfg.early_accept_cost:
                break
        return _occlusion_check(_general_check(result, side, cur, cfg), side, cfg)


def _refine(side: ReferenceSide, cur: F32, G: F64, start: Hypothesis, first_level: int, rival: bool
            ) -> list[Candidate]:
    """The refinements of the screened warp `G` of hypothesis `start`, scored over the full-resolution template."""
    return [Candidate(start.source, start.score.cost, r, photometric_score(side.template, r.sampled, r.valid), rival)
            for r in side.refine(cur, G, first_level, rival)]


def _ranked(refined: dict[int, list[Candidate]], cfg: GlobalInitConfig) -> list[Candidate]:
    """Every refined candidate, best first (`_rank`)."""
    return sorted((c for cs in refined.values() for c in cs), key=lambda c: _rank(c.score, cfg))


def _general_check(result: InitResult, side: ReferenceSide, cur: F32, cfg: GlobalInitConfig) -> InitResult:
    """Step 5 of the module docstring: a planar winner LOST only for its cost (at most `general_max_cost`) or for
    its margin is refined by the general model; if that converges, the decision is taken again with it as the
    winner."""
    best = result.winner
    if (result.status == "OK" or best is None or best.refinement.model != "planar"
            or best.score.visible < cfg.min_visible):
        return result
    costly = _max_cost(best, cfg) < result.cost <= cfg.general_max_cost
    ambiguous = result.cost <= _max_cost(best, cfg) and result.margin < cfg.min_margin
    if not (costly or ambiguous):
        return result
    general = [Candidate(best.source, best.start_cost, r, photometric_score(side.template, r.sampled, r.valid))
               for r in side.general(cur, best.refinement.G, 0)]
    if not general:
        return result
    decided = _decide([*general, *result.candidates], general[0].score.cost_visible, result.hypotheses,
                      side.points, cfg)
    return decided if decided.status == "OK" else result


def _occlusion_check(result: InitResult, side: ReferenceSide, cfg: GlobalInitConfig) -> InitResult:
    """Step 6 of the module docstring: an OK winner must also fit the best-matching `trimmed_kept` share of the ROI
    at least as well as every different solution kept in view (`trimmed_score`); otherwise LOST."""
    best = result.winner
    if result.status != "OK" or best is None:
        return result
    def trimmed(candidate: Candidate) -> float:
        r = candidate.refinement
        return trimmed_score(side.template, r.sampled, r.valid, cfg.trimmed_kept).cost

    own = trimmed(best)
    for other in result.candidates[1:]:
        GATE.checkpoint()  # a frame waiting for Taichi goes first (`kernels.exclusive`)
        if (other.score.visible >= cfg.min_visible
                and rms_distance(other.refinement.G, best.refinement.G, side.points) > cfg.distinct_px):
            cost = trimmed(other)
            if cost < own - cfg.trimmed_tolerance:
                return replace(result, status="LOST", G=None, reason=(
                    f"ambiguous under partial occlusion: a different solution fits the best-matching "
                    f"{cfg.trimmed_kept:.0%} of the ROI better ({cost:.3f} < {own:.3f})"))
    return result


def _max_cost(best: Candidate, cfg: GlobalInitConfig) -> float:
    """The quality threshold of a winner: `tilt_max_cost` for a planar refinement of a stage-3 start, `max_cost`
    otherwise (a general-model winner, already held to converging, is judged on its full-resolution cost)."""
    return cfg.tilt_max_cost if best.source == FORESHORTENED and best.refinement.model == "planar" else cfg.max_cost


def foreshortened(search: SearchPair, side: ReferenceSide, screened: list[tuple[float, F64]],
                  cfg: GlobalInitConfig) -> list[Hypothesis]:
    """Stage 3 starts: each of the `cfg.tilt_seeds` best distinct `screened` warps (ranking key, full-resolution G)
    composed with a compression by `cfg.tilt_factor` of the reference ROI along 0°, 45°, 90° and 135° about its
    centre (`G · C A C⁻¹`; a stretch is a compression across plus a scale, which the refinement absorbs)."""
    x, y, w, h = side.roi
    C = np.array([[1.0, 0.0, x + (w - 1) / 2], [0.0, 1.0, y + (h - 1) / 2], [0.0, 0.0, 1.0]])
    order = sorted(screened, key=lambda item: item[0])
    seeds = _distinct([(G, G) for _, G in order], cfg.tilt_seeds, side.points, cfg.distinct_px)
    starts = []
    for G in seeds:
        for phi in np.radians([0.0, 45.0, 90.0, 135.0]):
            d = np.array([np.cos(phi), np.sin(phi)])
            A = np.eye(3)
            A[:2, :2] -= (1.0 - cfg.tilt_factor) * np.outer(d, d)
            start = G @ C @ A @ np.linalg.inv(C)
            starts.append(start / np.cbrt(np.linalg.det(start)))
    return [Hypothesis(G=G, source=FORESHORTENED, score=score) for G, score in zip(starts, search.scores(starts),
                                                                                     strict=True)]


def _rank(score: PhotometricScore, cfg: GlobalInitConfig) -> float:
    """Ranking key of a refined solution: its visible cost, after every solution that keeps `min_visible` of the ROI
    in view (the total cost, which charges 1 per pixel out of view, would prefer a wrong match inside the image to
    the right one partly outside)."""
    return score.cost_visible + (1.0 if score.visible < cfg.min_visible else 0.0)


def _distinct(items: list[tuple[F64, T]], limit: int, points: F64, distinct_px: float) -> list[T]:
    """The first `limit` items whose warps are pairwise farther apart than `distinct_px` RMS over the ROI
    (`points`: `ReferenceSide.points`)."""
    kept: list[tuple[F64, T]] = []
    for G, item in items:
        if len(kept) == limit:
            break
        if all(rms_distance(G, other, points) > distinct_px for other, _ in kept):
            kept.append((G, item))
    return [item for _, item in kept]


def _decide(candidates: list[Candidate], quality: float, n_raw: int, points: F64, cfg: GlobalInitConfig
            ) -> InitResult:
    """Winner, margin to the best *good* different solution, and the LOST criteria of the module docstring.
    `quality`: the winner's visible cost at the search level (coarse: sub-pixel model errors, e.g. the parallax a
    planar warp leaves on a curved target, and aliasing weigh less there than a wrong match); for the general-model
    winner of step 5, its own visible cost at full resolution."""
    if not candidates:
        return InitResult("LOST", None, 1.0, 0.0, "no hypothesis could be refined", candidates, n_raw)
    best = candidates[0]
    rival = next((c for c in candidates[1:] if c.score.cost_visible <= cfg.max_cost
                  and rms_distance(c.refinement.G, best.refinement.G, points) > cfg.distinct_px), None)
    margin = (rival.score.cost_visible if rival else 1.0) - best.score.cost_visible
    cost = quality
    max_cost = _max_cost(best, cfg)
    if cost > max_cost:
        reason = f"best robust cost {cost:.3f} (visible pixels, search level) above the threshold {max_cost}"
    elif best.score.visible < cfg.min_visible:
        reason = f"only {best.score.visible:.0%} of the ROI visible (need {cfg.min_visible:.0%})"
    elif margin < cfg.min_margin:
        reason = f"ambiguous: margin {margin:.3f} to a different good solution below {cfg.min_margin}"
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
