"""Stateful general tracker: eq. (2) `p ∝ G p* + ρ*(p*) e` through a video stream, ρ* kept in the reference frame.

- First frame (or after LOST): `G` from the re-acquisition (`reacquisition.Reacquisition`: the global initialiser
  on this tracker's engine; when it is off, the last good `G`, identity at first); when no ρ* is known yet it is
  estimated on that frame (several epipole starts, `general.GeneralRegistration.estimate`), else `e` restarts from
  0 with ρ* kept.
- Every other frame: `G`, `e`, `S`, `β` warm-started from the last good frame, ρ* held fixed (13 unknowns with one
  gain), so ρ* cannot drift when the camera stops translating (`e → 0`). Like the planar `Tracker`, the frame is
  solved on the finest `tracking_levels` pyramid levels first, from the constant-velocity prediction when
  `config.base.predict_motion` is set and the last two frames converged: the last inter-frame motion
  `M = G_{k−1} G_{k−2}⁻¹` (current-image pixels) applied once more, `(G, e) = (M G_{k−1}, M e_{k−1})` (eq. (2):
  `P_k = M P_{k−1}`); when that fails, again from the last good estimate over the whole pyramid, under the capped
  robust scale (unlike the planar `Tracker`'s retry, so a jump of a few pixels within one frame is not recovered
  within the frame but re-acquired after `lost_after` frames). These warm-started frames converge at
  `config.base.tracking_step_tolerance_px`, and both attempts give up early on a hopeless frame (as the planar
  `Tracker`: the stream refines its estimate again on every frame, and the frame that discovers a loss costs about
  twice `tracking_give_up_iterations`, not `max_iterations` at every level of both attempts).
  The information on ρ* (given `e`) of each converged frame is added to `rho_information`; it grows only while
  the camera translates.
- Integrity (`registration.integrity`, as the planar `Tracker`): the robust scale of the warm-started frames is
  capped at a multiple of the last good frames' and a converged fit whose own scale or whose corners jumped
  implausibly counts as not converged.
- A frame that does not converge leaves the state unchanged and is reported (`converged = False`, reason, flags);
  `lost_after` consecutive failures declare LOST (flag `lost`), and the next frame re-acquires `G` and `e` globally.
`track` never raises and never returns non-finite numbers.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.registration.general import GeneralRegistration
from ddvs_service.registration.general_basis import ParallaxBasis
from ddvs_service.registration.general_config import FLAG_DIVERGED, FLAG_LOST, GeneralConfig
from ddvs_service.registration.general_result import GeneralResult
from ddvs_service.registration.global_init import GlobalInitConfig
from ddvs_service.registration.images import checked_grey
from ddvs_service.registration.integrity import Integrity
from ddvs_service.registration.reacquisition import Reacquisition
from ddvs_service.registration.reference import Roi

F64 = NDArray[np.float64]


class GeneralTracker:
    """Track the ROI of the engine's reference (same face as the planar `Tracker`). `acquire`: how the first frame
    and a frame after LOST are started (the global initialiser with its default settings, on this engine, when
    None). `rho` optionally gives known ρ* coefficients (`ParallaxBasis` of `config.rho_degree`), e.g. from an
    earlier session."""

    def __init__(
        self,
        engine: GeneralRegistration,
        acquire: Reacquisition | None = None,
        rho: ArrayLike | None = None,
    ) -> None:
        self._problem = engine
        self._acquire = acquire or Reacquisition(engine.planar, engine, GlobalInitConfig())
        n = self._problem.basis.size
        self._rho: F64 | None = None if rho is None else np.asarray(rho, dtype=np.float64).reshape(n).copy()
        self._information = np.zeros((n, n))
        self._G: F64 | None = None  # None: (re)acquire globally on the next frame
        self._last_G = np.eye(3)  # the last good estimate, kept through LOST
        self._G_before: F64 | None = None  # the good estimate before `_G` (None: no velocity known)
        self._e = np.zeros(3)
        self._gains = np.ones(self._problem.grid)
        self._beta = 0.0
        self._scale: float | None = None
        self._failures = 0
        self._integrity = Integrity(engine.roi)

    @classmethod
    def prepare(
        cls,
        reference: ArrayLike,
        roi: Roi | None = None,
        config: GeneralConfig = GeneralConfig(),  # noqa: B008 - frozen, immutable default
        mask: ArrayLike | None = None,
        rho: ArrayLike | None = None,
    ) -> GeneralTracker:
        """A tracker on its own engine (`GeneralRegistration.prepare`), re-acquiring with the default settings."""
        return cls(GeneralRegistration.prepare(reference, roi=roi, mask=mask, config=config), rho=rho)

    @property
    def basis(self) -> ParallaxBasis:
        """The parallax basis of ρ*."""
        return self._problem.basis

    @property
    def rho_coeffs(self) -> F64 | None:
        """ρ* coefficients (None until estimated)."""
        return None if self._rho is None else self._rho.copy()

    @property
    def rho_information(self) -> F64:
        """Accumulated information on the ρ* coefficients (given `e`)."""
        return self._information.copy()

    @property
    def lost(self) -> bool:
        """True when the next frame will be re-acquired globally."""
        return self._G is None

    def lose(self) -> None:
        """Re-acquire `G` and `e` globally on the next frame (ρ* is kept): the caller found the last fit wrong."""
        self._G = self._G_before = None
        self._failures = 0

    def track(self, current: ArrayLike) -> GeneralResult:
        """Register `current` (module docstring); on failure keep the state and report why."""
        try:
            result = self._track(checked_grey(current, "current"))
        except Exception as exc:  # the tracker's contract: report, never raise
            return self._failure(f"error: {type(exc).__name__}: {exc}", [FLAG_DIVERGED])
        finite = all(np.all(np.isfinite(x)) for x in (result.G, result.e, result.rho_coeffs, result.S, [result.beta]))
        if not finite:
            return self._count_failure(self._failure(f"non-finite estimate ({result.reason})", [FLAG_DIVERGED]))
        if not result.converged:
            return self._count_failure(result)
        self._G_before = self._G
        self._last_G = result.G
        self._G, self._e, self._gains, self._beta = result.G, result.e, result.S, result.beta
        self._integrity.accept(result.scale, result.inlier_ratio)
        self._scale = max(result.scale, self._integrity.config.min_anchor) if np.isfinite(result.scale) else None
        self._information = self._information + result.rho_information
        result.rho_information = self._information.copy()
        self._failures = 0
        return result

    def _track(self, current: NDArray[np.float32]) -> GeneralResult:
        problem = self._problem
        if self._G is None:
            acquisition = self._acquire(current)
            G0 = self._last_G if acquisition.status == "OFF" else acquisition.G
            if G0 is None:
                return self._failure("LOST: the global initialiser found no confident estimate", [FLAG_LOST])
            if self._rho is None:
                result = problem.estimate(current, G0)
                if result.converged:
                    self._rho = result.rho_coeffs.copy()
                return result
            return problem.track(current, G0, np.zeros(3), self._rho)
        assert self._rho is not None
        G0, e0 = self._prediction()
        photometric = (self._gains, self._beta, self._scale)
        base = problem.config.base
        tolerance = base.tracking_step_tolerance_px
        cap = self._integrity.scale_cap
        result = problem.track(current, G0, e0, self._rho, *photometric, first_level=base.tracking_levels - 1,
                               tolerance_px=tolerance, scale_cap=cap, give_up=True)
        if not result.converged and (G0 is not self._G or len(result.iterations) < len(problem.levels)):
            # under the last frames' capped σ (re-estimated, as the planar retry's, a hard combination's retries
            # under an occluder gave up at the coarsest level: LOST frames on the saddle)
            result = problem.track(current, self._G, self._e, self._rho, *photometric, tolerance_px=tolerance,
                                   scale_cap=cap, give_up=True)
        implausible = self._integrity.judge(G0, result.G, result.scale) if result.converged else ""
        if implausible:
            result.converged, result.reason = False, implausible
        return result

    def _prediction(self) -> tuple[F64, F64]:
        """Start `(G, e)` of the next frame: the last estimate, or its constant-velocity extrapolation (module
        docstring)."""
        assert self._G is not None
        if self._G_before is None or not self._problem.config.base.predict_motion:
            return self._G, self._e
        M = self._G @ np.linalg.inv(self._G_before)
        G, e = M @ self._G, M @ self._e
        if not (np.all(np.isfinite(G)) and np.all(np.isfinite(e)) and np.linalg.det(G) > 0.0):
            return self._G, self._e
        return G, e

    def _count_failure(self, result: GeneralResult) -> GeneralResult:
        self._G_before = None
        self._failures += 1
        if self._failures >= self._problem.config.lost_after and self._G is not None:
            self._G = None
            result.flags.append(FLAG_LOST)
            result.reason += f"; LOST after {self._failures} failed frames: re-acquiring on the next frame"
        return result

    def _failure(self, reason: str, flags: list[str]) -> GeneralResult:
        """The last good state, reported as not converged."""
        n = self._problem.basis.size
        return GeneralResult(
            G=np.eye(3) if self._G is None else self._G.copy(), e=self._e.copy(),
            rho_coeffs=np.zeros(n) if self._rho is None else self._rho.copy(), basis=self._problem.basis,
            S=self._gains.copy(), beta=self._beta, rho_information=self._information.copy(), converged=False,
            reason=reason, flags=list(flags),
        )
