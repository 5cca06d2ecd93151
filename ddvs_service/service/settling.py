"""The figures the stop decision compares (`state.StateMachine`), over the last tracked frames' control errors ε̄_k.

Two windows of the same frames (an untracked frame empties both):
- the short one, the last `settle_frames` (10): the norm of the mean error ‖ē‖ and the scatter of the errors about
  it, s = √(mean_k ‖ε̄_k − ē‖²) (inf while the window is not full). A clean estimate stops on it: ‖ē‖ below the
  stop threshold and s below `scatter_factor` × it.
- the long one, the last `noise_frames` (90), for an estimate that image noise makes scatter by more than that (a
  scene dimmed 3× under noise and JPEG: results/robustness): the norm of its mean, the standard error of that mean
  s/√N (the mean is known to within it when the frames' errors are independent draws about it) and the ratio of s
  to the scatter the image noise alone predicts, p = √tr(A Σ̄ Aᵀ), Σ̄ the window's mean of the registration's Gauss-Newton
  covariances of `G` and `e` (`RegistrationResult.covariance`) and A the law's Jacobian at the newest frame
  (`error_jacobian`). The stop needs all three: the mean below the threshold, known to within it, and a scatter
  the noise explains — a fit that wanders (a biased estimate under an occluder, a servo that oscillates) scatters
  more than its noise predicts, and over a longer window more than over a short one, so its mean is not known to
  within the threshold. The Gauss-Newton covariance understates the scatter of an unbiased noisy estimate (noise
  after JPEG and blur is not independent from pixel to pixel; robust weights): the bound on the ratio,
  `noise_ratio`, leaves room for that (results/robustness: the measured ratios). A steady bias is not seen: an
  estimate biased by several thresholds whose scatter is the noise's stops where its mean reads zero.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from ddvs_service.control.law import ControlLaw

F64 = NDArray[np.float64]
Figures = tuple[float, float, float, float, float | Callable[[], float]]
NOT_SETTLED: Figures = (float("nan"), math.inf, float("nan"), math.inf, math.inf)
STEP = 1e-6  # forward-difference step on `G`'s and `e`'s entries (the third row's: against a denominator of ~1)


def error_jacobian(law: ControlLaw, G: F64, e: F64, rho: float) -> F64:
    """A = ∂ε̄/∂[vec(G), e] (6×12, `G`'s entries row-major, then the epipole's) of the law's error at (`G`, `e`,
    `ρ*`), by forward differences."""
    base = law.error(G, e, rho)
    x = np.concatenate([np.asarray(G, dtype=np.float64).reshape(9), np.asarray(e, dtype=np.float64)])
    steps = np.eye(12) * STEP
    return np.stack([(law.error((x + d)[:9].reshape(3, 3), (x + d)[9:], rho) - base) / STEP for d in steps], axis=1)


class _Sums:
    """Running sums over the newest `length` frames of a `SettleWindow`'s buffers: Σε̄_k, Σ‖ε̄_k‖², and with
    `covariances` ΣΣ_k and the number of frames whose covariance is unknown (only the long window's figures use them)
    (a frame costs one add and one subtract, not a pass over the window; the rounding they accumulate, ~1e-14 per
    frame on errors of norm ≤ 2, stays far below the thresholds)."""

    def __init__(self, length: int, covariances: bool) -> None:
        self.length, self.covariances = length, covariances
        self.clear()

    def clear(self) -> None:
        self.error = np.zeros(6)
        self.square = 0.0
        self.covariance = np.zeros((12, 12))
        self.unknown = 0

    def update(self, sign: int, error: F64, square: float, covariance: F64 | None) -> None:
        """A frame enters (`sign` 1) or leaves (−1) the window: its error, ‖error‖² and covariance (None: unknown)."""
        self.error += sign * error
        self.square += sign * square
        if not self.covariances:
            return
        if covariance is None:
            self.unknown += sign
        else:
            self.covariance += sign * covariance

    def mean_and_scatter(self) -> tuple[float, float]:
        """‖mean‖ and the RMS deviation from the mean of the window's errors (full window)."""
        mean = self.error / self.length
        mean_square = float(mean @ mean)
        return math.sqrt(mean_square), math.sqrt(max(self.square / self.length - mean_square, 0.0))


class SettleWindow:
    """The last tracked frames' control errors and registration covariances (module docstring): a ring buffer of
    the longer window's length and running sums over each window. `threshold`: the stop threshold; the long window's
    predicted scatter (the law evaluated 13 times) is computed only on frames where its mean and standard error are
    both below it, the other two conditions of that clause, and only when asked for (`add`)."""

    def __init__(self, settle_frames: int, noise_frames: int, threshold: float) -> None:
        self.threshold = threshold
        self._lengths: tuple[int, int] | None = None
        self.resize(settle_frames, noise_frames)

    def resize(self, settle_frames: int, noise_frames: int) -> None:
        """New window lengths; the window starts empty when they changed (otherwise nothing changes)."""
        if (settle_frames, noise_frames) == self._lengths:
            return
        self._lengths = (settle_frames, noise_frames)
        self.settle_frames, self.noise_frames = settle_frames, noise_frames
        length = max(settle_frames, noise_frames)
        self._errors = np.zeros((length, 6))
        self._squares = [0.0] * length  # ‖ε̄_k‖², computed once per frame
        self._covariances: list[F64 | None] = [None] * length
        self._short, self._long = _Sums(settle_frames, covariances=False), _Sums(noise_frames, covariances=True)
        self.clear()

    def clear(self) -> None:
        self._count = self._next = 0  # frames in the buffer, slot of the next frame
        self._short.clear()
        self._long.clear()

    def add(self, error: F64 | None, covariance: F64 | None = None,
            jacobian: Callable[[], F64] | None = None) -> Figures:
        """Add a tracked frame's control error and its registration's covariance of [vec(G), e] (None: unknown;
        `RegistrationResult.covariance`), or None for an untracked frame (which empties the window). `jacobian`:
        the newest frame's `error_jacobian`, used for the whole long window (its mean below the threshold: the
        camera is near the goal, where A changes little). Returns the figures `StateMachine` compares: (‖ē‖, s) of
        the short window (s inf while it is not full), (‖ē‖, s/√N, s/p) of the long one (nan, inf, inf while it is
        not full or a frame's covariance is unknown; s/p inf unless ‖ē‖ and s/√N are below the threshold, and then a
        function that computes it when called, as it costs 13 evaluations of the law and the stop decision needs it
        only while the short window does not settle); `NOT_SETTLED` for an untracked frame."""
        if error is None:
            self.clear()
            return NOT_SETTLED
        length = len(self._errors)
        error = np.asarray(error, dtype=np.float64)
        square = float(error @ error)
        for sums in (self._short, self._long):
            if self._count >= sums.length:  # the frame `sums.length` frames ago leaves that window
                old = (self._next - sums.length) % length
                sums.update(-1, self._errors[old], self._squares[old], self._covariances[old])
            sums.update(1, error, square, covariance)
        self._errors[self._next], self._covariances[self._next] = error, covariance
        self._squares[self._next] = square
        self._next = (self._next + 1) % length
        self._count = min(self._count + 1, length)
        short_norm, scatter = self._short.mean_and_scatter() if self._count >= self.settle_frames else (
            float(np.linalg.norm(self._short.error)) / self._count, math.inf)
        if self._count < self.noise_frames or self._long.unknown:
            return short_norm, scatter, float("nan"), math.inf, math.inf
        norm, s = self._long.mean_and_scatter()
        standard_error = s / math.sqrt(self.noise_frames)
        if not (norm < self.threshold and standard_error < self.threshold and jacobian is not None):
            return short_norm, scatter, norm, standard_error, math.inf
        covariance = self._long.covariance / self.noise_frames
        evaluate = jacobian

        def ratio() -> float:
            A = evaluate()
            predicted = float(np.trace(A @ covariance @ A.T))
            return s / math.sqrt(predicted) if predicted > 0.0 else math.inf

        return short_norm, scatter, norm, standard_error, ratio
