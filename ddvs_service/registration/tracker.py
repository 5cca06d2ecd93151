"""Stateful planar tracker for a video stream: registers each frame warm-started from the last good estimate.

Consecutive frames move little, so a frame is first solved on the finest `config.tracking_levels` pyramid levels
only, from a constant-velocity prediction when `config.predict_motion` is set and the last two frames converged:
`G_k = G_{k−1} · G_{k−2}⁻¹ · G_{k−1}` (the last inter-frame motion `G_{k−1} G_{k−2}⁻¹`, in current-image pixels,
applied once more). When that does not converge the frame is solved again from the last good estimate over the
whole pyramid, its robust scale estimated afresh (no cap). Both attempts give up on a level not converged after
`config.tracking_give_up_iterations` iterations, unless it is the finest and keeps the inlier ratio the result needs
(`solver.gauss_newton`'s `give_up_below`): a frame within reach converges at a coarse level in a few and keeps its
support at the finest, while on a lost frame (the target hidden or out of reach) every level of both attempts would
run `max_iterations`; the frame that discovers the loss costs about twice `tracking_give_up_iterations`.

The state is `G` (SL(3), reference → current full-image pixels), the gains `S`, the bias `β` (eq. (4)) and the
robust scale σ. Integrity (`registration.integrity`): the σ the engine uses is capped at a multiple of the scale of
the last good frames, and a converged fit whose own scale or whose corners jumped implausibly is refused. A frame
whose registration converged and passed that check replaces the state; any other frame leaves it unchanged and
is reported with `converged = False` and the reason. `track` never raises and never returns a non-finite `G`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.lie import det3, inv3, sl3_normalize
from ddvs_service.registration.config import RegistrationConfig
from ddvs_service.registration.integrity import Integrity
from ddvs_service.registration.planar import PlanarRegistration
from ddvs_service.registration.reference import Roi
from ddvs_service.registration.residual import residual_image
from ddvs_service.registration.result import RegistrationResult


class Tracker:
    """Track the ROI of the engine's reference through successive frames (same size as the reference). `engine`
    (its prepared reference and settings) may be shared with the global initialiser that re-acquires for it."""

    def __init__(self, engine: PlanarRegistration) -> None:
        self._problem = engine
        self._integrity = Integrity(engine.roi)  # kept through resets: the reference does not change
        self.reset()

    @classmethod
    def prepare(
        cls,
        reference: ArrayLike,
        roi: Roi | None = None,
        config: RegistrationConfig = RegistrationConfig(),  # noqa: B008 - frozen, immutable default
        mask: ArrayLike | None = None,
    ) -> Tracker:
        """A tracker on its own engine (`PlanarRegistration.prepare`)."""
        return cls(PlanarRegistration.prepare(reference, roi=roi, mask=mask, config=config))

    @property
    def engine(self) -> PlanarRegistration:
        return self._problem

    @property
    def G(self) -> NDArray[np.float64]:
        """Current estimate (3×3, det 1), reference → current pixels."""
        return self._G.copy()

    @property
    def photometric(self) -> tuple[NDArray[np.float64], float]:
        """The gains `S` (node values, shape `gain_grid`) and bias `β` of the current state (eq. (4))."""
        return self._gains.copy(), self._beta

    def residual(self, current: ArrayLike) -> NDArray[np.float32]:
        """The residual image of `current` over the ROI under the current state (`registration.residual`)."""
        prepared, config = self._problem.prepared, self._problem.config
        return residual_image(prepared.image, np.asarray(current), prepared.roi, self._G, self._gains, self._beta,
                              config.gamma, config.defocus_px)

    def reset(self, G: ArrayLike | None = None) -> None:
        """Restart from `G` (identity when None; any scale, positive determinant), unit gains, zero bias."""
        self._G = np.eye(3) if G is None else sl3_normalize(np.asarray(G, dtype=np.float64).reshape(3, 3))
        self._G_before: NDArray[np.float64] | None = None  # the good estimate before `_G` (None: no velocity)
        self._gains = np.ones(self._problem.grid)
        self._beta = 0.0
        self._scale: float | None = None

    def track(self, current: ArrayLike) -> RegistrationResult:
        """Register `current` from the last good state; on failure keep the state and report why."""
        try:
            start = self._prediction()
            config = self._problem.config
            tolerance = config.tracking_step_tolerance_px
            cap = self._integrity.scale_cap
            floor = self._integrity.inlier_floor(config.min_inlier_ratio)  # lower while an occluder slides in
            result = self._problem.run(current, G0=start, gains0=self._gains, beta0=self._beta, scale0=self._scale,
                                       first_level=config.tracking_levels - 1, tolerance_px=tolerance, scale_cap=cap,
                                       give_up=True, min_inlier_ratio=floor)
            if not result.converged and (start is not self._G or len(result.iterations) < len(self._problem.levels)):
                # the robust scale re-estimated on this frame: a sudden motion of several pixels leaves the last
                # frames' σ far below this frame's residuals, and Tukey weights at that σ reject the signal itself
                result = self._problem.run(current, G0=self._G, gains0=self._gains, beta0=self._beta,
                                           scale0=None, tolerance_px=tolerance, give_up=True)
        except Exception as exc:  # the tracker's contract: report, never raise
            return self._failure(f"error: {type(exc).__name__}: {exc}")
        if not np.isfinite(result.G).all():
            return self._failure(f"non-finite estimate ({result.reason})")
        if result.converged:
            implausible = self._integrity.judge(start, result.G, result.scale, result.inlier_ratio)
            if implausible:
                result.converged, result.reason = False, implausible
        if result.converged:
            self._integrity.accept(result.scale, result.inlier_ratio)
            self._G_before, self._G = self._G, result.G
            # the next frame's first σ: never below the anchor's floor (a frame identical to the reference measures
            # σ at the engine's floor, and Tukey weights at that scale would reject the next frame's every pixel)
            self._gains, self._beta = result.S, result.beta
            self._scale = max(result.scale, self._integrity.config.min_anchor)
        else:
            self._G_before = None
        return result

    def _prediction(self) -> NDArray[np.float64]:
        """Start of the next frame: `_G` itself, or its constant-velocity extrapolation (module docstring)."""
        if self._G_before is None or not self._problem.config.predict_motion:
            return self._G
        G = self._G @ (inv3(self._G_before) @ self._G)
        d = det3(G)
        return G / np.cbrt(d) if math.isfinite(d) and d > 0.0 and np.isfinite(G).all() else self._G

    def _failure(self, reason: str) -> RegistrationResult:
        self._G_before = None
        return RegistrationResult(G=self._G.copy(), S=self._gains.copy(), beta=self._beta, iterations=[],
                                  converged=False, reason=reason, failed=True)
