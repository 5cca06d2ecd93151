"""Planar registration on real pairs with ground truth (issue 3): Oxford boat 1→2, bikes 1→2…6, leuven 1→2…6.

For each pair and each central ROI of image 1 (200×150 and 400×300), both methods start at identity:
- ours: `register` with the default `RegistrationConfig` (pyramid levels chosen from the ROI size, Huber, one gain;
  the cold start's shift and rough angle from the correlation search of `registration.coarse_search`);
- ours with the camera response and the defocus (`RegistrationConfig(gamma=2.2)`, the defocus radius estimated by
  `registration.defocus.register_defocus`): irradiance instead of encoded grey levels, the reference blurred by the
  disk that best explains the current image (bikes is a defocus sequence; defocus blurs irradiance);
- `cv2.findTransformECC` (MOTION_HOMOGRAPHY, the ROI of image 1 as template, the whole image N as input, identity
  start shifted to the ROI, 200 iterations or 1e-6 change, Gaussian pre-filter 5) — a single level, as OpenCV has it.
Error: the largest distance between the ROI corners mapped by the estimate and by the ground truth `H1toNp`
(normalised by `H[2,2]`), in pixels of image N. The ground truth itself is good to about 0.5–1 px
(`bikes_ground_truth.py` compares it with an independent SIFT estimate on bikes). A method's
failure (exception, not converged, or error > 5 px) is shown as such.

Run: `.venv/bin/python benchmarks/real_pairs.py [--write-readme]` prints a markdown table (and with
`--write-readme` replaces its section of its results page, `docs/results/accuracy.md`).
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_registration import table_main  # noqa: E402
from ddvs_service.registration.config import RegistrationConfig  # noqa: E402
from ddvs_service.registration.defocus import register_defocus  # noqa: E402
from ddvs_service.registration.planar import register  # noqa: E402
from evaluation.datasets import require_datasets  # noqa: E402
from evaluation.pairs import (  # noqa: E402
    CAMERA_GAMMA,
    ONE_GAIN_HUBER,
    PAIRS,
    ROI_SIZES,
    centred_roi,
    corner_error,
    ground_truth,
    load,
)

FAILED_PX = 5.0


def ecc(
    ref: np.ndarray, cur: np.ndarray, roi: tuple[int, int, int, int], H0: np.ndarray | None = None
) -> np.ndarray:
    """`cv2.findTransformECC` from `H0` (reference → current pixels; identity by default); returns H (reference →
    current pixels). Raises cv2.error on failure."""
    x, y, w, h = roi
    template = np.ascontiguousarray(ref[y : y + h, x : x + w])
    start = np.eye(3) if H0 is None else H0 / H0[2, 2]
    W = (start @ np.array([[1.0, 0, x], [0, 1.0, y], [0, 0, 1.0]])).astype(np.float32)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-6)
    _, W = cv2.findTransformECC(template, cur, W, cv2.MOTION_HOMOGRAPHY, criteria, None, 5)
    T = np.array([[1.0, 0, -x], [0, 1.0, -y], [0, 0, 1.0]])  # reference pixels → template pixels
    return W.astype(np.float64) @ T


def cell(error: float | None, ok: bool, why: str = "") -> str:
    if error is None:
        return f"failed ({why})"
    text = f"{error:.2f}"
    return text if ok and error <= FAILED_PX else f"failed ({text} px{', ' + why if why else ''})"


def run() -> str:
    header = ["pair"] + [f"{name} {w}×{h}" for w, h in ROI_SIZES for name in ("ours", "ours γ 2.2 + defocus", "ECC")]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    worst = 0.0
    for seq, k in PAIRS:
        ref, cur, H_true = load(seq, 1), load(seq, k), ground_truth(seq, k)
        cells = [f"{seq} 1→{k}"]
        for w, h in ROI_SIZES:
            roi = centred_roi(ref.shape, w, h)
            result = register(ref, cur, roi=roi, config=RegistrationConfig(**ONE_GAIN_HUBER))
            error = corner_error(H_true, result.H, roi)
            worst = max(worst, error)
            cells.append(cell(error, result.converged, "" if result.converged else "not converged"))
            fit = register_defocus(ref, cur, roi=roi, config=RegistrationConfig(gamma=CAMERA_GAMMA,
                                                                                          **ONE_GAIN_HUBER))
            converged = fit.result.converged
            text = cell(corner_error(H_true, fit.result.H, roi), converged, "" if converged else "not converged")
            cells.append(f"{text} (r {fit.defocus_px:.1f})")
            try:
                cells.append(cell(corner_error(H_true, ecc(ref, cur, roi), roi), True))
            except cv2.error as exc:
                cells.append(cell(None, False, str(exc).strip().splitlines()[-1][-60:]))
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", f"Largest corner error of ours (default settings): {worst:.2f} px (target ≤ 1 px; ground truth good "
              f"to ~0.5–1 px). Corner errors in pixels; 'failed' = exception, not converged or > {FAILED_PX:g} px; "
              "r = the estimated defocus radius (px)."]
    return "\n".join(lines)


def main() -> int:
    require_datasets()
    return table_main(__doc__, run, "registration-real-pairs", "Registration on real pairs", "real_pairs.py")


if __name__ == "__main__":
    sys.exit(main())
