"""Integrity of a tracked fit: is a converged frame plausible given the frames accepted before it?

A Gauss-Newton fit can converge (its steps shrink) on a wrong optimum, e.g. when a foreign object covers part of
the template: with the robust scale σ re-estimated from the median residual of every iteration, the occluder's
pixels raise σ, gain weight and drag the fit; the inlier ratio (|r| ≤ 4.685 σ) is then measured against a σ that
fits whatever the frame shows and stays near 1. Two measures keep the estimate honest:

- an anchored scale: `anchor` is the median of the inliers' scales measured on the last `anchor_frames` accepted
  frames (grey levels, never below `min_anchor`). A frame's inliers' scale is its robust scale 1.4826 · median |r|
  (before any cap) corrected for its outliers (`inlier_scale`): with a fraction ε of the pixels beyond the cut-off
  the median of all |r| is the `0.5 / (1 − ε)` quantile of the inliers' |r|, not their median (an occluder over a
  quarter of the ROI inflates the uncorrected σ by about 1.4×). (An 8-bit camera's frames differ from the reference
  by quantisation, noise and interpolation: after frames identical to the reference, one turned 3° measures 7 grey
  levels of interpolation error on a sharp texture, and must not look implausible), and defined only once
  `min_frames` frames were accepted (the first frame after a reference taken from the stream is the reference
  itself, σ at the engine's floor; the next ones, on a sharp texture, measure several grey levels of interpolation
  error). The engine's σ is capped at `scale_cap × anchor` (`PlanarRegistration.run(scale_cap=…)`), so residuals far
  beyond the good frames' stay outliers: their weight is bounded (Huber) or zero (Tukey), and the inlier ratio
  counts pixels consistent with the good frames. Gradual changes (light, blur, a slowly entering occluder) move the
  anchor with them. The cap is below the anchor (`scale_cap` 0.6: Tukey's cut-off at 2.8 inlier σ, which keeps
  99.5 % of Gaussian inliers): a foreign object's pixels that fall within the cut-off pull the fit, and on a dimmed
  scene (gains ≈ 3) their gradients, multiplied by the gain, outweigh the target's; `tests/test_integrity.py` and the
  docs/results/robustness.md give the measurements (a biased fit at the frame's own σ, and the saddle's hard
  combination). A looser cap (2×) let the weights follow a sweeping highlight or an occluder.
- the scale test is coarse (`scale_jump` 4): on a texture with large uniform regions a misregistered fit keeps many
  pixels near the noise level, and a correct fit under a 43 % occluder measures 1.5–2.4× the anchor, so the two
  overlap; the service's error guard (`service.guard`) is the finer test of a jump.
- plausibility of a converged frame (`judge`): its own scale at most `scale_jump × anchor`, and the ROI corners
  within `max(corner_jump_fraction × ROI size, min_corner_jump_px)` pixels of where the frame started
  (the constant-velocity prediction or the last good estimate): consecutive frames at 30 Hz move a few pixels and
  the prediction absorbs most of it (a dropped frame or an irregular stream adds a period or more of motion: up to
  11 px at the saturated rotation, f = 420 px): a larger jump is a different optimum.

- support (`inlier_floor`): the engine refuses a fit with fewer than `min_inlier_ratio` (0.5) of the ROI's pixels
  inliers. Beyond half the pixels hidden the median |r| is an occluder's residual: the frame's robust scale then
  measures the occluder (a right fit 0.1 px from the truth under a 57 % occluder: 28 grey levels against an anchor
  of 4.1), and neither it nor the inliers' scale derived from it says anything about the fit. The inlier ratio at
  the capped σ still does (pixels within 2.8 σ of the good frames' noise). So a tracked frame may keep fewer than
  half the pixels when its support fell gradually: at least the last accepted frame's inlier ratio less
  `max_support_drop`, never below `min_support` (an occluder sliding over the template takes a few hundredths per
  frame; a wrong optimum loses its support at once). The scale test then does not apply, and such a frame does
  not move the anchor. A fit that lost more at once stays refused below `min_inlier_ratio`, as before.

Before the anchor is defined only the corner test applies. The anchor survives a re-acquisition (the reference, and
so the scale of a good fit, is the same), and so does the last accepted frame's support.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from statistics import NormalDist, median

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
Roi = tuple[int, int, int, int]


@dataclass(frozen=True)
class IntegrityConfig:
    """Thresholds of the integrity check (module docstring). Scales are ratios to the anchor, jumps in
    full-resolution pixels or fractions of the ROI's larger side."""

    anchor_frames: int = 15
    min_frames: int = 3
    min_anchor: float = 3.0
    scale_cap: float = 0.6
    scale_jump: float = 4.0
    corner_jump_fraction: float = 0.25
    min_corner_jump_px: float = 12.0
    max_support_drop: float = 0.1
    min_support: float = 0.3

    def __post_init__(self) -> None:
        if not (1 <= self.min_frames <= self.anchor_frames and self.min_anchor > 0.0):
            raise ValueError(f"need 1 ≤ min_frames ≤ anchor_frames and min_anchor > 0, got {self.min_frames}, "
                             f"{self.anchor_frames}, {self.min_anchor}")
        if not 0.0 < self.scale_cap <= self.scale_jump:
            raise ValueError(f"need 0 < scale_cap ≤ scale_jump, got {self.scale_cap} and {self.scale_jump}")
        if not (self.corner_jump_fraction > 0.0 and self.min_corner_jump_px > 0.0):
            raise ValueError("corner_jump_fraction and min_corner_jump_px must be > 0")
        if not (0.0 <= self.max_support_drop < 1.0 and 0.0 < self.min_support <= 1.0):
            raise ValueError(f"need 0 ≤ max_support_drop < 1 and 0 < min_support ≤ 1, got {self.max_support_drop} "
                             f"and {self.min_support}")


class Integrity:
    """The anchored scale and the plausibility test of one tracked template `roi = (x, y, w, h)`."""

    def __init__(self, roi: Roi, config: IntegrityConfig = IntegrityConfig()) -> None:
        x, y, w, h = roi
        self.config = config
        self._corners = np.array([[x, x + w - 1, x + w - 1, x], [y, y, y + h - 1, y + h - 1], [1.0, 1.0, 1.0, 1.0]])
        self._max_jump = max(config.corner_jump_fraction * max(w, h), config.min_corner_jump_px)
        self._scales: deque[float] = deque(maxlen=config.anchor_frames)
        self._anchor: float | None = None  # `anchor`, updated when a frame is accepted (read twice per frame)
        self._support: float | None = None  # the last accepted frame's inlier ratio

    @property
    def anchor(self) -> float | None:
        """Median robust scale of the last accepted frames (grey levels), None before `min_frames` were."""
        return self._anchor

    @property
    def scale_cap(self) -> float | None:
        """The largest σ the engine may use on the next frame (None: no cap yet)."""
        anchor = self.anchor
        return None if anchor is None else self.config.scale_cap * anchor

    def inlier_floor(self, min_inlier_ratio: float) -> float:
        """The smallest inlier ratio the next tracked frame may have, the engine's `min_inlier_ratio` lowered to
        the last accepted frame's support less `max_support_drop` (not below `min_support`; module docstring)."""
        if self._support is None or self.anchor is None:
            return min_inlier_ratio
        return min(min_inlier_ratio, max(self._support - self.config.max_support_drop, self.config.min_support))

    def judge(self, start: F64, G: F64, frame_scale: float, inlier_ratio: float = 1.0) -> str:
        """Why the converged fit `G` of a frame that started from `start` is implausible ("" when it is not). With
        at most `MEASURED_SUPPORT` of the pixels inliers its scale measures the occluder and is not tested: under
        the cap the test can fail only there anyway (more than half the pixels within the cut-off `4.685 ×
        scale_cap` put the scale below 4.2 × the anchor), and `inlier_floor` stands for it."""
        anchor = self.anchor
        if anchor is not None and (inlier_ratio > MEASURED_SUPPORT
                                   and not frame_scale <= self.config.scale_jump * anchor):
            return (f"implausible fit: residual scale {frame_scale:.2f} is more than {self.config.scale_jump:g}× the "
                    f"last good frames' {anchor:.2f} grey levels")
        jump = corner_distance(start, G, self._corners)
        if not jump <= self._max_jump:
            return (f"implausible fit: the template's corners jumped {jump:.1f} px from the frame's start (at most "
                    f"{self._max_jump:.1f} px between frames)")
        return ""

    def accept(self, frame_scale: float, inlier_ratio: float = 1.0) -> None:
        """Add an accepted frame's inliers' scale (`inlier_scale` of its robust scale and inlier ratio) to the
        anchor, unless its median is not an inlier's (`MEASURED_SUPPORT`), and keep its inlier ratio as the support
        of the next frame."""
        self._support = inlier_ratio
        scale = inlier_scale(frame_scale, inlier_ratio)
        if inlier_ratio > MEASURED_SUPPORT and math.isfinite(scale) and scale > 0.0:
            self._scales.append(scale)
            if len(self._scales) >= self.config.min_frames:
                self._anchor = max(median(self._scales), self.config.min_anchor)


_STANDARD_NORMAL = NormalDist()
_HALF_NORMAL_MEDIAN = _STANDARD_NORMAL.inv_cdf(0.75)  # median of |N(0, 1)|: 1 / 1.4826
MAX_QUANTILE = 0.95  # the correction stops at half the pixels beyond the cut-off (an outlier share ≥ 47 %)
MEASURED_SUPPORT = 0.5 / MAX_QUANTILE  # from this inlier ratio down the median |r| does not measure the inliers


def inlier_scale(frame_scale: float, inlier_ratio: float) -> float:
    """The scale of a frame's inliers (grey levels) from its robust scale `1.4826 · median |r|` over every pixel and
    the fraction `inlier_ratio` within the cut-off: the overall median is the `q = 0.5 / inlier_ratio` quantile of
    the inliers' |r| (Gaussian: `σ Φ⁻¹((1 + q) / 2)`), so `σ = frame_scale · Φ⁻¹(0.75) / Φ⁻¹((1 + q) / 2)`."""
    if not (math.isfinite(frame_scale) and 0.0 < inlier_ratio <= 1.0):
        return frame_scale
    q = min(0.5 / inlier_ratio, MAX_QUANTILE)
    return float(frame_scale * _HALF_NORMAL_MEDIAN / _STANDARD_NORMAL.inv_cdf(0.5 + 0.5 * q))


def corner_distance(A: F64, B: F64, corners: F64) -> float:
    """Largest distance (pixels) between the images of the homogeneous `corners` (3×n) under `A` and under `B`."""
    a, b = A @ corners, B @ corners
    d = a[:2] / a[2] - b[:2] / b[2]
    return float(np.sqrt(np.add.reduce(d * d, axis=0)).max())  # np.linalg.norm(d, axis=0)'s arithmetic
