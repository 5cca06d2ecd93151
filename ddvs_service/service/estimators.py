"""The geometry sources of the servo: planar (`ρ* ≡ 0`, `e = 0`) or general (eq. (2), `G`, `e`, `ρ*`).

Both adapt a stateful tracker to one face, `estimate(grey) -> Estimate`, with global (re-)initialisation on the first
frame after a reference and while LOST, so the pipeline does not care which model runs. Each prepares the reference
once: its tracker and its re-acquisition (`registration.reacquisition`, honouring `global_init` and
`feature_source`) share the prepared reference. With `background` (the service's default) the re-acquisition runs
on a worker thread (`service.reacquirer`) on engines of its own (workspaces over the same prepared reference), so a
frame that needs it costs the loop no more than a tracked one: it is answered untracked while the worker searches,
and the worker's pose is adopted on a later frame only if the tracker, started from it, registers that newest frame.
The worker's search also makes the attempt from the last good estimate first (a failing one costs a whole
registration budget), so the loop's only registration of a LOST spell is the failing one that discovers the loss
(after a restart, the first frame's attempt from the persisted estimate runs on the loop: `PlanarEstimator.resume`).
Without `background` the search runs within `estimate` (lockstep experiments: the plant waits for it). The general
estimator's parallax `ρ*` lives in the reference frame: `rho_coeffs` can be persisted and handed back after a restart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ddvs_service.registration.general import GeneralRegistration
from ddvs_service.registration.general_tracker import GeneralTracker
from ddvs_service.registration.global_init import GlobalInitConfig
from ddvs_service.registration.planar import PlanarRegistration
from ddvs_service.registration.reacquisition import Acquisition, Reacquisition
from ddvs_service.registration.residual import residual_image
from ddvs_service.registration.result import RegistrationResult
from ddvs_service.registration.tracker import Tracker
from ddvs_service.service.config import RegistrationSettings
from ddvs_service.service.reacquirer import LAST_GOOD, BackgroundReacquisition, Retry

Roi = tuple[int, int, int, int]
F64 = NDArray[np.float64]


@dataclass
class Estimate:
    """One frame's geometry (reference → current pixels) and registration quality. `rho` is ρ* at the control
    point; `tracked` is False when the registration failed or its quality is below the configured threshold.
    `covariance`: the registration's covariance of `G`'s and `e`'s entries from the image noise
    (`RegistrationResult`), None where the engine does not give it."""

    tracked: bool
    G: F64
    e: F64
    rho: float
    iterations: int
    residual_rms: float
    inlier_ratio: float
    message: str = ""
    rho_coeffs: list[float] = field(default_factory=list)
    covariance: F64 | None = None


class PlanarEstimator:
    """Planar tracker + direct global initialiser (the planar path of the issue, `e = 0`, `ρ* = 0`).

    A frame that needs re-acquisition (any after an untracked one) is first tracked from the last good estimate
    (the servo held the camera still since: the cheapest re-acquisition, and the only one that survives a large
    occluder, under which the global search's photometric cost exceeds its threshold) — with `background` on the
    worker, by a tracker of its own started from this one's `G` (the worker then answers OK with `LAST_GOOD` and
    this tracker registers the newest frame from its unchanged state); when that fails, from the global
    initialiser's estimate, and when there is none (yet) the frame is untracked — never tracked on from
    an estimate the initialiser has not confirmed. The first frame after a reference has no last good estimate. A
    re-acquired frame passes the tracker's own checks (convergence, inliers, `registration.integrity`) like any
    other; the pipeline's error guard and the state machine's confirmation frames come on top."""

    def __init__(self, reference: NDArray[np.float32], roi: Roi, settings: RegistrationSettings,
                 background: bool = False) -> None:
        self.reference, self.roi, self.settings = reference, roi, settings
        engine = PlanarRegistration.prepare(reference, roi, config=settings.engine_config())
        self._tracker = Tracker(engine)
        searcher = PlanarRegistration(engine.prepared, engine.config) if background else engine
        self._acquire = _reacquisition(searcher, None, settings, background, self._retry(Tracker(searcher)))
        self._needs_init = True
        self._last_good: F64 | None = None  # where a re-acquisition tracks from first (None: nowhere yet)
        self._before: F64 | None = None  # the estimate before the last tracked frame (reverted to by `lose`)
        self._acquired = False  # the estimate descends from a global re-acquisition the guard has not trusted yet
        self._resumed = False  # `resume`d, no frame since: the next one is tracked from there on this thread first

    @property
    def G(self) -> F64:
        return self._tracker.G

    @property
    def acquisition(self) -> Reacquisition:
        return self._acquire

    def assume(self, G: F64) -> None:
        """Start tracking from a known `G` (e.g. identity when the reference is the current frame)."""
        self._tracker.reset(G)
        self._needs_init = False
        self._last_good = self._tracker.G

    @property
    def last_good(self) -> F64 | None:
        """The last good estimate, where a re-acquisition tracks from first (None: none, or forgotten by `lose`)."""
        return self._last_good

    def resume(self, G: F64) -> None:
        """Take `G` as the last good estimate without trusting it (a restart: an earlier process's last estimate):
        the next frame is re-acquired from it first, then by the initialiser. That first attempt runs within
        `estimate` even with `background` (a failing one gives up early, `tracking_give_up_iterations`): the view
        after a restart is usually the one the estimate was made on, and the frame it registers is the first of
        the state machine's confirmation frames instead of an untracked one."""
        self._tracker.reset(G)
        self._needs_init = True
        self._last_good = self._tracker.G
        self._resumed = True

    def lose(self) -> None:
        """The last tracked frame's fit is suspect (the pipeline's error guard). Tracked on from the tracker's own
        estimate, it is forgotten: the tracker goes back to the estimate before it and the next frame is
        re-acquired by the global initialiser only (tracking again from there could reproduce the same fit frame
        after frame, which the guard would adopt once 30 frames agree). Descended from a global re-acquisition
        since the guard last trusted a frame, it is kept: the initialiser found it independently, and the guard
        holds the servo until the tracked frames agree on it."""
        if self._acquired:
            return
        self._needs_init = True
        if self._before is not None:
            self._tracker.reset(self._before)
        self._last_good = None

    def trust(self) -> None:
        """The pipeline's error guard accepted the last tracked frame."""
        self._acquired = False

    def close(self) -> None:
        """End the background re-acquisition, if any (a new reference replaces this estimator)."""
        self._acquire.close()

    def residual(self, grey: NDArray[np.float32]) -> NDArray[np.float32]:
        """The residual image of `grey` over the ROI under the current state (`registration.residual`)."""
        gains, beta = self._tracker.photometric
        s = self.settings
        return residual_image(self.reference, grey, self.roi, self._tracker.G, gains, beta, s.gamma, s.defocus_px)

    def estimate(self, grey: NDArray[Any], control_px: tuple[float, float]) -> Estimate:
        message, result = "", None
        G_before = self._tracker.G
        resumed, self._resumed = self._resumed, False
        if self._needs_init and self._acquire.enabled:
            beside = isinstance(self._acquire, BackgroundReacquisition)  # the worker tries the last good itself
            if self._last_good is not None and (resumed or not beside):
                result = self._tracker.track(grey)
                if _accepted(result):
                    message = "re-acquired by tracking from the last good estimate"
            if not (result is not None and _accepted(result)):
                init = self._search(grey, retry=result is None)
                if init.G is None:  # never track on from an unconfirmed estimate
                    local = "" if result is None else f"tracking from the last good estimate: {result.reason}; "
                    return Estimate(False, self._tracker.G, np.zeros(3), 0.0, 0, 0.0, 0.0,
                                    f"{local}global initialisation: LOST ({init.reason})")
                if init.reason == LAST_GOOD:  # the worker registered a frame from this tracker's state: track on
                    message = "re-acquired by tracking from the last good estimate"
                else:
                    self._tracker.reset(init.G)
                    self._acquired = True
                    message = "global initialisation: ok" + (" (contradicted the tracking estimate)"
                                                             if init.contradicts else "")
                result = None
        if result is None:
            result = self._tracker.track(grey)
        tracked = _accepted(result)
        self._needs_init = not tracked
        if tracked:
            self._before, self._last_good = G_before, result.G
        else:
            message = f"{message}; registration: {result.reason}".strip("; ")
        return Estimate(tracked, result.G, np.zeros(3), 0.0, int(sum(result.iterations)),
                        _finite(result.residual_rms), _finite(result.inlier_ratio), message,
                        covariance=result.covariance)

    def _search(self, grey: NDArray[np.float32], retry: bool) -> Acquisition:
        """The re-acquisition of `grey`; on the worker, from the tracker's state first when there is a last good
        estimate (its state is that estimate: an untracked frame leaves it unchanged) and `retry` (this frame was
        not tried from there already)."""
        G = self._tracker.G
        if isinstance(self._acquire, BackgroundReacquisition):
            return self._acquire(grey, G, G if self._last_good is not None and retry else None)
        return self._acquire(grey, G)

    def _retry(self, trial: Tracker) -> Retry:
        """The attempt from the last good estimate on the worker: `trial` (on the worker's engine) restarted there
        registers the frame and passes this estimator's checks."""
        def retry(current: NDArray[np.float32], start: F64) -> bool:
            trial.reset(start)
            return _accepted(trial.track(current))
        return retry


class GeneralEstimator:
    """General tracker of eq. (2): ρ* estimated once and kept in the reference frame (`rho_coeffs`); `G`, `e`
    tracked. Once the tracker declares LOST, it re-acquires as the planar estimator does: from the last good
    estimate first, then from the global initialiser's (`LastGoodFirst`)."""

    def __init__(self, reference: NDArray[np.float32], roi: Roi, settings: RegistrationSettings,
                 rho_coeffs: list[float] | None = None, background: bool = False) -> None:
        self.settings = settings
        engine = GeneralRegistration.prepare(reference, roi, config=settings.general_config())
        searcher = GeneralRegistration(engine.prepared, engine.config) if background else engine
        self._search = _reacquisition(searcher.planar, searcher, settings, background, self._retry(searcher))
        self._acquire = LastGoodFirst(self._search)
        self._tracker = GeneralTracker(engine, self._acquire, rho=rho_coeffs or None)
        self._G: F64 = np.eye(3)
        self._acquired = False  # as `PlanarEstimator._acquired`

    @property
    def G(self) -> F64:
        return self._G

    @property
    def acquisition(self) -> Reacquisition:
        return self._search

    def assume(self, G: F64) -> None:
        """The general tracker always re-acquires globally (it also estimates ρ* on that frame)."""

    @property
    def last_good(self) -> F64 | None:
        """The last tracked `G` (`PlanarEstimator.last_good`)."""
        return self._acquire.last_good

    def resume(self, G: F64) -> None:
        """Take `G` as the last good estimate without trusting it (`PlanarEstimator.resume`): the tracker's first
        re-acquisition starts from it, with ρ* the persisted `rho_coeffs` (none: the initialiser)."""
        self._G = np.array(G, dtype=np.float64)
        self._acquire.last_good = self._G

    def lose(self) -> None:
        """The last tracked frame's fit is suspect: re-acquire `G` and `e` by the global initialiser only on the next
        frames (the tracker also re-acquires by itself after `lost_after` failed frames) — unless the fit descends
        from a global re-acquisition the guard has not trusted yet (`PlanarEstimator.lose`)."""
        if not self._acquired:
            self._tracker.lose()
            self._acquire.last_good = None

    def trust(self) -> None:
        """The pipeline's error guard accepted the last tracked frame."""
        self._acquired = False

    def close(self) -> None:
        """End the background re-acquisition, if any (a new reference replaces this estimator)."""
        self._search.close()

    def _retry(self, searcher: GeneralRegistration) -> Retry:
        """The attempt from the last good estimate on the worker, as the tracker makes it after LOST: `G` from
        there, `e` from 0, ρ* the tracker's (none known yet: no attempt)."""
        def retry(current: NDArray[np.float32], start: F64) -> bool:
            rho = self._tracker.rho_coeffs
            if rho is None:
                return False
            return _accepted(searcher.track(current, start, np.zeros(3), rho))
        return retry

    def residual(self, grey: NDArray[np.float32]) -> None:
        """Not available for the general model yet (its warp has the parallax term of eq. (2), not `G` alone)."""
        return None

    def estimate(self, grey: NDArray[Any], control_px: tuple[float, float]) -> Estimate:
        adopted = self._search.adopted
        result = self._tracker.track(grey)
        tracked = _accepted(result)
        message = "" if tracked else f"registration: {result.reason} {result.flags}"
        if tracked:
            self._G = result.G
            self._search.cancel()
            self._acquired |= self._search.adopted > adopted
            if self._acquire.offered:
                message = "re-acquired by tracking from the last good estimate"
            self._acquire.last_good, self._acquire.offered = result.G, False
        coeffs = self._tracker.rho_coeffs
        return Estimate(
            tracked, result.G, result.e, float(result.rho_at(control_px)) if tracked else 0.0,
            int(sum(result.iterations)), _finite(result.residual_rms), _finite(result.inlier_ratio), message,
            [] if coeffs is None else [float(c) for c in coeffs], covariance=result.covariance,
        )


class LastGoodFirst(Reacquisition):
    """The general tracker's re-acquisition: `last_good` (the estimator's last tracked `G`) handed over as the start
    on the first call of a LOST spell (the tracker then registers the frame from it), `search` (the global
    initialiser) on the next one, and so on alternately. A background `search` makes the attempt from `last_good`
    itself, on the worker, before its global search, and answers `LAST_GOOD` when it registered the frame: then
    `last_good` is handed over. `offered`: the last call handed over `last_good`."""

    def __init__(self, search: Reacquisition) -> None:
        super().__init__(search.engine)  # no initialiser of its own: `search` has it
        self.search_with = search
        self.last_good: F64 | None = None
        self.offered = False

    @property
    def enabled(self) -> bool:
        return self.search_with.enabled

    @property
    def busy(self) -> bool:
        return self.search_with.busy

    def __call__(self, current: NDArray[np.float32], tracking_G: F64 | None = None) -> Acquisition:
        if isinstance(self.search_with, BackgroundReacquisition):
            found = self.search_with(current, tracking_G, self.last_good)
            self.offered = found.reason == LAST_GOOD
            return found
        if self.last_good is not None and not self.offered:
            self.offered = True
            return Acquisition("OK", self.last_good, LAST_GOOD)
        self.offered = False
        return self.search_with(current, tracking_G)

    def cancel(self) -> None:
        self.search_with.cancel()

    def close(self) -> None:
        self.search_with.close()


def _reacquisition(engine: PlanarRegistration, general: GeneralRegistration | None,
                   settings: RegistrationSettings, background: bool, retry: Retry) -> Reacquisition:
    """The service's re-acquisition on `engine` (and `general`): off unless `global_init`, from `feature_source`;
    on a worker thread with `background` (the engines must then be the worker's own), which tries `retry` first."""
    config = GlobalInitConfig(feature_source=settings.feature_source) if settings.global_init else None
    return BackgroundReacquisition(engine, general, config, retry) if background else Reacquisition(
        engine, general, config)


def _accepted(result: RegistrationResult) -> bool:
    """A registration the service acts on: converged. The engine's verdict needs `min_inlier_ratio` of the ROI's
    pixels inliers, or a tracker's lower floor while an occluder slides over the template
    (`registration.integrity.Integrity.inlier_floor`)."""
    return result.converged


def _finite(x: float) -> float:
    return float(x) if math.isfinite(x) else 0.0
