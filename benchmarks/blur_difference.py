"""Would modelling the blur difference help? `register` on a blur-matched pair, σ chosen by the lowest residual.

The engine compares a sharp reference with a defocused current image as they are. This benchmark emulates a blur
model outside the engine: before `register` (from identity), one image is blurred by a point-spread function of size
σ px (σ > 0: the reference, σ < 0: the current image by |σ|), for every σ of `SIZES[psf]`, and the result with the
lowest residual RMS (grey levels, after the gain and bias of eq. (4)) among the converged ones is kept — the same rule
for every pair. Blurring either image leaves the true homography unchanged. `--psf gaussian` (default):
`cv2.GaussianBlur` of standard deviation σ; `--psf disk`: a uniform disk of radius σ (a defocused lens's PSF;
`kernels.image_formation.defocus_kernel`), which is what bikes img6 shows (a ~5.5 px disk when the PSF is fitted by
least squares with the ground truth).
- Synthetic rows: Oxford boat img1 (σ 1.5 px) moved by 45 px, −30 px, 5°, 3 % scale about the 200×150 ROI centre,
  then defocused by the same PSF of size `b` px; error against the exact homography.
- Real rows: the pairs and central ROIs of `real_pairs.py`; error against the ground truth `H1toNp`, and for bikes
  also against the independent SIFT estimate of `bikes_ground_truth.py`.
Both the default `RegistrationConfig` and a 2×2 gain grid (eq. (4)'s S bilinear over the ROI) are run. Error: the
largest distance between the ROI corners mapped by the estimate and by the reference homography (`real_pairs.
corner_error`), pixels of image N; `*` marks a result that did not converge.

Run: `.venv/bin/python benchmarks/blur_difference.py [--psf disk]` prints a markdown table (a few minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bikes_ground_truth import SiftFit  # noqa: E402
from ddvs_service.registration.config import RegistrationConfig  # noqa: E402
from ddvs_service.registration.planar import register  # noqa: E402
from evaluation.datasets import require_datasets  # noqa: E402
from evaluation.pairs import ONE_GAIN_HUBER, PAIRS, ROI_SIZES, centred_roi, corner_error, ground_truth, load  # noqa: E402
from kernels.image_formation import defocus_kernel  # noqa: E402

SIZES = {  # px; > 0 blurs the reference, < 0 the current image
    "gaussian": (-2.0, -1.0, 0.0, 1.0, 2.0, 3.0, 4.0, 5.0),
    "disk": (-2.0, 0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0),
}
CONFIGS = {"default": RegistrationConfig(**ONE_GAIN_HUBER),
           "gain 2×2": RegistrationConfig(**{**ONE_GAIN_HUBER, "gain_grid": (2, 2)})}
SYNTHETIC_BLURS = (0.0, 2.0, 3.0, 4.0)  # defocus of the synthetic current image, px
Roi = tuple[int, int, int, int]


@dataclass(frozen=True)
class Fit:
    sigma: float
    H: np.ndarray
    residual_rms: float
    converged: bool


def blurred(image: np.ndarray, size: float, psf: str) -> np.ndarray:
    """`image` blurred by the `psf` of `size` px (unchanged when `size` ≤ 0)."""
    if size <= 0:
        return image
    if psf == "gaussian":
        return cv2.GaussianBlur(image, (0, 0), size)
    return cv2.filter2D(image.astype(np.float32), -1, defocus_kernel(size), borderType=cv2.BORDER_REFLECT)


def fits(ref: np.ndarray, cur: np.ndarray, roi: Roi, config: RegistrationConfig, psf: str) -> list[Fit]:
    """`register` from identity with the blur difference σ of every `SIZES[psf]` entry."""
    out = []
    for sigma in SIZES[psf]:
        result = register(blurred(ref, sigma, psf), blurred(cur, -sigma, psf), roi=roi, config=config)
        out.append(Fit(sigma, result.H / result.H[2, 2], result.residual_rms, result.converged))
    return out


def chosen(candidates: list[Fit]) -> Fit:
    """The lowest residual among the converged fits (among all when none converged)."""
    pool = [f for f in candidates if f.converged] or candidates
    return min(pool, key=lambda f: f.residual_rms)


def text(fit: Fit, truth: np.ndarray, roi: Roi) -> str:
    return f"{corner_error(truth, fit.H, roi):.2f}{'' if fit.converged else '*'}"


def synthetic_rows(psf: str) -> list[str]:
    texture = cv2.GaussianBlur(load("boat", 1), (0, 0), 1.5)
    w, h = ROI_SIZES[0]
    roi = centred_roi(texture.shape, w, h)
    cx, cy = roi[0] + (w - 1) / 2, roi[1] + (h - 1) / 2
    a, s = np.deg2rad(5.0), 1.03
    H = np.eye(3)
    H[:2, :2] = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    H[:2, 2] = np.array([cx + 45.0, cy - 30.0]) - H[:2, :2] @ np.array([cx, cy])
    rows = []
    for b in SYNTHETIC_BLURS:
        moved = cv2.warpPerspective(texture, H, (texture.shape[1], texture.shape[0]), flags=cv2.INTER_LINEAR)
        cur = blurred(moved, b, psf)
        cells = [f"synthetic, defocus {b:g} px", f"{w}×{h}"]
        for config in CONFIGS.values():
            found = fits(texture, cur, roi, config, psf)
            best = chosen(found)
            cells += [text(found[SIZES[psf].index(0.0)], H, roi), f"{text(best, H, roi)} (σ {best.sigma:g})", "—"]
        rows.append("| " + " | ".join(cells) + " |")
    return rows


def real_rows(psf: str) -> list[str]:
    rows = []
    sift = cv2.SIFT_create()
    for seq, k in PAIRS:
        ref, cur, truth = load(seq, 1), load(seq, k), ground_truth(seq, k)
        independent = None
        if seq == "bikes":
            features = {i: sift.detectAndCompute(np.clip(img, 0, 255).astype(np.uint8), None)
                        for i, img in ((1, ref), (k, cur))}
            independent = SiftFit(features, 1, k).H
        for w, h in ROI_SIZES:
            roi = centred_roi(ref.shape, w, h)
            cells = [f"{seq} 1→{k}", f"{w}×{h}"]
            for config in CONFIGS.values():
                found = fits(ref, cur, roi, config, psf)
                as_is, best = found[SIZES[psf].index(0.0)], chosen(found)
                versus = "—" if independent is None else (
                    f"{corner_error(independent, as_is.H, roi):.2f} → {corner_error(independent, best.H, roi):.2f}")
                cells += [text(as_is, truth, roi), f"{text(best, truth, roi)} (σ {best.sigma:g})", versus]
            rows.append("| " + " | ".join(cells) + " |")
    return rows


def run(psf: str) -> str:
    header = ["pair", "ROI"]
    for name in CONFIGS:
        header += [f"{name}: as is", f"{name}: blur-matched (σ)", f"{name}: vs SIFT, as is → matched"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += synthetic_rows(psf) + real_rows(psf)
    lines += ["", "Corner errors in pixels against the exact homography (synthetic) or the ground truth (real); σ > 0 "
              f"blurred the reference, σ < 0 the current image ({psf} PSF); * = not converged."]
    return "\n".join(lines)


def main() -> int:
    require_datasets()
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--psf", choices=sorted(SIZES), default="gaussian", help="the blur's point-spread function")
    print(run(parser.parse_args().psf))
    return 0


if __name__ == "__main__":
    sys.exit(main())
