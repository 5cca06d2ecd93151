"""What the cold start's correlation search (`registration.coarse_search`) adds to `register` from identity, and costs.

1. Basin: for each texture (Oxford img1 of boat, graf, wall, bark, trees, ubc, Gaussian σ 1.5 px), `TRIALS` random
   similarities about the centre of a central 200×150 ROI (shift uniform in ±`MAX_SHIFT_PX` per axis, angle in
   ±`MAX_ANGLE_DEG`, scale log-uniform in `SCALES`; seeded), the current image rendered with `cv2.warpPerspective`.
   A trial succeeds when `register` (default `RegistrationConfig`) converges with a corner error below `OK_PX` (the
   largest distance between the ROI corners mapped by the estimate and by the true homography, pixels); "wrong" counts
   converged results above it.
2. Time (`--timing`): median and range of `register` on the 200×150 central ROI of real pairs, both variants
   interleaved, `TIMING_REPEATS` calls each after one warm-up. Run it under the timing lock.
The variant "without" replaces `planar.coarse_alignment` by a function returning None, which is the cold start as it
was before the search (identity, then the translation-only and similarity Gauss-Newton).

Run: `.venv/bin/python benchmarks/cold_start.py [--timing]` prints markdown tables.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ddvs_service.registration import planar  # noqa: E402
from ddvs_service.registration.coarse_search import coarse_alignment  # noqa: E402
from ddvs_service.registration.config import RegistrationConfig  # noqa: E402
from evaluation.datasets import require_datasets  # noqa: E402
from evaluation.pairs import ONE_GAIN_HUBER, corner_error, load  # noqa: E402

COLD = RegistrationConfig(**ONE_GAIN_HUBER)  # the settings the results were measured with

TEXTURES = ("boat", "graf", "wall", "bark", "trees", "ubc")
TRIALS = 40
MAX_SHIFT_PX = 50.0
MAX_ANGLE_DEG = 25.0
SCALES = (0.85, 1.15)
OK_PX = 0.1
SEED = 1
TIMING_PAIRS = (("boat", 2), ("bikes", 2), ("bikes", 4), ("leuven", 2))
TIMING_REPEATS = 15
VARIANTS: dict[str, Callable[..., np.ndarray | None]] = {"with search": coarse_alignment,
                                                          "without": lambda *args: None}


def central_roi(image: np.ndarray, w: int = 200, h: int = 150) -> tuple[int, int, int, int]:
    return (image.shape[1] - w) // 2, (image.shape[0] - h) // 2, w, h


def similarity(centre: tuple[float, float], shift: np.ndarray, angle_deg: float, scale: float) -> np.ndarray:
    """Turn by `angle_deg` and scale about `centre`, then shift (pixels)."""
    a = np.deg2rad(angle_deg)
    H = np.eye(3)
    H[:2, :2] = scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    H[:2, 2] = np.asarray(centre) + shift - H[:2, :2] @ np.asarray(centre)
    return H


def basin() -> str:
    rng = np.random.default_rng(SEED)
    lines = ["| texture | " + " | ".join(f"{v}: ok / wrong" for v in VARIANTS) + " |",
             "|---|" + "---|" * len(VARIANTS)]
    totals = dict.fromkeys(VARIANTS, 0)
    for name in TEXTURES:
        texture = cv2.GaussianBlur(load(name, 1), (0, 0), 1.5)
        roi = central_roi(texture)
        centre = (roi[0] + (roi[2] - 1) / 2, roi[1] + (roi[3] - 1) / 2)
        counts = {v: [0, 0] for v in VARIANTS}
        for _ in range(TRIALS):
            H = similarity(centre, rng.uniform(-MAX_SHIFT_PX, MAX_SHIFT_PX, 2),
                           rng.uniform(-MAX_ANGLE_DEG, MAX_ANGLE_DEG), float(np.exp(rng.uniform(*np.log(SCALES)))))
            current = cv2.warpPerspective(texture, H, (texture.shape[1], texture.shape[0]), flags=cv2.INTER_LINEAR)
            for variant, search in VARIANTS.items():
                planar.coarse_alignment = search
                result = planar.register(texture, current, roi=roi, config=COLD)
                if result.converged:
                    counts[variant][corner_error(H, result.H, roi) >= OK_PX] += 1
        planar.coarse_alignment = coarse_alignment
        for variant in VARIANTS:
            totals[variant] += counts[variant][0]
        lines.append(f"| {name} | " + " | ".join(f"{ok}/{TRIALS} / {wrong}" for ok, wrong in counts.values()) + " |")
    lines.append("| all | " + " | ".join(f"{totals[v]}/{TRIALS * len(TEXTURES)}" for v in VARIANTS) + " |")
    lines += ["", f"ok: converged with a corner error < {OK_PX:g} px; wrong: converged with a larger one. Motions: "
              f"±{MAX_SHIFT_PX:g} px, ±{MAX_ANGLE_DEG:g}°, scale {SCALES[0]:g}–{SCALES[1]:g}, 200×150 central ROI."]
    return "\n".join(lines)


def timing() -> str:
    lines = ["| pair (200×150 ROI, from identity) | " + " | ".join(f"{v}: median (range) ms" for v in VARIANTS) + " |",
             "|---|" + "---|" * len(VARIANTS)]
    for seq, k in TIMING_PAIRS:
        ref, cur = load(seq, 1), load(seq, k)
        roi = central_roi(ref)
        times: dict[str, list[float]] = {v: [] for v in VARIANTS}
        for repeat in range(TIMING_REPEATS + 1):
            for variant, search in VARIANTS.items():
                planar.coarse_alignment = search
                start = time.perf_counter()
                planar.register(ref, cur, roi=roi, config=COLD)
                if repeat:
                    times[variant].append(1e3 * (time.perf_counter() - start))
        planar.coarse_alignment = coarse_alignment
        lines.append(f"| {seq} 1→{k} | " + " | ".join(
            f"{np.median(t):.1f} ({min(t):.1f}–{max(t):.1f})" for t in times.values()) + " |")
    lines += ["", f"`register` = reference pyramid + cold-start registration; {TIMING_REPEATS} calls per variant, "
              "interleaved, after one warm-up."]
    return "\n".join(lines)


def main() -> int:
    require_datasets()
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--timing", action="store_true", help="also time register with and without the search")
    args = parser.parse_args()
    print(basin())
    if args.timing:
        print()
        print(timing())
    return 0


if __name__ == "__main__":
    sys.exit(main())
