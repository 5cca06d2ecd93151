"""Does blurring irradiance instead of encoded grey levels explain the bikes errors? Synthetic defocused pairs.

Bikes img1 moved by the ground truth `H1toNp` (N = 4, 5, 6) and defocused by a uniform disk of radius 3.5 / 4.5 /
5.5 px (the radii `register_defocus` finds on the real pairs), in two ways:
- encoded: the disk blurs the grey levels themselves;
- irradiance: the grey levels are decoded with γ 2.2 (`255 (I / 255)^γ`), warped, blurred and encoded again — what
  a γ-encoding camera records through a defocused lens (`evaluation.defocus.defocused`).
Each current image is registered from identity on the central ROIs with the default settings, with the reference
blurred by the same disk (`RegistrationConfig(defocus_px=r)`), and with the camera response as well
(`gamma=2.2, defocus_px=r`). Error: the largest distance between the ROI corners mapped by the estimate and by
`H1toNp` (`evaluation.pairs.corner_error`), pixels; `*` = not converged.

Run: `.venv/bin/python benchmarks/irradiance_blur.py` prints a markdown table (under a minute on 2 cores).
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ddvs_service.registration.config import RegistrationConfig  # noqa: E402
from ddvs_service.registration.planar import register  # noqa: E402
from evaluation.datasets import require_datasets  # noqa: E402
from evaluation.defocus import defocused  # noqa: E402
from evaluation.pairs import CAMERA_GAMMA, ONE_GAIN_HUBER, ROI_SIZES, centred_roi, corner_error, ground_truth, load  # noqa: E402

CASES = ((4, 3.5), (5, 4.5), (6, 5.5))  # bikes image N, defocus radius (px)


def run() -> str:
    sharp = load("bikes", 1)
    header = ["pair, disk", "blurred", "ROI", "default", "reference blurred", "γ 2.2 + reference blurred"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for k, radius in CASES:
        H = ground_truth("bikes", k)
        for name, gamma in (("encoded", 1.0), ("irradiance", CAMERA_GAMMA)):
            current = defocused(sharp, H, radius, gamma)
            for w, h in ROI_SIZES:
                roi = centred_roi(sharp.shape, w, h)
                cells = [f"bikes 1→{k}, {radius:g} px", name, f"{w}×{h}"]
                for config in (RegistrationConfig(**ONE_GAIN_HUBER),
                               RegistrationConfig(defocus_px=radius, **ONE_GAIN_HUBER),
                               RegistrationConfig(gamma=CAMERA_GAMMA, defocus_px=radius, **ONE_GAIN_HUBER)):
                    result = register(sharp, current, roi=roi, config=config)
                    cells.append(f"{corner_error(H, result.H, roi):.2f}{'' if result.converged else '*'}")
                lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Corner errors in pixels against the homography used to make the pair; * = not converged."]
    return "\n".join(lines)


def main() -> int:
    require_datasets()
    print(run())
    return 0


if __name__ == "__main__":
    sys.exit(main())
