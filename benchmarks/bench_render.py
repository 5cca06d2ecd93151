"""Rendering speed of the free-flyer's Taichi ray caster: a 550×418 frame of the paper's saddle (goal ≤ 10 ms on
2 cores), against a float64 numpy ray caster with the same geometry and bilinear texture sampling, measured in the
same run.

Run: `.venv/bin/python benchmarks/bench_render.py [--frames N] [--json]`
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from ddvs_service.camera import Intrinsics
from ddvs_service.lie import pose, so3_exp
from sim.freeflyer import Appearance, render_view
from sim.surfaces import Surface, paper_saddle

GOAL_MS = 10.0


def numpy_render(surface: Surface, texture: np.ndarray, intr: Intrinsics, T_world_cam: np.ndarray) -> np.ndarray:
    """Baseline: vectorised float64 ray casting and bilinear sampling (mirrored repeat) in numpy."""
    u, v = np.meshgrid(np.arange(intr.width, dtype=float), np.arange(intr.height, dtype=float))
    m = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1) @ intr.K_inv.T
    depth = surface.intersect(T_world_cam, m)
    R, o = surface.camera_in_surface(T_world_cam)
    hit = np.isfinite(depth)
    local = o + (m[hit] @ R.T) * depth[hit, None]
    th, tw = texture.shape
    coords = []
    for x, n, extent in ((local[:, 0], tw, surface.extent[0]), (local[:, 1], th, surface.extent[1])):
        c = np.mod(x * n / extent + 0.5 * n, 2 * n)
        coords.append(np.where(c >= n, 2 * n - c, c) - 0.5)
    cu, cv = (np.clip(c, 0.0, n - 1.000001) for c, n in zip(coords, (tw, th)))
    u0, v0 = cu.astype(int), cv.astype(int)
    fu, fv = cu - u0, cv - v0
    top = texture[v0, u0] * (1 - fu) + texture[v0, u0 + 1] * fu
    bottom = texture[v0 + 1, u0] * (1 - fu) + texture[v0 + 1, u0 + 1] * fu
    image = np.zeros(u.size)
    image[hit] = top * (1 - fv) + bottom * fv
    return image.reshape(u.shape)


def timed(fn, frames: int, clock=time.perf_counter) -> float:
    """Median time of `fn(i)` in milliseconds on `clock` (wall by default, `time.process_time` for CPU time)."""
    times = []
    for i in range(frames):
        t0 = clock()
        fn(i)
        times.append(clock() - t0)
    return 1e3 * float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    intr = Intrinsics.centred(500.0, 550, 418)
    saddle = paper_saddle()
    texture = (np.random.default_rng(0).random((768, 1024)) * 255.0).astype(np.float32)
    T = pose(so3_exp([-0.1, -0.31, 1.04]), [0.17, -0.11, 0.01])
    noisy = Appearance(gain=(1.1, 0.05, 0.0, 0.0, 0.0, 0.0), bias=3.0, noise=2.0, seed=1)
    render_view(saddle, texture, intr, T)  # compile
    results = {
        "taichi_ms": timed(lambda i: render_view(saddle, texture, intr, T, index=i), args.frames),
        # CPU time summed over the threads: the work per frame, less sensitive than wall time to a shared machine.
        "taichi_cpu_ms": timed(
            lambda i: render_view(saddle, texture, intr, T, index=i), args.frames, time.process_time
        ),
        "taichi_illumination_noise_ms": timed(lambda i: render_view(saddle, texture, intr, T, noisy, i), args.frames),
        "numpy_float64_ms": timed(lambda i: numpy_render(saddle, texture, intr, T), max(5, args.frames // 10)),
    }
    results["speedup_vs_numpy"] = results["numpy_float64_ms"] / results["taichi_ms"]
    results["goal_ms"] = GOAL_MS
    results["meets_goal"] = results["taichi_ms"] <= GOAL_MS
    if args.json:
        print(json.dumps(results))
    else:
        for key, value in results.items():
            print(f"{key:>30}: {value:.2f}" if isinstance(value, float) else f"{key:>30}: {value}")


if __name__ == "__main__":
    main()
