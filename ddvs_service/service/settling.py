"""The figures the stop decision compares (`state.StateMachine`), over the last tracked frames' control errors ε̄_k.

Two windows of the same frames (an untracked frame empties both):
- the short one, the last `settle_frames` (10): the norm of the mean error ‖ē‖ and the scatter of the errors about
  it, s = √(mean_k ‖ε̄_k − ē‖²) (inf while the window is not full). A clean estimate stops on it: ‖ē‖ below the
  stop threshold and s below `scatter_factor` × it.
- the long one, the last `noise_frames` (90), for an estimate that image noise makes scatter by more than that (a
  scene dimmed 3× under noise and JPEG: README, Robustness): the norm of its mean, the standard error of that mean
  s/√N (the mean is known to within it when the frames' errors are independent draws about it) and the ratio of s
  to the scatter the image noise alone predicts, p = √tr(A Σ̄ Aᵀ), Σ̄ the window's mean of the registration's Gauss-Newton
  covariances of `G` and `e` (`RegistrationResult.covariance`) and A the law's Jacobian at the newest frame
  (`error_jacobian`). The stop needs all three: the mean below the threshold, known to within it, and a scatter
  the noise explains — a fit that wanders (a biased estimate under an occluder, a servo that oscillates) scatters
  more than its noise predicts, and over a longer window more than over a short one, so its mean is not known to
  within the threshold. The Gauss-Newton covariance understates the scatter of an unbiased noisy estimate (noise
  after JPEG and blur is not independent from pixel to pixel; robust weights): the bound on the ratio,
  `noise_ratio`, leaves room for that (README, Robustness: the measured ratios). A steady bias is not seen: an
  estimate biased by several thresholds whose scatter is the noise's stops where its mean reads zero.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from ddvs_service.control.law import ControlLaw

F64 = NDArray[np.float64]
NOT_SETTLED = (float("nan"), math.inf, float("nan"), math.inf, math.inf)
STEP = 1e-6  # forward-difference step on `G`'s and `e`'s entries (the third row's: against a denominator of ~1)


def error_jacobian(law: ControlLaw, G: F64, e: F64, rho: float) -> F64:
    """A = ∂ε̄/∂[vec(G), e] (6×12, `G`'s entries row-major, then the epipole's) of the law's error at (`G`, `e`,
    `ρ*`), by forward differences."""
    base = law.error(G, e, rho)
    x = np.concatenate([np.asarray(G, dtype=np.float64).reshape(9), np.asarray(e, dtype=np.float64)])
    steps = np.eye(12) * STEP
    return np.stack([(law.error((x + d)[:9].reshape(3, 3), (x + d)[9:], rho) - base) / STEP for d in steps], axis=1)


class SettleWindow:
    """The last tracked frames' control errors and registration covariances (module docstring). `threshold`: the
    stop threshold; the long window's predicted scatter (9 evaluations of the law) is computed only on frames where
    its mean and standard error are both below it, the other two conditions of that clause."""

    def __init__(self, settle_frames: int, noise_frames: int, threshold: float) -> None:
        self.threshold = threshold
        self._errors: deque[F64] = deque()
        self._covariances: deque[F64 | None] = deque()
        self.resize(settle_frames, noise_frames)

    def resize(self, settle_frames: int, noise_frames: int) -> None:
        """New window lengths, keeping the newest frames."""
        self.settle_frames, self.noise_frames = settle_frames, noise_frames
        self._errors = deque(self._errors, maxlen=max(settle_frames, noise_frames))
        self._covariances = deque(self._covariances, maxlen=max(settle_frames, noise_frames))

    def clear(self) -> None:
        self._errors.clear()
        self._covariances.clear()

    def add(self, error: F64 | None, covariance: F64 | None = None,
            jacobian: Callable[[], F64] | None = None) -> tuple[float, float, float, float, float]:
        """Add a tracked frame's control error and its registration's covariance of [vec(G), e] (None: unknown;
        `RegistrationResult.covariance`), or None for an untracked frame (which empties the window). `jacobian`:
        the newest frame's `error_jacobian`, used for the whole long window (its mean below the threshold: the
        camera is near the goal, where A changes little). Returns the figures `StateMachine` compares: (‖ē‖, s) of
        the short window (s inf while it is not full), (‖ē‖, s/√N, s/p) of the long one (nan, inf, inf while it is
        not full or a frame's covariance is unknown; s/p inf unless ‖ē‖ and s/√N are below the threshold);
        `NOT_SETTLED` for an untracked frame."""
        if error is None:
            self.clear()
            return NOT_SETTLED
        self._errors.append(np.asarray(error, dtype=np.float64))
        self._covariances.append(covariance)
        errors = np.asarray(self._errors)
        short_norm, scatter = _mean_and_scatter(errors[-self.settle_frames:])
        if len(errors) < self.settle_frames:
            scatter = math.inf
        covariances = list(self._covariances)[-self.noise_frames:]
        if len(errors) < self.noise_frames or any(c is None for c in covariances):
            return short_norm, scatter, float("nan"), math.inf, math.inf
        norm, s = _mean_and_scatter(errors[-self.noise_frames:])
        standard_error = s / math.sqrt(self.noise_frames)
        ratio = math.inf
        if norm < self.threshold and standard_error < self.threshold and jacobian is not None:
            A = jacobian()
            predicted = float(np.trace(A @ np.mean(np.asarray(covariances), axis=0) @ A.T))
            ratio = s / math.sqrt(predicted) if predicted > 0.0 else math.inf
        return short_norm, scatter, norm, standard_error, ratio


def _mean_and_scatter(errors: F64) -> tuple[float, float]:
    """‖mean‖ and the RMS deviation from the mean of the rows of `errors`."""
    mean = errors.mean(axis=0)
    return float(np.linalg.norm(mean)), float(np.sqrt(np.mean(np.sum((errors - mean) ** 2, axis=1))))
