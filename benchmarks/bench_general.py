"""Tracking-frame time of the general registration (eq. (2), ρ* fixed: G, e, gain, bias) against the planar tracker,
same frames, same run: 200×150 ROI of the paper's saddle rendered along small consecutive camera motions.

Run: `.venv/bin/python benchmarks/bench_general.py [--frames 60]`. Prints median / p90 ms per frame for both paths,
and their ratio (the general frame includes its pass that accumulates the information on ρ*).
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np

from ddvs_service.camera import Intrinsics
from ddvs_service.datasets import dataset_image
from ddvs_service.lie import pose, so3_exp
from ddvs_service.registration.general_tracker import GeneralTracker
from ddvs_service.registration.tracker import Tracker
from sim.freeflyer import render_view
from sim.ground_truth import ground_truth
from sim.surfaces import paper_saddle

INTR = Intrinsics.centred(500.0, 550, 418)
ROI = (175, 134, 200, 150)
PHOTO = str(dataset_image("oxford/graf/img1.png"))


def frames(n: int) -> list[np.ndarray]:
    """`n` renders along a slow approach (about 1/20 of the paper's start shrinking to 1/200)."""
    saddle = paper_saddle()
    tex = cv2.imread(PHOTO, cv2.IMREAD_GRAYSCALE).astype(np.float32)
    out = []
    for s in np.linspace(0.05, 0.005, n):
        T = pose(so3_exp(s * np.array([-0.1, -0.31, 1.04])), s * np.array([0.17, -0.11, 0.01]))
        out.append(render_view(saddle, tex, INTR, T)[0])
    return out


def timed(track, images: list[np.ndarray]) -> np.ndarray:
    times = []
    for image in images:
        t0 = time.perf_counter()
        result = track(image)
        times.append(time.perf_counter() - t0)
        if not result.converged:
            raise RuntimeError(f"benchmark frame failed: {result.reason}")
    return 1e3 * np.array(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=60)
    args = parser.parse_args()
    saddle = paper_saddle()
    tex = cv2.imread(PHOTO, cv2.IMREAD_GRAYSCALE).astype(np.float32)
    reference = render_view(saddle, tex, INTR, np.eye(4))[0]
    images = frames(args.frames)
    T0 = pose(so3_exp(0.05 * np.array([-0.1, -0.31, 1.04])), 0.05 * np.array([0.17, -0.11, 0.01]))
    planar = Tracker(reference, ROI)
    planar.reset(ground_truth(saddle, INTR, np.eye(4), T0).G)
    general = GeneralTracker(reference, ROI)
    general.track(images[0])  # ρ* estimated here (multi-start), not timed
    for track in (planar.track, general.track):  # warm-up: compile every kernel variant
        timed(track, images[:2])
    t_planar = timed(planar.track, images)
    t_general = timed(general.track, images)
    for name, t in (("planar Tracker", t_planar), ("GeneralTracker", t_general)):
        print(f"{name:24s} median {np.median(t):6.2f} ms  p90 {np.percentile(t, 90):6.2f} ms")
    print(f"ratio general/planar (median): {np.median(t_general) / np.median(t_planar):.2f}")


if __name__ == "__main__":
    main()
