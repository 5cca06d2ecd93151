"""Imaging conditions of a real camera, as composable transforms of rendered frames (robustness experiments).

Each condition is a frozen dataclass called as `condition(image, ctx) -> image` on a float32 grey frame (levels
0…255, the plant's noise-free rendering) with the frame's `FrameContext`; `apply(conditions, image, ctx)` runs them
in order and quantises the result to 8 bits as a camera does. Conditions are deterministic: anything random is
seeded by the condition's `seed` and the frame index. Image coordinates: 0-based pixel centres, u right, v down;
`ctx.roi = (x, y, w, h)` is the template's box in the reference image (the image region the servo registers once
converged). Times in seconds, from the start of the run.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from sim.textures import load_texture

F32 = NDArray[np.float32]
Roi = tuple[int, int, int, int]


@dataclass(frozen=True)
class FrameContext:
    """What a condition may know about a frame: `index` (0 first), `time` (s), the template box `roi` in reference
    pixels and `motion_px` = (du, dv), the image motion of the control point since the previous frame (pixels,
    from the plant's ground truth; zeros on the first frame)."""

    index: int
    time: float
    roi: Roi
    motion_px: tuple[float, float] = (0.0, 0.0)


class Condition(Protocol):
    def __call__(self, image: F32, ctx: FrameContext) -> F32: ...


def apply(conditions: Sequence[Condition], image: F32, ctx: FrameContext) -> F32:
    """`image` through each condition in order, then rounded and clipped to 0…255 (an 8-bit camera)."""
    out = np.asarray(image, dtype=np.float32)
    for condition in conditions:
        out = condition(out, ctx)
    return np.clip(np.rint(out), 0.0, 255.0).astype(np.float32)


def _rng(seed: int, index: int) -> np.random.Generator:
    return np.random.default_rng([seed, index])


def _grid(image: F32) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    h, w = image.shape
    return np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))


@dataclass(frozen=True)
class Dimming:
    """Global gain falling linearly from 1 to `factor` over `duration_s`, then held."""

    factor: float = 1.0 / 3.0
    duration_s: float = 10.0

    def __call__(self, image: F32, ctx: FrameContext) -> F32:
        s = min(max(ctx.time / self.duration_s, 0.0), 1.0)
        return image * np.float32(1.0 + (self.factor - 1.0) * s)


@dataclass(frozen=True)
class GainGradient:
    """A spatial gain rising linearly from `low` to `high` across the image along a direction at angle
    `angle_deg + 360° · t / turn_period_s` from the u axis (static when `turn_period_s` is 0)."""

    low: float = 0.6
    high: float = 1.4
    turn_period_s: float = 20.0
    angle_deg: float = 0.0

    def __call__(self, image: F32, ctx: FrameContext) -> F32:
        turn = 0.0 if self.turn_period_s == 0.0 else 2.0 * np.pi * ctx.time / self.turn_period_s
        a = np.radians(self.angle_deg) + turn
        u, v = _grid(image)
        h, w = image.shape
        d = (u - 0.5 * (w - 1)) * np.cos(a) + (v - 0.5 * (h - 1)) * np.sin(a)
        half = 0.5 * (abs(np.cos(a)) * (w - 1) + abs(np.sin(a)) * (h - 1))
        gain = 0.5 * (self.low + self.high) + 0.5 * (self.high - self.low) * d / half
        return (image * gain).astype(np.float32)


@dataclass(frozen=True)
class Specular:
    """An additive Gaussian highlight (`amplitude` grey levels, standard deviation `sigma_px`) sweeping across the
    template box diagonally, from outside its top-left corner to outside its bottom-right one in `sweep_s`, then
    back (a triangle wave)."""

    amplitude: float = 150.0
    sigma_px: float = 12.0
    sweep_s: float = 10.0

    def __call__(self, image: F32, ctx: FrameContext) -> F32:
        x, y, w, h = ctx.roi
        phase = (ctx.time / self.sweep_s) % 2.0
        s = phase if phase <= 1.0 else 2.0 - phase
        cu, cv = x - 0.25 * w + 1.5 * w * s, y - 0.25 * h + 1.5 * h * s
        u, v = _grid(image)
        blob = self.amplitude * np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2.0 * self.sigma_px**2))
        return (image + blob).astype(np.float32)


@cache
def _occluder_texture(name: str, shape: tuple[int, int]) -> F32:
    return np.asarray(cv2.resize(load_texture(name), (shape[1], shape[0]), interpolation=cv2.INTER_AREA), np.float32)


@dataclass(frozen=True)
class Occluder:
    """A foreign textured object (texture `texture`, another scene than the target's) entering from the image's
    left edge at `start_frame`, sliding in over `enter_frames` until it covers the left `fraction` of the template
    box (full image height), then staying; with `leave_after` > 0 frames it slides out again the same way and
    re-enters `leave_after` frames later (one that comes and goes)."""

    fraction: float = 0.3
    start_frame: int = 100
    enter_frames: int = 15
    leave_after: int = 0
    texture: str = "boat"

    def covered_until(self, ctx: FrameContext) -> int:
        """Column (exclusive) the occluder covers up to in this frame (0: not in view)."""
        x, _, w, _ = ctx.roi
        k = ctx.index - self.start_frame
        if k < 0:
            return 0
        n = self.enter_frames
        if self.leave_after > 0:  # cycle: enter (n), stay, leave (n), stay away
            k %= 2 * (n + self.leave_after)
            if k >= n + self.leave_after:
                k = max(0, 2 * n + self.leave_after - k)
        return round((x + self.fraction * w) * min(k / n, 1.0))

    def __call__(self, image: F32, ctx: FrameContext) -> F32:
        cols = self.covered_until(ctx)
        if cols <= 0:
            return image
        out = image.copy()
        tex = _occluder_texture(self.texture, image.shape)
        out[:, :cols] = tex[:, image.shape[1] - cols :]
        return out


@dataclass(frozen=True)
class Noise:
    """Additive Gaussian sensor noise of standard deviation `sigma` grey levels (seeded per frame)."""

    sigma: float = 4.0
    seed: int = 0

    def __call__(self, image: F32, ctx: FrameContext) -> F32:
        return (image + self.sigma * _rng(self.seed, ctx.index).standard_normal(image.shape)).astype(np.float32)


@dataclass(frozen=True)
class MotionBlur:
    """Blur along the frame's image motion: a line kernel of length `exposure` × `ctx.motion_px` (the control
    point's motion since the previous frame; a shutter open for that fraction of the frame period). The motion of
    the control point stands for the whole frame's."""

    exposure: float = 1.0

    def __call__(self, image: F32, ctx: FrameContext) -> F32:
        du, dv = (self.exposure * m for m in ctx.motion_px)
        length = float(np.hypot(du, dv))
        if length < 0.5:
            return image
        n = int(np.ceil(length)) | 1
        kernel = np.zeros((n, n), dtype=np.float32)
        c = n // 2
        for s in np.linspace(-0.5, 0.5, 4 * n):
            kernel[round(c + s * dv), round(c + s * du)] += 1.0
        return np.asarray(cv2.filter2D(image, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REFLECT), np.float32)


@dataclass(frozen=True)
class Jpeg:
    """JPEG compression at `quality` (OpenCV's encoder) and decoding, as a compressed camera stream."""

    quality: int = 70

    def __call__(self, image: F32, ctx: FrameContext) -> F32:
        ok, data = cv2.imencode(".jpg", np.clip(np.rint(image), 0, 255).astype(np.uint8),
                                [cv2.IMWRITE_JPEG_QUALITY, self.quality])
        decoded = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE) if ok else None
        if decoded is None:
            raise RuntimeError("OpenCV could not JPEG-encode and decode the frame")
        return decoded.astype(np.float32)
