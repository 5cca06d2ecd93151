"""One servo step per frame, without I/O: register against the reference, compute the law, update the state.

Data flow: grey frame → tracking session (planar or general model, one lifecycle: warm-started; re-acquired on the
first frame after a reference and while LOST, by default on a worker thread beside this one: a frame that needs it
is answered at once, untracked — zero twist — and the worker's pose is adopted on a later frame once the tracker
registers that frame from it; `registration.session`, `service.estimators`, `service.reacquirer`) → control error
and twist from `G`, `e`, `ρ*` of the control point → error guard (a tracked frame whose error jumped from the last
trusted one is a suspect fit: treated as lost, and the session re-acquires on the next frame; `guard.ErrorGuard`)
→ state machine. The twist is in the current camera frame (OpenCV axes, m/s and rad/s) and is zero unless the state
is SERVOING.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.control.law import ControlLaw, ControlOutput
from ddvs_service.registration.images import to_grey
from ddvs_service.registration.reacquisition import Reacquisition
from ddvs_service.registration.session import Estimate, TrackingSession
from ddvs_service.service.config import ServiceConfig
from ddvs_service.service.estimators import tracking_session
from ddvs_service.service.guard import ErrorGuard
from ddvs_service.service.settling import Figures, SettleWindow, error_jacobian
from ddvs_service.service.state import FrameOutcome, ServoState, StateMachine
from kernels.exclusive import GATE

Roi = tuple[int, int, int, int]
ZERO6 = np.zeros(6)


@dataclass
class StepResult:
    """What one frame produced: the twist to publish, the law's error, registration figures, timings (ms)."""

    twist: NDArray[np.float64]
    error: NDArray[np.float64]
    error_norm: float
    state: ServoState
    iterations: int
    residual_rms: float
    inlier_ratio: float
    message: str
    timings_ms: dict[str, float] = field(default_factory=dict)


def template_roi(config: ServiceConfig, intrinsics: Intrinsics) -> Roi:
    """The configured ROI, or a `template_size` box centred on the control pixel, clipped to the image."""
    reg = config.registration
    if reg.roi is not None:
        return reg.roi
    w, h = reg.template_size
    px, py = config.control.p_star if config.control.p_star is not None else (intrinsics.cx, intrinsics.cy)
    x = round(px - (w - 1) / 2.0)
    y = round(py - (h - 1) / 2.0)
    x = min(max(x, 0), intrinsics.width - w)
    y = min(max(y, 0), intrinsics.height - h)
    if x < 0 or y < 0:
        raise ValueError(f"template {w}×{h} does not fit in the {intrinsics.width}×{intrinsics.height} image")
    return (x, y, w, h)


class ServoPipeline:
    """Reference, estimator, law and state machine of one servo; `step(frame)` runs one control period.
    `background_reacquisition`: re-acquire on a worker thread (the service); False: within `step` (lockstep
    experiments, where the plant waits for the answer). The pipeline's Taichi work holds `kernels.exclusive.GATE`."""

    def __init__(self, config: ServiceConfig, intrinsics: Intrinsics | None = None,
                 background_reacquisition: bool = True) -> None:
        self.config = config
        self.background_reacquisition = background_reacquisition
        self.intrinsics = intrinsics
        control = config.control
        self.machine = StateMachine(control.stop_threshold, control.stop_threshold * control.resume_factor,
                                    control.converge_frames,
                                    scatter_threshold=control.stop_threshold * control.scatter_factor,
                                    max_noise_ratio=control.noise_ratio)
        self.reference: NDArray[np.float32] | None = None
        self.roi: Roi | None = None
        self.rho_coeffs: list[float] = []
        self._estimator: TrackingSession | None = None
        self._law: ControlLaw | None = None
        self.guard = ErrorGuard()
        self._window = SettleWindow(control.settle_frames, control.noise_frames, control.stop_threshold)
        self._suspect = False  # the last frame's fit was suspect: re-acquire on the next one
        if intrinsics is not None:
            self._law = ControlLaw(config.control.law_config(), intrinsics)

    # --- configuration ------------------------------------------------------------------------------------------
    def set_intrinsics(self, intrinsics: Intrinsics) -> None:
        """Adopt camera intrinsics (from camera info); builds the law (raises if the configuration is unstable)."""
        if intrinsics == self.intrinsics:
            return
        law = ControlLaw(self.config.control.law_config(), intrinsics)
        self.intrinsics, self._law = intrinsics, law
        if self.reference is not None:
            self._build_estimator(self.reference, self.roi)

    def apply_config(self, config: ServiceConfig) -> None:
        """Switch to an already validated configuration, keeping the reference and the servo state."""
        law = ControlLaw(config.control.law_config(), self.intrinsics) if self.intrinsics else None
        registration_changed = config.registration != self.config.registration
        self.config, self._law = config, law
        self.machine.stop_threshold = config.control.stop_threshold
        self.machine.resume_threshold = config.control.stop_threshold * config.control.resume_factor
        self.machine.converge_frames = config.control.converge_frames
        self.machine.scatter_threshold = config.control.stop_threshold * config.control.scatter_factor
        self.machine.max_noise_ratio = config.control.noise_ratio
        self._window.resize(config.control.settle_frames, config.control.noise_frames)
        self._window.threshold = config.control.stop_threshold
        if self.reference is not None and registration_changed:
            self._build_estimator(self.reference, config.registration.roi)

    # --- reference ----------------------------------------------------------------------------------------------
    def set_reference(self, image: NDArray, roi: Roi | None = None, G0: NDArray | None = None,
                      rho_coeffs: list[float] | None = None, last_good: NDArray | None = None) -> Roi:
        """Adopt `image` as the reference I*; the first frame after it is globally initialised unless `G0` (e.g.
        identity when the reference is the current frame) is given, or re-acquired from `last_good` first (an
        earlier process's last good estimate, persisted across restarts; not trusted: `TrackingSession.resume`).
        `rho_coeffs`: a known parallax field of this reference (general model; persisted across restarts). Returns
        the ROI used."""
        if self.intrinsics is None:
            raise ValueError("no camera intrinsics yet: configure 'intrinsics' or publish camera info first")
        grey = np.ascontiguousarray(to_grey(image), dtype=np.float32)
        if grey.shape != (self.intrinsics.height, self.intrinsics.width):
            raise ValueError(f"reference is {grey.shape[1]}×{grey.shape[0]}, the camera is "
                             f"{self.intrinsics.width}×{self.intrinsics.height}")
        self.rho_coeffs = list(rho_coeffs or [])
        estimator = self._build_estimator(grey, roi)
        if G0 is not None:
            estimator.assume(G0)
        elif last_good is not None:
            estimator.resume(np.asarray(last_good, dtype=np.float64))
        self.machine.reference_set()
        assert self.roi is not None
        return self.roi

    def _build_estimator(self, grey: NDArray[np.float32], roi: Roi | None) -> TrackingSession:
        assert self.intrinsics is not None
        roi = roi if roi is not None else template_roi(self.config, self.intrinsics)
        with GATE.hold():
            estimator = tracking_session(grey, roi, self.config.registration, self.background_reacquisition,
                                         self.rho_coeffs)
        self.close()
        self.reference, self.roi, self._estimator = grey, roi, estimator
        self.guard.reset()
        self._window.clear()
        self._suspect = False
        return estimator

    def clear_reference(self) -> None:
        self.close()
        self.reference, self.roi, self._estimator, self.rho_coeffs = None, None, None, []
        self.machine.reset()

    def close(self) -> None:
        """End the estimator's background re-acquisition, if any (it finishes its current search unused)."""
        if self._estimator is not None:
            self._estimator.close()

    @property
    def reacquisition(self) -> Reacquisition | None:
        """The estimator's re-acquisition (a `service.reacquirer.BackgroundReacquisition` with
        `background_reacquisition`), None without a reference."""
        return None if self._estimator is None else self._estimator.acquisition

    @property
    def G(self) -> NDArray[np.float64] | None:
        return None if self._estimator is None else self._estimator.G

    @property
    def last_good(self) -> NDArray[np.float64] | None:
        """The estimator's last good estimate (what a restart re-acquires from first), None when there is none."""
        return None if self._estimator is None else self._estimator.last_good

    @property
    def control_px(self) -> tuple[float, float]:
        """The control point `p*` in reference pixels (default: the principal point)."""
        assert self.intrinsics is not None
        p = self.config.control.p_star
        return (self.intrinsics.cx, self.intrinsics.cy) if p is None else p

    # --- one frame ----------------------------------------------------------------------------------------------
    def step(self, frame: NDArray) -> StepResult:
        """Register `frame` (grey or colour, same size as the reference) and compute the twist of this period."""
        if self._estimator is None or self._law is None or self.reference is None:
            return StepResult(ZERO6, ZERO6, 0.0, self.machine.state, 0, 0.0, 0.0, "no reference")
        # a grey frame goes on as it came (a camera's uint8): the engine converts it to float32 in the pass that
        # copies it into its workspace (`registration.images.checked_image`)
        frame = np.asarray(frame)
        grey = frame if frame.ndim == 2 else to_grey(frame)
        if grey.shape != self.reference.shape:
            raise ValueError(f"frame is {grey.shape[1]}×{grey.shape[0]}; the reference is "
                             f"{self.reference.shape[1]}×{self.reference.shape[0]}")
        t0 = time.perf_counter()
        with GATE.hold():
            if self._suspect:
                self._estimator.lose()
            est = self._estimator.estimate(grey, self.control_px)
        if est.rho_coeffs:
            self.rho_coeffs = est.rho_coeffs
        t1 = time.perf_counter()
        out = self._control(est) if est.tracked else None
        # the guard's premise (the camera moves at most a period of the servo's twist between frames) holds only
        # while the servo drives or holds it: outside, the first frame after a start is trusted
        if not self.machine.servo_active:
            self.guard.reset()
        suspect = self.guard.check(out.error) if out is not None and self.machine.servo_active else ""
        self._suspect = bool(suspect)
        if out is not None and not suspect:
            self._estimator.trust()
        if suspect:
            out = None
            est.message = f"{est.message}; {suspect}".strip("; ")
        error = out.error if out is not None else ZERO6
        norm = out.error_norm if out is not None else float("nan")
        state = self.machine.on_frame(FrameOutcome(out is not None, norm, *self._settled(out, est)))
        twist = out.twist if (out is not None and self.machine.moves) else ZERO6
        t2 = time.perf_counter()
        return StepResult(
            twist=np.asarray(twist, dtype=np.float64), error=np.asarray(error, dtype=np.float64),
            error_norm=norm if math.isfinite(norm) else 0.0, state=state, iterations=est.iterations,
            residual_rms=est.residual_rms, inlier_ratio=est.inlier_ratio, message=est.message,
            timings_ms={"registration": (t1 - t0) * 1e3, "control": (t2 - t1) * 1e3},
        )

    def residual(self, frame: NDArray) -> NDArray[np.float32] | None:
        """The registration's residual image of `frame` over the ROI (warped current − reference after the
        photometric model, grey levels; `registration.residual`: eq. (2)'s warp for the general model) under the
        newest estimate; None without a reference."""
        if self._estimator is None:
            return None
        with GATE.hold():
            return self._estimator.residual(to_grey(frame))

    def _settled(self, out: ControlOutput | None, est: Estimate) -> Figures:
        """What the stop decision compares (`service.settling`): the short window's ‖ē‖ and scatter, the long
        window's ‖ē‖, standard error and scatter over the one the registration's covariance predicts; an untracked
        frame (`out` None) empties the window. What a resume compares: `StateMachine`."""
        if out is None:
            return self._window.add(None)
        law = self._law
        assert law is not None
        return self._window.add(out.error, est.covariance, lambda: error_jacobian(law, est.G, est.e, est.rho))

    def _control(self, est: Estimate) -> ControlOutput | None:
        assert self._law is not None
        try:
            return self._law.compute(est.G, est.e, est.rho)
        except ValueError:
            return None
