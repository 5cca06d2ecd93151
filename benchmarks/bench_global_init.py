"""Time one global initialisation (hypotheses + refinement) at 320×240 and 640×480; goals 100 ms and 250 ms.

Same scene as the paper's planar experiment (poster at 0.7 m, f = 420 px at 320×240, scaled with the image; ROI
70×70 at 320×240, 140×140 at 640×480). Reports the median of `--repeats` runs after one warm-up (kernel compile):
hypothesis generation (every stage, for reference), the full initialisation against the same reference (the
initialiser keeps the reference side: a tracker re-initialising after LOST; it stops after the first stage when that
has a clear winner, as here), and the first initialisation after a new reference (a new initialiser, which prepares
the reference side first); the load average is printed before and after (the goals are for 2 free cores).
Run: `.venv/bin/python benchmarks/bench_global_init.py`.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from ddvs_service.camera import Intrinsics
from ddvs_service.lie import so3_exp
from ddvs_service.registration.global_init import GlobalInitializer
from sim.planar_scene import POSTER_BLUR_SIGMA, PlanarScene
from sim.textures import TEXTURES, load_texture

GOALS_MS = {320: 100.0, 640: 250.0}


def median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    init = GlobalInitializer()
    print(f"load average before: {os.getloadavg()[0]:.1f}")
    for width in (320, 640):
        k = width // 320
        cam = Intrinsics.centred(420.0 * k, width, 240 * k)
        scene = PlanarScene(cam, load_texture(TEXTURES[1], POSTER_BLUR_SIGMA))
        H = scene.homography(so3_exp(np.radians([-20.3, 2.17, 14.59])), np.array([0.13, -0.23, -0.08]))
        ref, cur = scene.render(), scene.render(H)
        side = 70 * k
        roi = (round(cam.cx - side / 2 + 0.5), round(cam.cy - side / 2 + 0.5), side, side)
        hyp = median_ms(lambda: init.hypotheses(ref, roi, cur), args.repeats)  # noqa: B023 - evaluated in-loop
        full = median_ms(lambda: init.initialize(ref, roi, cur), args.repeats)  # noqa: B023 - evaluated in-loop
        first = median_ms(lambda: GlobalInitializer().initialize(ref, roi, cur), args.repeats)  # noqa: B023
        goal = GOALS_MS[width]
        print(f"{width}x{240 * k}: hypotheses {hyp:.1f} ms, full initialisation {full:.1f} ms (goal {goal} ms), "
              f"first after a new reference {first:.1f} ms, load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
