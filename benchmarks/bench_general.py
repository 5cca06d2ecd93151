"""Tracking-frame time of the general registration (eq. (2), ρ* fixed: G, e, gain, bias) against the planar tracker,
same frames, same run: 200×150 ROI of the paper's saddle rendered along small consecutive camera motions.

Run: `.venv/bin/python benchmarks/bench_general.py [--frames 60]`. Prints median / p90 ms and iterations per frame
for both paths (timed frame by frame in turn), their ratio and the load average (the general frame includes the
information on ρ* it accumulates).
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from ddvs_service.camera import Intrinsics
from ddvs_service.lie import pose, so3_exp
from ddvs_service.registration.config import RegistrationConfig
from ddvs_service.registration.general_config import GeneralConfig
from ddvs_service.registration.general_tracker import GeneralTracker
from ddvs_service.registration.tracker import Tracker
from evaluation.pairs import ONE_GAIN_HUBER
from sim.freeflyer import render_view
from sim.ground_truth import ground_truth
from sim.surfaces import paper_saddle
from sim.textures import texture_path

INTR = Intrinsics.centred(500.0, 550, 418)
ROI = (175, 134, 200, 150)
PHOTO = str(texture_path("graf"))


def frames(n: int) -> list[np.ndarray]:
    """`n` renders along a slow approach (about 1/20 of the paper's start shrinking to 1/200)."""
    saddle = paper_saddle()
    tex = cv2.imread(PHOTO, cv2.IMREAD_GRAYSCALE).astype(np.float32)
    out = []
    for s in np.linspace(0.05, 0.005, n):
        T = pose(so3_exp(s * np.array([-0.1, -0.31, 1.04])), s * np.array([0.17, -0.11, 0.01]))
        out.append(render_view(saddle, tex, INTR, T)[0])
    return out


def timed(tracks: dict[str, Callable[[np.ndarray], Any]], images: list[np.ndarray]) -> dict[str, np.ndarray]:
    """ms per frame and iterations per frame of each tracker, frame by frame in turn (so that the VM's speed drift
    hits both alike)."""
    times: dict[str, list[float]] = {name: [] for name in tracks}
    iterations: dict[str, list[int]] = {name: [] for name in tracks}
    for image in images:
        for name, track in tracks.items():
            t0 = time.perf_counter()
            result = track(image)
            times[name].append(time.perf_counter() - t0)
            if not result.converged:
                raise RuntimeError(f"benchmark frame failed ({name}): {result.reason}")
            iterations[name].append(sum(result.iterations))
    return {name: np.c_[1e3 * np.array(times[name]), iterations[name]] for name in tracks}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=60)
    args = parser.parse_args()
    saddle = paper_saddle()
    tex = cv2.imread(PHOTO, cv2.IMREAD_GRAYSCALE).astype(np.float32)
    reference = render_view(saddle, tex, INTR, np.eye(4))[0]
    images = frames(args.frames)
    T0 = pose(so3_exp(0.05 * np.array([-0.1, -0.31, 1.04])), 0.05 * np.array([0.17, -0.11, 0.01]))
    planar = Tracker.prepare(reference, ROI, RegistrationConfig(**ONE_GAIN_HUBER))
    planar.reset(ground_truth(saddle, INTR, np.eye(4), T0).G)
    general = GeneralTracker.prepare(reference, ROI, GeneralConfig(base=RegistrationConfig(**ONE_GAIN_HUBER)))
    general.reset(planar.G)
    general.track(images[0])  # ρ* estimated here (multi-start, from the true G of the start), not timed
    tracks = {"planar Tracker": planar.track, "GeneralTracker": general.track}
    timed(tracks, images[:2])  # warm-up: compile every kernel variant
    load = os.getloadavg()[0]
    runs = timed(tracks, images)
    for name, run in runs.items():
        t = run[:, 0]
        print(f"{name:24s} median {np.median(t):6.2f} ms  p90 {np.percentile(t, 90):6.2f} ms  "
              f"iterations/frame {np.mean(run[:, 1]):.2f}")
    ratio = np.median(runs["GeneralTracker"][:, 0]) / np.median(runs["planar Tracker"][:, 0])
    print(f"ratio general/planar (median): {ratio:.2f}  (load average {load:.2f} before, "
          f"{os.getloadavg()[0]:.2f} after)")


if __name__ == "__main__":
    main()
