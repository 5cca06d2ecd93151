"""The geometry source of a servo, built from its settings: a `registration.session.TrackingSession` over the
configured model — planar (`ρ* ≡ 0`, `e = 0`: `registration.tracker.Tracker`) or general (eq. (2), `G`, `e`, `ρ*`:
`registration.general_tracker.GeneralTracker`) — and its re-acquisition (`registration.reacquisition`, honouring
`global_init` and `feature_source`), which shares the tracker's prepared reference.

With `background` (the service's default) the re-acquisition runs on a worker thread (`service.reacquirer`) on
engines of its own (workspaces over the same prepared reference), and the worker's attempt from the last good
estimate runs a tracker of its own, started there (for the general model, with the loop's tracker's ρ*). Without
`background` the search runs within the frame (lockstep experiments: the plant waits for it). The general model's
ρ* lives in the reference frame: `rho_coeffs` can be persisted and handed back after a restart.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ddvs_service.registration.general import GeneralRegistration
from ddvs_service.registration.general_tracker import GeneralTracker
from ddvs_service.registration.global_init import GlobalInitConfig
from ddvs_service.registration.planar import PlanarRegistration
from ddvs_service.registration.reacquisition import Reacquisition
from ddvs_service.registration.session import ModelTracker, TrackingSession
from ddvs_service.registration.tracker import Tracker
from ddvs_service.service.config import RegistrationSettings
from ddvs_service.service.reacquirer import BackgroundReacquisition, Retry

Roi = tuple[int, int, int, int]
F64 = NDArray[np.float64]


def tracking_session(reference: NDArray[np.float32], roi: Roi, settings: RegistrationSettings,
                     background: bool = False, rho_coeffs: list[float] | None = None) -> TrackingSession:
    """The session of `settings.model` on `reference` (grey, float32) over `roi` (module docstring); `rho_coeffs`:
    a known ρ* of this reference (general model; ignored by the planar one)."""
    tracker: ModelTracker
    if settings.model == "general":
        engine = GeneralRegistration.prepare(reference, roi, config=settings.general_config())
        general_tracker = GeneralTracker(engine, rho=rho_coeffs or None)
        searcher = GeneralRegistration(engine.prepared, engine.config) if background else engine
        retry = _general_retry(general_tracker, GeneralTracker(searcher))
        tracker, planar, general = general_tracker, searcher.planar, searcher
    else:
        planar_engine = PlanarRegistration.prepare(reference, roi, config=settings.engine_config())
        tracker = Tracker(planar_engine)
        planar = PlanarRegistration(planar_engine.prepared, planar_engine.config) if background else planar_engine
        retry, general = _planar_retry(Tracker(planar)), None
    config = GlobalInitConfig(feature_source=settings.feature_source) if settings.global_init else None
    acquisition = (BackgroundReacquisition(planar, general, config, retry) if background
                   else Reacquisition(planar, general, config))
    return TrackingSession(tracker, acquisition)


def _planar_retry(trial: Tracker) -> Retry:
    """The worker's attempt from the last good estimate: `trial` (on the worker's engine) restarted there registers
    the frame."""
    def retry(current: NDArray[np.float32], start: F64) -> bool:
        trial.reset(start)
        return trial.track(current).converged
    return retry


def _general_retry(loop: GeneralTracker, trial: GeneralTracker) -> Retry:
    """The worker's attempt from the last good estimate: `trial` (on the worker's engine) restarted there with the
    loop tracker's ρ* (`e` from 0) registers the frame; none while no ρ* is known (the attempt would estimate it)."""
    def retry(current: NDArray[np.float32], start: F64) -> bool:
        rho = loop.rho_coeffs
        if rho is None:
            return False
        trial.adopt_rho(rho)
        trial.reset(start)
        return trial.track(current).converged
    return retry
