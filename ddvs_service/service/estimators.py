"""The geometry sources of the servo: planar (`ρ* ≡ 0`, `e = 0`) or general (eq. (2), `G`, `e`, `ρ*`).

Both adapt a stateful tracker to one face, `estimate(grey) -> Estimate`, with global (re-)initialisation on the first
frame after a reference and while LOST, so the pipeline does not care which model runs. Each prepares the reference
once: its tracker and its re-acquisition (`registration.reacquisition`, honouring `global_init` and
`feature_source`) share the engine. The general estimator's
parallax `ρ*` lives in the reference frame: `rho_coeffs` can be persisted and handed back after a restart.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ddvs_service.registration.general import GeneralRegistration
from ddvs_service.registration.general_tracker import GeneralTracker
from ddvs_service.registration.global_init import GlobalInitConfig
from ddvs_service.registration.planar import PlanarRegistration
from ddvs_service.registration.reacquisition import Reacquisition
from ddvs_service.registration.residual import residual_image
from ddvs_service.registration.tracker import Tracker
from ddvs_service.service.config import RegistrationSettings

Roi = tuple[int, int, int, int]
F64 = NDArray[np.float64]


@dataclass
class Estimate:
    """One frame's geometry (reference → current pixels) and registration quality. `rho` is ρ* at the control
    point; `tracked` is False when the registration failed or its quality is below the configured threshold."""

    tracked: bool
    G: F64
    e: F64
    rho: float
    iterations: int
    residual_rms: float
    inlier_ratio: float
    message: str = ""
    rho_coeffs: list[float] = field(default_factory=list)


class PlanarEstimator:
    """Planar tracker + direct global initialiser (the planar path of the issue, `e = 0`, `ρ* = 0`). A frame that
    needs re-acquisition (the first after a reference, any after an untracked one) is tracked only from the global
    initialiser's estimate: when that fails the frame is untracked, never tracked on from the stale estimate."""

    def __init__(self, reference: NDArray[np.float32], roi: Roi, settings: RegistrationSettings) -> None:
        self.reference, self.roi, self.settings = reference, roi, settings
        engine = PlanarRegistration.prepare(reference, roi, config=settings.engine_config())
        self._tracker = Tracker(engine)
        self._acquire = _reacquisition(engine, None, settings)
        self._needs_init = True

    @property
    def G(self) -> F64:
        return self._tracker.G

    def assume(self, G: F64) -> None:
        """Start tracking from a known `G` (e.g. identity when the reference is the current frame)."""
        self._tracker.reset(G)
        self._needs_init = False

    def lose(self) -> None:
        """Force a global re-initialisation on the next frame."""
        self._needs_init = True

    def residual(self, grey: NDArray[np.float32]) -> NDArray[np.float32]:
        """The residual image of `grey` over the ROI under the current state (`registration.residual`)."""
        gains, beta = self._tracker.photometric
        s = self.settings
        return residual_image(self.reference, grey, self.roi, self._tracker.G, gains, beta, s.gamma, s.defocus_px)

    def estimate(self, grey: NDArray[np.float32], control_px: tuple[float, float]) -> Estimate:
        message = ""
        if self._needs_init and self._acquire.enabled:
            init = self._acquire(grey, self._tracker.G)
            if init.G is not None:
                self._tracker.reset(init.G)
                message = "global initialisation: ok" + (" (contradicted the tracking estimate)" if init.contradicts
                                                         else "")
            else:  # never track on from the stale estimate: it is what was lost
                return Estimate(False, self._tracker.G, np.zeros(3), 0.0, 0, 0.0, 0.0,
                                f"global initialisation: LOST ({init.reason}); the last estimate is not used")
        result = self._tracker.track(grey)
        tracked = result.converged and result.inlier_ratio >= self.settings.min_inlier_ratio
        self._needs_init = not tracked
        if not tracked:
            message = f"{message}; registration: {result.reason}".strip("; ")
        return Estimate(tracked, result.G, np.zeros(3), 0.0, int(sum(result.iterations)),
                        _finite(result.residual_rms), _finite(result.inlier_ratio), message)


class GeneralEstimator:
    """General tracker of eq. (2): ρ* estimated once and kept in the reference frame (`rho_coeffs`); `G`, `e`
    tracked."""

    def __init__(self, reference: NDArray[np.float32], roi: Roi, settings: RegistrationSettings,
                 rho_coeffs: list[float] | None = None) -> None:
        self.settings = settings
        engine = GeneralRegistration.prepare(reference, roi, config=settings.general_config())
        self._tracker = GeneralTracker(engine, _reacquisition(engine.planar, engine, settings), rho=rho_coeffs or None)
        self._G: F64 = np.eye(3)

    @property
    def G(self) -> F64:
        return self._G

    def assume(self, G: F64) -> None:
        """The general tracker always re-acquires globally (it also estimates ρ* on that frame)."""

    def lose(self) -> None:
        """Force a global re-acquisition of `G` and `e` on the next frame (the tracker also does so by itself
        after `lost_after` failed frames)."""
        self._tracker.lose()

    def residual(self, grey: NDArray[np.float32]) -> None:
        """Not available for the general model yet (its warp has the parallax term of eq. (2), not `G` alone)."""
        return None

    def estimate(self, grey: NDArray[np.float32], control_px: tuple[float, float]) -> Estimate:
        result = self._tracker.track(grey)
        tracked = result.converged and result.inlier_ratio >= self.settings.min_inlier_ratio
        if tracked:
            self._G = result.G
        coeffs = self._tracker.rho_coeffs
        return Estimate(
            tracked, result.G, result.e, float(result.rho_at(control_px)) if tracked else 0.0,
            int(sum(result.iterations)), _finite(result.residual_rms), _finite(result.inlier_ratio),
            "" if tracked else f"registration: {result.reason} {result.flags}",
            [] if coeffs is None else [float(c) for c in coeffs],
        )


def _reacquisition(engine: PlanarRegistration, general: GeneralRegistration | None,
                   settings: RegistrationSettings) -> Reacquisition:
    """The service's re-acquisition on the estimator's engines: off unless `global_init`, from `feature_source`."""
    config = GlobalInitConfig(feature_source=settings.feature_source) if settings.global_init else None
    return Reacquisition(engine, general, config)


def _finite(x: float) -> float:
    return float(x) if np.isfinite(x) else 0.0
