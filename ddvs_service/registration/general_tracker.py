"""Stateful general tracker: eq. (2) `p ∝ G p* + ρ*(p*) e` through a video stream, ρ* kept in the reference frame.

The general model's tracker as `registration.session.TrackingSession` drives it, with the same face as the planar
`Tracker` (`reset`, `track`, `G`, `photometric`, `residual`); where a frame starts after a reference or a loss (the
global initialiser, the last good estimate) is the session's decision, not this tracker's.
- The first frame after `reset(G)`: when no ρ* is known yet it is estimated on that frame from `G` (several
  epipole starts, `general.GeneralRegistration.estimate`), else `e` starts from 0 with ρ* kept, over the whole
  pyramid.
- Every other frame: `G`, `e`, `S`, `β` warm-started from the last good frame, ρ* held fixed (13 unknowns with one
  gain), so ρ* cannot drift when the camera stops translating (`e → 0`). Like the planar `Tracker`, the frame is
  solved on the finest `tracking_levels` pyramid levels first, from the constant-velocity prediction when
  `config.base.predict_motion` is set and the last two frames converged: the last inter-frame motion
  `M = G_{k−1} G_{k−2}⁻¹` (current-image pixels) applied once more, `(G, e) = (M G_{k−1}, M e_{k−1})` (eq. (2):
  `P_k = M P_{k−1}`); when that fails, again from the last good estimate over the whole pyramid, under the capped
  robust scale (unlike the planar `Tracker`'s retry, so a jump of a few pixels within one frame is not recovered
  within the frame but re-acquired by the session on the next one). These warm-started frames converge at
  `config.base.tracking_step_tolerance_px`, and both attempts give up early on a hopeless frame (as the planar
  `Tracker`: the frame that discovers a loss costs about twice `tracking_give_up_iterations`).
  The information on ρ* (given `e`) of each converged frame is added to `rho_information`; it grows only while
  the camera translates. Near the equilibrium a frame may hold `e` at 0 (`general` module docstring, held
  epipole) unless the last `EPIPOLE_EVIDENCE_FRAMES` converged frames found it significant on average.
- Integrity (`registration.integrity`, as the planar `Tracker`): the robust scale of the warm-started frames is
  capped at a multiple of the last good frames' and a converged fit whose own scale or whose corners jumped
  implausibly counts as not converged.
- A frame that does not converge leaves the state unchanged and is reported (`converged = False`, reason, flags).
`track` never raises and never returns non-finite numbers.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.lie import sl3_normalize
from ddvs_service.registration.general import EPIPOLE_EVIDENCE_FRAMES, FREE_EPIPOLE_MEAN_WALD, GeneralRegistration
from ddvs_service.registration.general_basis import ParallaxBasis
from ddvs_service.registration.general_config import FLAG_DIVERGED, GeneralConfig
from ddvs_service.registration.general_result import GeneralResult
from ddvs_service.registration.images import checked_grey
from ddvs_service.registration.integrity import Integrity
from ddvs_service.registration.reference import Roi
from ddvs_service.registration.residual import residual_image

F64 = NDArray[np.float64]


class GeneralTracker:
    """Track the ROI of the engine's reference (module docstring). `rho` optionally gives known ρ* coefficients
    (`ParallaxBasis` of `config.rho_degree`), e.g. from an earlier session; `G`: where the first frame starts."""

    def __init__(self, engine: GeneralRegistration, rho: ArrayLike | None = None, G: ArrayLike | None = None) -> None:
        self._problem = engine
        n = self._problem.basis.size
        self._rho: F64 | None = None if rho is None else np.asarray(rho, dtype=np.float64).reshape(n).copy()
        self._information = np.zeros((n, n))
        self._integrity = Integrity(engine.roi)  # kept through resets: the reference does not change
        self.reset(G)

    @classmethod
    def prepare(
        cls,
        reference: ArrayLike,
        roi: Roi | None = None,
        config: GeneralConfig = GeneralConfig(),  # noqa: B008 - frozen, immutable default
        mask: ArrayLike | None = None,
        rho: ArrayLike | None = None,
    ) -> GeneralTracker:
        """A tracker on its own engine (`GeneralRegistration.prepare`)."""
        return cls(GeneralRegistration.prepare(reference, roi=roi, mask=mask, config=config), rho=rho)

    @property
    def basis(self) -> ParallaxBasis:
        """The parallax basis of ρ*."""
        return self._problem.basis

    @property
    def G(self) -> F64:
        """Current estimate (3×3, det 1), reference → current pixels."""
        return self._G.copy()

    @property
    def photometric(self) -> tuple[F64, float]:
        """The gains `S` (node values, shape `gain_grid`) and bias `β` of the current state (eq. (4))."""
        return self._gains.copy(), self._beta

    @property
    def rho_coeffs(self) -> F64 | None:
        """ρ* coefficients (None until estimated)."""
        return None if self._rho is None else self._rho.copy()

    @property
    def rho_information(self) -> F64:
        """Accumulated information on the ρ* coefficients (given `e`)."""
        return self._information.copy()

    def adopt_rho(self, rho: ArrayLike) -> None:
        """Hold ρ* at the coefficients `rho` (another tracker's of the same reference and basis) from now on."""
        self._rho = np.asarray(rho, dtype=np.float64).reshape(self._problem.basis.size).copy()

    def reset(self, G: ArrayLike | None = None) -> None:
        """Restart from `G` (identity when None) with `e = 0`, unit gains and zero bias, ρ* kept: the next frame is
        solved over the whole pyramid, and estimates ρ* when none is known (module docstring)."""
        self._G = np.eye(3) if G is None else sl3_normalize(np.asarray(G, dtype=np.float64).reshape(3, 3))
        self._G_before: F64 | None = None  # the good estimate before `_G` (None: no velocity known)
        self._e = np.zeros(3)
        self._gains = np.ones(self._problem.grid)
        self._beta = 0.0
        self._scale: float | None = None
        self._fresh = True  # the next frame starts from `reset`'s `G`
        self._epipole_wald: deque[float] = deque(maxlen=EPIPOLE_EVIDENCE_FRAMES)  # of the last converged frames

    def track(self, current: ArrayLike) -> GeneralResult:
        """Register `current` (module docstring); on failure keep the state and report why."""
        try:
            result = self._track(checked_grey(current, "current"))
        except Exception as exc:  # the tracker's contract: report, never raise
            return self._failure(f"error: {type(exc).__name__}: {exc}", [FLAG_DIVERGED])
        finite = all(np.all(np.isfinite(x)) for x in (result.G, result.e, result.rho_coeffs, result.S, [result.beta]))
        if not finite:
            return self._failure(f"non-finite estimate ({result.reason})", [FLAG_DIVERGED])
        if not result.converged:
            self._G_before = None
            return result
        if self._rho is None:
            self._rho = result.rho_coeffs.copy()
        self._G_before = None if self._fresh else self._G
        self._G, self._e, self._gains, self._beta = result.G, result.e, result.S, result.beta
        self._fresh = False
        self._integrity.accept(result.scale, result.inlier_ratio)
        self._scale = max(result.scale, self._integrity.config.min_anchor) if np.isfinite(result.scale) else None
        self._information = self._information + result.rho_information
        result.rho_information = self._information.copy()
        if np.isfinite(result.epipole_wald):
            self._epipole_wald.append(result.epipole_wald)
        return result

    def residual(self, current: ArrayLike) -> NDArray[np.float32]:
        """The residual image of `current` over the ROI under the current state, parallax included
        (`registration.residual`); ρ* = 0 until estimated."""
        prepared, config = self._problem.prepared, self._problem.config.base
        x, y, w, h = prepared.roi
        v, u = np.mgrid[y:y + h, x:x + w].astype(np.float64)
        coeffs = np.zeros(self.basis.size) if self._rho is None else self._rho
        rho = self.basis.rho(coeffs, np.c_[u.ravel(), v.ravel()]).reshape(h, w)
        return residual_image(prepared.image, np.asarray(current), prepared.roi, self._G, self._gains, self._beta,
                              config.gamma, config.defocus_px, parallax=(rho, self._e))

    def _track(self, current: NDArray[np.float32]) -> GeneralResult:
        problem = self._problem
        if self._fresh:
            if self._rho is None:
                return problem.estimate(current, self._G)
            return problem.track(current, self._G, np.zeros(3), self._rho)
        assert self._rho is not None
        G0, e0 = self._prediction()
        photometric = (self._gains, self._beta, self._scale)
        base = problem.config.base
        tolerance = base.tracking_step_tolerance_px
        cap = self._integrity.scale_cap
        evidence = self._epipole_wald
        may_hold = len(evidence) < EPIPOLE_EVIDENCE_FRAMES or float(np.mean(evidence)) < FREE_EPIPOLE_MEAN_WALD
        result = problem.track(current, G0, e0, self._rho, *photometric, first_level=base.tracking_levels - 1,
                               tolerance_px=tolerance, scale_cap=cap, give_up=True, may_hold_epipole=may_hold)
        if not result.converged and (G0 is not self._G or len(result.iterations) < len(problem.levels)):
            # under the last frames' capped σ (re-estimated, as the planar retry's, a hard combination's retries
            # under an occluder gave up at the coarsest level: LOST frames on the saddle)
            result = problem.track(current, self._G, self._e, self._rho, *photometric, tolerance_px=tolerance,
                                   scale_cap=cap, give_up=True, may_hold_epipole=may_hold)
        implausible = self._integrity.judge(G0, result.G, result.scale) if result.converged else ""
        if implausible:
            result.converged, result.reason = False, implausible
        return result

    def _prediction(self) -> tuple[F64, F64]:
        """Start `(G, e)` of the next frame: the last estimate, or its constant-velocity extrapolation (module
        docstring)."""
        if self._G_before is None or not self._problem.config.base.predict_motion:
            return self._G, self._e
        M = self._G @ np.linalg.inv(self._G_before)
        G, e = M @ self._G, M @ self._e
        if not (np.all(np.isfinite(G)) and np.all(np.isfinite(e)) and np.linalg.det(G) > 0.0):
            return self._G, self._e
        return G, e

    def _failure(self, reason: str, flags: list[str]) -> GeneralResult:
        """The last good state, reported as not converged."""
        self._G_before = None
        n = self._problem.basis.size
        return GeneralResult(
            G=self._G.copy(), e=self._e.copy(), rho_coeffs=np.zeros(n) if self._rho is None else self._rho.copy(),
            basis=self._problem.basis, S=self._gains.copy(), beta=self._beta,
            rho_information=self._information.copy(), converged=False, reason=reason, flags=list(flags),
            failed=True,
        )
