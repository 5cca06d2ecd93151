"""How good is the ground truth of Oxford bikes? An independent SIFT estimate against `H1toNp`, ours and ECC.

Bikes 1→2…6 blur image N more and more (defocus); `benchmarks/real_pairs.py` finds our estimate and ECC closer to each
other than to the ground truth on the blurriest pairs. This script builds a homography estimate that uses neither our
engine nor the ground truth, and compares everything at the ROI corners of `real_pairs.py`:
- SIFT: `cv2.SIFT_create` keypoints on the full grey images, Lowe's ratio test (0.8), `cv2.findHomography` with
  USAC_MAGSAC (threshold 2 px), then a least-squares (DLT) refit on the inliers. Its spread is the 95th percentile of
  the corner error of `BOOTSTRAP` least-squares refits on inliers resampled with replacement (a lower bound on its
  uncertainty: it ignores any bias of the keypoint positions under blur);
- SIFT chain: the product `H_{N−1→N} · … · H_{1→2}` of consecutive-pair SIFT estimates (each pair differs by a small
  step of blur, so its keypoints shift less between images);
- ours: `register` with the default `RegistrationConfig`, from identity; "ours γ+d": `register_defocus` with
  `gamma = real_pairs.CAMERA_GAMMA` (irradiance, the defocus estimated), as in `real_pairs.py`; ECC:
  `real_pairs.ecc`, from identity.
Every error is the largest distance (pixels of image N) between the ROI corners mapped by two estimates, each
normalised by `H[2, 2]` (`real_pairs.corner_error`); H maps image-1 pixels to image-N pixels, 0-based pixel centres.
If ours agrees with SIFT within ~0.5 px while the ground truth is > 1 px from both, the ground truth is the limit.

Run: `.venv/bin/python benchmarks/bikes_ground_truth.py` prints a markdown table (about a minute on 2 cores).
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.real_pairs import ecc  # noqa: E402
from ddvs_service.registration.config import RegistrationConfig  # noqa: E402
from ddvs_service.registration.defocus import register_defocus  # noqa: E402
from ddvs_service.registration.planar import register  # noqa: E402
from evaluation.datasets import require_datasets  # noqa: E402
from evaluation.pairs import CAMERA_GAMMA, ONE_GAIN_HUBER, ROI_SIZES, centred_roi, corner_error, ground_truth, load  # noqa: E402

SEQUENCE = "bikes"
FRAMES = range(1, 7)
RATIO = 0.8  # Lowe's ratio test
RANSAC_PX = 2.0  # USAC_MAGSAC inlier threshold, pixels of image N
BOOTSTRAP = 200  # least-squares refits on resampled inliers
SEED = 0


class SiftFit:
    """A SIFT + USAC_MAGSAC homography (image a → image b pixels, `H[2, 2]` = 1), its inliers and their residual."""

    def __init__(self, features: dict[int, tuple[tuple, np.ndarray]], ia: int, ib: int) -> None:
        (kp_a, des_a), (kp_b, des_b) = features[ia], features[ib]
        pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(des_a, des_b, k=2)
        matches = [m for m, n in pairs if m.distance < RATIO * n.distance]
        if len(matches) < 8:
            raise RuntimeError(f"{SEQUENCE} {ia}→{ib}: only {len(matches)} SIFT matches pass the ratio test")
        src = np.float64([kp_a[m.queryIdx].pt for m in matches])
        dst = np.float64([kp_b[m.trainIdx].pt for m in matches])
        H, inliers = cv2.findHomography(src, dst, cv2.USAC_MAGSAC, RANSAC_PX, maxIters=10000, confidence=0.9999)
        if H is None:
            raise RuntimeError(f"{SEQUENCE} {ia}→{ib}: USAC_MAGSAC found no homography in {len(matches)} matches")
        keep = inliers.ravel().astype(bool)
        self.src, self.dst = src[keep], dst[keep]
        self.H = self._fit(self.src, self.dst)
        mapped = cv2.perspectiveTransform(self.src[None], self.H)[0]
        self.rms_px = float(np.sqrt(np.mean(np.sum((mapped - self.dst) ** 2, axis=1))))

    @staticmethod
    def _fit(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
        H, _ = cv2.findHomography(src, dst, 0)
        return H / H[2, 2]

    def spread(self, roi: tuple[int, int, int, int], rng: np.random.Generator) -> float:
        """95th percentile of the corner error between this fit and refits on inliers drawn with replacement."""
        n = len(self.src)
        errors = [corner_error(self.H, self._fit(self.src[i], self.dst[i]), roi)
                  for i in (rng.integers(0, n, n) for _ in range(BOOTSTRAP))]
        return float(np.percentile(errors, 95))


def run() -> str:
    images = {k: load(SEQUENCE, k) for k in FRAMES}
    sift = cv2.SIFT_create()
    features = {k: sift.detectAndCompute(np.clip(img, 0, 255).astype(np.uint8), None) for k, img in images.items()}
    rng = np.random.default_rng(SEED)
    steps = {k: SiftFit(features, k - 1, k).H for k in FRAMES[1:]}
    header = ["pair", "ROI", "SIFT inliers (rms px)", "SIFT spread", "chain vs SIFT", "GT vs SIFT", "GT vs chain",
              "ours vs SIFT", "ours vs GT", "ours γ+d vs SIFT", "ours γ+d vs GT", "ECC vs SIFT", "ECC vs GT",
              "ours vs ECC"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    chain = np.eye(3)
    for k in FRAMES[1:]:
        chain = steps[k] @ chain
        chain = chain / chain[2, 2]
        fit = SiftFit(features, 1, k)
        H_true = ground_truth(SEQUENCE, k)
        for w, h in ROI_SIZES:
            ref = images[1]
            roi = centred_roi(ref.shape, w, h)
            result = register(ref, images[k], roi=roi, config=RegistrationConfig(**ONE_GAIN_HUBER))
            ours = result.H / result.H[2, 2]
            physical = register_defocus(ref, images[k], roi=roi, config=RegistrationConfig(
                gamma=CAMERA_GAMMA, **ONE_GAIN_HUBER)).result
            try:
                H_ecc: np.ndarray | None = ecc(ref, images[k], roi)
            except cv2.error:
                H_ecc = None

            def vs(a: np.ndarray | None, b: np.ndarray, roi: tuple[int, int, int, int] = roi) -> str:
                return "failed" if a is None else f"{corner_error(b, a, roi):.2f}"

            ours_text = "" if result.converged else " (not converged)"
            physical_text = "" if physical.converged else " (not converged)"
            lines.append("| " + " | ".join([
                f"1→{k}", f"{w}×{h}", f"{len(fit.src)} ({fit.rms_px:.2f})", f"{fit.spread(roi, rng):.2f}",
                vs(chain, fit.H), vs(H_true, fit.H), vs(H_true, chain), vs(ours, fit.H) + ours_text, vs(ours, H_true),
                vs(physical.H, fit.H) + physical_text, vs(physical.H, H_true),
                vs(H_ecc, fit.H), vs(H_ecc, H_true), "failed" if H_ecc is None else vs(ours, H_ecc),
            ]) + " |")
    lines += ["", "Corner errors in pixels of image N (largest of the four ROI corners). SIFT: direct 1→N fit; "
              "chain: product of consecutive SIFT fits; spread: 95th percentile of the bootstrap corner error of the "
              "SIFT fit."]
    return "\n".join(lines)


def main() -> int:
    require_datasets()
    print(run())
    return 0


if __name__ == "__main__":
    sys.exit(main())
