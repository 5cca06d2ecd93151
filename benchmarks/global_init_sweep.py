"""Success-rate sweep of the global initialiser over random planar displacements; writes a markdown table.

Displacements (`global_scenes.random_displacement`): in-plane rotation ±180°, tilt ≤ 40°, scale 0.7–1.4, ROI shift
≤ half the image; 320×240, f = 420 px, poster at 0.7 m, 70×70 ROI at the image centre. A trial succeeds when the
status is OK and the warp is within 1 px RMS of the truth; a failure is "reported" when the status is LOST.
Run: `.venv/bin/python benchmarks/global_init_sweep.py --trials 25 --out reports/global_init_sweep.md`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ddvs_service.camera import Intrinsics
from ddvs_service.registration.global_init import GlobalInitConfig, GlobalInitializer
from ddvs_service.registration.global_scenes import (
    TEXTURES,
    PlanarScene,
    load_texture,
    random_displacement,
    visible_fraction,
    warp_rms,
)

ROI = (125, 85, 70, 70)
SUCCESS_PX = 1.0


def sweep(texture: str, feature_source: str, trials: int, seed: int) -> dict[str, int]:
    """Counts for one texture and feature setting (≥ 70 % visible vs below)."""
    cam = Intrinsics.centred(420.0, 320, 240)
    scene = PlanarScene(cam, load_texture(texture))
    reference = scene.render()
    init = GlobalInitializer(GlobalInitConfig(feature_source=feature_source))
    rng = np.random.default_rng(seed)
    counts = dict.fromkeys(("n70", "ok70", "lost70", "wrong70", "n_low", "ok_low", "lost_low", "wrong_low"), 0)
    for _ in range(trials):
        d = random_displacement(rng, cam.width, cam.height)
        H = scene.homography(*d.pose(scene, (cam.cx, cam.cy)))
        key = "70" if visible_fraction(H, ROI, cam.width, cam.height) >= 0.7 else "_low"
        result = init.initialize(reference, ROI, scene.render(H))
        counts["n" + key] += 1
        if result.status == "LOST":
            counts["lost" + key] += 1
        elif warp_rms(result.G, H, ROI) < SUCCESS_PX:
            counts["ok" + key] += 1
        else:
            counts["wrong" + key] += 1
    return counts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=25, help="random displacements per texture and setting")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--features", nargs="+", default=["none", "orb"], help="feature sources to compare")
    parser.add_argument("--out", type=Path, default=Path("reports/global_init_sweep.md"))
    args = parser.parse_args()
    lines = [
        "| texture | feature source | ≥70 % visible: success | LOST | wrong OK | <70 %: success | LOST | wrong OK |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for texture in TEXTURES:
        for source in args.features:
            c = sweep(texture, source, args.trials, args.seed)
            rate = 100.0 * c["ok70"] / max(c["n70"], 1)
            lines.append(
                f"| {texture} | {source} | {c['ok70']}/{c['n70']} ({rate:.0f} %) | {c['lost70']} | {c['wrong70']} | "
                f"{c['ok_low']}/{c['n_low']} | {c['lost_low']} | {c['wrong_low']} |"
            )
            print(lines[-1], flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
