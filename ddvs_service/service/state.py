"""The servo state machine (pure logic, no I/O).

States: IDLE (no reference) → READY (reference set, not servoing) → SERVOING → CONVERGED (zero twist; resumes
SERVOING when the error grows past `resume_threshold`, a hysteresis above the stop threshold) and LOST (registration
failed, quality below threshold or a suspect fit: zero twist, keeps trying to re-acquire; back to SERVOING only after
`confirm_frames` consecutive tracked frames, so one re-acquired fit never moves the camera) and STOPPED (an operator
stopped it).
Only SERVOING publishes a non-zero twist.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum


class ServoState(str, Enum):
    IDLE = "IDLE"
    READY = "READY"
    SERVOING = "SERVOING"
    CONVERGED = "CONVERGED"
    LOST = "LOST"
    STOPPED = "STOPPED"


class TransitionError(ValueError):
    """A command that is not allowed in the current state (the state is left unchanged)."""


@dataclass
class FrameOutcome:
    """What one registered frame says: registration quality, the control-error norm of this frame, and the figures
    the stop decision compares (`service.settling`): `settled_norm` (the norm of the mean error over a few frames;
    this frame's own when not given) and `scatter` (the RMS deviation of those frames' errors from their mean, same
    units as the error; `math.inf` while too few frames back the mean, 0 when not given); over a longer window,
    `noisy_norm` (the norm of its mean), `standard_error` (of that mean, s/√N) and `noise_ratio` (its scatter over
    the one the image noise predicts) — not given: that clause never stops the servo."""

    tracked: bool
    error_norm: float
    settled_norm: float | None = None
    scatter: float = 0.0
    noisy_norm: float = math.nan
    standard_error: float = math.inf
    noise_ratio: float | Callable[[], float] = math.inf  # a function: computed only if the decision needs it


@dataclass
class StateMachine:
    """Servo state with the transitions driven by commands and by frame outcomes.

    `stop_threshold` (0: never; the servo keeps following the reference) is the error norm below which the servo is
    CONVERGED, once it stayed below for
    `converge_frames` consecutive frames (one noisy dip does not stop the arm) with the estimate's `scatter` below
    `scatter_threshold` on each (a mean below the threshold is no evidence of the pose when the estimates it averages
    scatter by more than the threshold: the confident wrong answer of a biased fit) — or, for an estimate that image
    noise makes scatter by more, with the long window's mean below the threshold, its standard error below the threshold
    and its scatter at most `max_noise_ratio` × the one the noise predicts (`service.settling`); `resume_threshold`
    (> stop) is the norm above which a CONVERGED servo resumes: the frame's own norm (a disturbance is answered at
    once), or after a stop on the long window the norm of that window's mean (there a single frame's norm exceeds
    it routinely; a disturbance of norm d moves the mean past it within N · resume_threshold / d frames). LOST and
    CONVERGED servos go back to SERVOING by themselves, a LOST one after `confirm_frames` consecutive tracked
    frames.
    """

    stop_threshold: float
    resume_threshold: float
    converge_frames: int = 1
    confirm_frames: int = 3
    scatter_threshold: float = math.inf
    max_noise_ratio: float = 3.0
    state: ServoState = ServoState.IDLE
    _below: int = 0
    _tracked: int = 0
    _noisy_stop: bool = False  # CONVERGED on the long window's clause

    def __post_init__(self) -> None:
        if not (self.stop_threshold == 0.0 or 0.0 < self.stop_threshold < self.resume_threshold):
            raise ValueError(f"need stop_threshold 0 (never CONVERGED) or 0 < stop_threshold < resume_threshold, got "
                             f"{self.stop_threshold} and {self.resume_threshold}")
        if not (self.scatter_threshold > 0.0 or self.stop_threshold == 0.0):
            raise ValueError(f"scatter_threshold must be > 0, got {self.scatter_threshold}")
        if not self.max_noise_ratio > 0.0:
            raise ValueError(f"max_noise_ratio must be > 0, got {self.max_noise_ratio}")
        if self.converge_frames < 1:
            raise ValueError(f"converge_frames must be ≥ 1, got {self.converge_frames}")
        if self.confirm_frames < 1:
            raise ValueError(f"confirm_frames must be ≥ 1, got {self.confirm_frames}")

    # --- commands ---------------------------------------------------------------------------------------------
    def reference_set(self) -> ServoState:
        """A new reference image was accepted: READY (servoing restarts only on an explicit start)."""
        self.state = ServoState.READY
        return self.state

    def start(self) -> ServoState:
        if self.state == ServoState.IDLE:
            raise TransitionError("cannot start: no reference image is set (state IDLE); set a reference first")
        self.state = ServoState.SERVOING
        return self.state

    def resume(self) -> ServoState:
        """A restart resumes an active servo (SERVOING, CONVERGED or LOST when its process stopped) from what an
        earlier process persisted, an estimate not trusted yet: LOST (zero twist) until `confirm_frames`
        consecutive tracked frames confirm the re-acquisition, as after any loss."""
        if self.state == ServoState.IDLE:
            raise TransitionError("cannot resume: no reference image is set (state IDLE)")
        self.state, self._tracked, self._below = ServoState.LOST, 0, 0
        return self.state

    def stop(self) -> ServoState:
        if self.state == ServoState.IDLE:
            raise TransitionError("cannot stop: nothing to stop (state IDLE, no reference set)")
        self.state = ServoState.STOPPED
        return self.state

    def reset(self) -> ServoState:
        """Forget the reference: back to IDLE."""
        self.state = ServoState.IDLE
        return self.state

    # --- frames -----------------------------------------------------------------------------------------------
    @property
    def servo_active(self) -> bool:
        """True in the states where frames drive the servo (SERVOING, CONVERGED, LOST)."""
        return self.state in (ServoState.SERVOING, ServoState.CONVERGED, ServoState.LOST)

    def on_frame(self, outcome: FrameOutcome) -> ServoState:
        """Update the state from one frame's registration outcome (only while the servo is active)."""
        if not self.servo_active:
            return self.state
        settled = outcome.error_norm if outcome.settled_norm is None else outcome.settled_norm
        clean = settled < self.stop_threshold and outcome.scatter < self.scatter_threshold
        # the long window's clause matters only while not CONVERGED and the short one does not hold
        below = outcome.tracked and (clean or (self.state != ServoState.CONVERGED and self._noisy(outcome)))
        noisy_mean = self._noisy_stop and math.isfinite(outcome.noisy_norm)
        disturbance = outcome.noisy_norm if noisy_mean else outcome.error_norm
        self._below = self._below + 1 if below else 0
        self._tracked = self._tracked + 1 if outcome.tracked else 0
        if not outcome.tracked:
            self.state = ServoState.LOST
        elif self.state == ServoState.LOST and self._tracked < self.confirm_frames:
            pass  # re-acquired: hold still until the fit is confirmed
        elif self.state == ServoState.CONVERGED:
            if disturbance > self.resume_threshold:
                self.state = ServoState.SERVOING
        elif self._below >= self.converge_frames:
            self.state = ServoState.CONVERGED
            self._noisy_stop = not clean
        else:
            self.state = ServoState.SERVOING
        return self.state

    def _noisy(self, outcome: FrameOutcome) -> bool:
        """The long window's clause: its mean below the threshold, known to within it, a scatter the noise explains."""
        if not (outcome.noisy_norm < self.stop_threshold and outcome.standard_error < self.stop_threshold):
            return False
        ratio = outcome.noise_ratio() if callable(outcome.noise_ratio) else outcome.noise_ratio
        return ratio <= self.max_noise_ratio

    @property
    def moves(self) -> bool:
        """True when the twist computed for this frame is to be published (otherwise a zero twist is)."""
        return self.state == ServoState.SERVOING
