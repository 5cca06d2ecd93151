"""The tracking lifecycle, one for every model: acquire, track, trust, lose, re-acquire, resume.

A `TrackingSession` drives a model's stateful tracker (`ModelTracker`: the planar `tracker.Tracker`, the general
`general_tracker.GeneralTracker`) and a re-acquisition (`reacquisition.Reacquisition`: within the call for lockstep
experiments, where the plant waits for the answer; beside the loop on a worker thread for the service,
`service.reacquirer`). It owns the lifecycle's state; the trackers own only their estimate.

- First frame after a reference (and any frame after an untracked one): re-acquired. From the last good estimate
  first (the servo held the camera still since: the cheapest re-acquisition, and the only one that survives a large
  occluder, under which the global search's photometric cost exceeds its threshold) — within the call by this
  session's tracker, beside the loop by the worker's own tracker, which then answers OK with `LAST_GOOD` and this
  tracker registers the newest frame from its unchanged state; when that fails, from the global initialiser's
  estimate, and when there is none (yet) the frame is untracked — never tracked on from an estimate the initialiser
  has not confirmed. The first frame after a reference has no last good estimate; beside the loop, a frame that
  needs a search is answered at once, untracked, and the worker's pose is adopted on a later frame only if the
  tracker, started from it, registers that newest frame.
- `assume(G)`: start tracking from a known `G` (identity when the reference is the current frame).
- `resume(G)`: an earlier process's last good estimate, not trusted: the next frame is re-acquired from it first,
  on the calling thread even beside the loop (the view after a restart is usually the one it was made on, and the
  frame it registers is the first of the state machine's confirmation frames instead of an untracked one).
- `lose()`: the caller's error guard found the last tracked fit suspect. Tracked on from the tracker's own estimate,
  it is forgotten (the tracker goes back to the estimate before it and the next frame is re-acquired by the global
  initialiser only: tracking again from there could reproduce the same fit frame after frame). Descended from a
  global re-acquisition the guard has not trusted yet, it is kept: the initialiser found it independently, and the
  guard holds the servo until the tracked frames agree on it. `trust()`: the guard accepted the last tracked frame.
A re-acquired frame passes the tracker's own checks (convergence, inliers, `integrity`) like any other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.registration.general_result import GeneralResult
from ddvs_service.registration.reacquisition import LAST_GOOD, Acquisition, Reacquisition
from ddvs_service.registration.result import RegistrationResult

F64 = NDArray[np.float64]


class ModelTracker(Protocol):
    """A model's stateful tracker as the session drives it (module docstring)."""

    @property
    def G(self) -> F64:
        """Current estimate (3×3, det 1), reference → current pixels."""
        ...

    def reset(self, G: ArrayLike | None = None) -> None:
        """Restart from `G` (photometric model and epipole reset, ρ* kept); the next frame is solved from there."""
        ...

    def track(self, current: ArrayLike) -> RegistrationResult:
        """Register `current` from the state; a failure leaves the state unchanged and says why."""
        ...

    def residual(self, current: ArrayLike) -> NDArray[np.float32]:
        """The residual image of `current` over the ROI under the state (`registration.residual`)."""
        ...


@dataclass
class Estimate:
    """One frame's geometry (reference → current pixels) and registration quality. `tracked` is False when the
    registration failed; `e` (3) and `rho` (ρ* at the control point) are zero for the planar model; `rho_coeffs`:
    the general model's ρ* coefficients (empty for the planar model or until estimated); `covariance`: the
    registration's covariance of `G`'s and `e`'s entries from the image noise (`RegistrationResult`), None where
    the engine does not give it."""

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


class TrackingSession:
    """The lifecycle of module docstring over `tracker` and `acquisition` (whose engines share the tracker's
    prepared reference; beside the loop, workspaces of their own)."""

    def __init__(self, tracker: ModelTracker, acquisition: Reacquisition) -> None:
        self._tracker = tracker
        self._acquire = acquisition
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

    @property
    def last_good(self) -> F64 | None:
        """The last good estimate, where a re-acquisition tracks from first (None: none, or forgotten by `lose`)."""
        return self._last_good

    def assume(self, G: ArrayLike) -> None:
        """Start tracking from a known `G` (e.g. identity when the reference is the current frame)."""
        self._tracker.reset(G)
        self._needs_init = False
        self._last_good = self._tracker.G

    def resume(self, G: ArrayLike) -> None:
        """Take `G` as the last good estimate without trusting it (a restart; module docstring)."""
        self._tracker.reset(G)
        self._needs_init = True
        self._last_good = self._tracker.G
        self._resumed = True

    def lose(self) -> None:
        """The last tracked frame's fit is suspect (module docstring)."""
        if self._acquired:
            return
        self._needs_init = True
        if self._before is not None:
            self._tracker.reset(self._before)
        self._last_good = None

    def trust(self) -> None:
        """The caller's error guard accepted the last tracked frame."""
        self._acquired = False

    def close(self) -> None:
        """End the re-acquisition beside the loop, if any (a new reference replaces this session)."""
        self._acquire.close()

    def residual(self, current: ArrayLike) -> NDArray[np.float32]:
        """The residual image of `current` over the ROI under the newest estimate (`registration.residual`)."""
        return self._tracker.residual(current)

    def estimate(self, current: ArrayLike, control_px: tuple[float, float]) -> Estimate:
        """Register `current` (same size as the reference); `control_px`: the control point `p*` (reference pixels)
        where ρ* is reported."""
        message, result = "", None
        before = self._tracker.G
        resumed, self._resumed = self._resumed, False
        if self._needs_init and self._acquire.enabled:
            beside = self._acquire.beside  # the worker tries the last good estimate itself
            if self._last_good is not None and (resumed or not beside):
                result = self._tracker.track(current)
                if result.converged:
                    message = "re-acquired by tracking from the last good estimate"
            if not (result is not None and result.converged):
                init = self._search(np.asarray(current, dtype=np.float32), retry=result is None)
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
            result = self._tracker.track(current)
        self._needs_init = not result.converged
        if result.converged:
            self._before, self._last_good = before, result.G
            self._acquire.cancel()  # a search under way is for a frame this one supersedes
        else:
            flags = f" {result.flags}" if isinstance(result, GeneralResult) and result.flags else ""
            message = f"{message}; registration: {result.reason}{flags}".strip("; ")
        e, rho, coeffs = _parallax(result, control_px)
        return Estimate(result.converged, result.G, e, rho, int(sum(result.iterations)),
                        _finite(result.residual_rms), _finite(result.inlier_ratio), message, coeffs,
                        result.covariance)

    def _search(self, current: NDArray[np.float32], retry: bool) -> Acquisition:
        """The re-acquisition of `current`; beside the loop, from the tracker's state first when there is a last
        good estimate (its state is that estimate: an untracked frame leaves it unchanged) and `retry` (this frame
        was not tried from there already). The tracker's state is the estimate a contradiction is reported against
        once it has tracked a frame or been resumed."""
        G = self._tracker.G
        start = G if self._acquire.beside and self._last_good is not None and retry else None
        tracked = self._last_good is not None or self._before is not None  # else G is only where the tracker began
        return self._acquire(current, G if tracked else None, start)


def _parallax(result: RegistrationResult, control_px: tuple[float, float]) -> tuple[F64, float, list[float]]:
    """`(e, ρ*(p*), ρ* coefficients)` of a result: the general model's when it converged, else zeros (planar: eq. (2)
    with ρ* ≡ 0, e = 0)."""
    if not (isinstance(result, GeneralResult) and result.converged):
        return np.zeros(3), 0.0, []
    return result.e, float(result.rho_at(control_px)), [float(c) for c in result.rho_coeffs]


def _finite(x: float) -> float:
    return float(x) if math.isfinite(x) else 0.0
