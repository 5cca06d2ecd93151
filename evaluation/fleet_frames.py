"""Rendered frame sequences for a fleet of robots, shared by the lock-step tests and `benchmarks/bench_batched.py`.

Robot `k` looks at a poster of the shipped texture `TEXTURES[k % 4]` 0.7 m ahead (`sim.planar_scene`, the fleet
benchmark's 320×240 camera, f = 420 px): its reference is the view from the reference pose, its template the
centred 200×150 ROI, and its frames the views along a path that starts at a random pose within ±10 mm / ±0.9° and
moves by a random small twist per frame (≤ 1 mm, ≤ 0.06°: a servo's motion between frames at 30 Hz), so that
every robot's tracker needs its own number of iterations. `start` is the true homography of the first frame's
predecessor, where a tracker starts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.lie import se3_exp, so3_exp
from sim.planar_scene import POSTER_BLUR_SIGMA, PlanarScene
from sim.textures import load_texture

TEXTURES = ("boat", "graf", "notredame", "wall")
WIDTH, HEIGHT, FOCAL = 320, 240, 420.0
CAMERA = Intrinsics(FOCAL, FOCAL, (WIDTH - 1) / 2, (HEIGHT - 1) / 2, WIDTH, HEIGHT)
TEMPLATE = (200, 150)


@dataclass(frozen=True)
class RobotFrames:
    """One robot's reference, ROI `(x, y, w, h)`, true starting homography and frames (grey float32)."""

    reference: NDArray[np.float32]
    roi: tuple[int, int, int, int]
    start: NDArray[np.float64]
    frames: list[NDArray[np.float32]]


def robot_frames(k: int, n_frames: int) -> RobotFrames:
    """Robot `k`'s sequence of `n_frames` frames (module docstring); the same for the same `k`."""
    rng = np.random.default_rng(1000 + k)
    scene = PlanarScene(CAMERA, load_texture(TEXTURES[k % len(TEXTURES)], POSTER_BLUR_SIGMA), depth=0.7)
    pose = np.eye(4)
    pose[:3, :3] = so3_exp(rng.uniform(-0.015, 0.015, 3))
    pose[:3, 3] = rng.uniform(-0.01, 0.01, 3)
    start = scene.homography(pose[:3, :3], pose[:3, 3])
    frames = []
    for _ in range(n_frames):
        pose = pose @ se3_exp(np.r_[rng.uniform(-0.001, 0.001, 3), rng.uniform(-0.001, 0.001, 3)])
        frames.append(_grey(scene.render(scene.homography(pose[:3, :3], pose[:3, 3]))))
    w, h = TEMPLATE
    roi = ((WIDTH - w) // 2, (HEIGHT - h) // 2, w, h)
    return RobotFrames(_grey(scene.render()), roi, start, frames)


def _grey(image: NDArray[np.float32]) -> NDArray[np.float32]:
    """A camera's 8-bit grey levels, as float32."""
    return np.clip(np.round(image), 0, 255).astype(np.float32)
