"""Optional feature-based hypotheses for the global initialiser (never required): ORB or SIFT + RANSAC homography.

ORB has binary descriptors (matched by Hamming distance), SIFT float ones (matched by L2 distance); both are in
OpenCV's main modules (AKAZE is not: OpenCV 5 moved it to the contrib modules, which we do not install).

Keypoints of the reference are taken inside the ROI only; matches pass Lowe's ratio test (0.8) and
`cv2.findHomography(RANSAC, 3 px)`. The homography maps reference pixels to current pixels (0-based pixel centres,
the same convention as OpenCV's keypoint coordinates) and is returned normalised to det 1; none is returned when fewer
than 8 RANSAC inliers are found or the homography is not orientation-preserving.
"""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
Roi = tuple[int, int, int, int]
FeatureKind = Literal["orb", "sift"]
MIN_INLIERS = 8


def _detector(kind: FeatureKind) -> tuple[cv2.Feature2D, int]:
    """The detector-descriptor of `kind` and the matcher norm of its descriptors."""
    if kind == "orb":
        return cv2.ORB.create(nfeatures=1500, edgeThreshold=15, patchSize=15), cv2.NORM_HAMMING
    if kind == "sift":
        return cv2.SIFT.create(nfeatures=1500), cv2.NORM_L2
    raise ValueError(f"unknown feature source {kind!r}; expected 'orb' or 'sift'")


def feature_homography(reference: F32, roi: Roi, current: F32, kind: FeatureKind) -> F64 | None:
    """RANSAC homography (det 1) from features of the reference ROI to the current image, or None."""
    x, y, w, h = roi
    mask = np.zeros(reference.shape, np.uint8)
    mask[y : y + h, x : x + w] = 255
    det, norm = _detector(kind)
    k1, d1 = det.detectAndCompute(np.clip(reference, 0, 255).astype(np.uint8), mask)
    k2, d2 = det.detectAndCompute(np.clip(current, 0, 255).astype(np.uint8), None)
    if d1 is None or d2 is None or len(k1) < MIN_INLIERS or len(k2) < MIN_INLIERS:
        return None
    pairs = cv2.BFMatcher(norm).knnMatch(d1, d2, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < 0.8 * p[1].distance]
    if len(good) < MIN_INLIERS:
        return None
    src = np.array([k1[m.queryIdx].pt for m in good], dtype=np.float32)
    dst = np.array([k2[m.trainIdx].pt for m in good], dtype=np.float32)
    H, inliers = cv2.findHomography(src, dst, cv2.RANSAC, 3.0)
    if H is None or int(inliers.sum()) < MIN_INLIERS:
        return None
    d = float(np.linalg.det(H))
    if not np.isfinite(d) or d <= 0:
        return None
    return H / np.cbrt(d)
