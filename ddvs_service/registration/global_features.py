"""Optional feature-based hypotheses for the global initialiser (never required): ORB or AKAZE + RANSAC homography.

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
FeatureKind = Literal["orb", "akaze"]
MIN_INLIERS = 8


def _detector(kind: FeatureKind) -> cv2.Feature2D:
    if kind == "orb":
        return cv2.ORB_create(nfeatures=1500, edgeThreshold=15, patchSize=15)
    if kind == "akaze":
        return cv2.AKAZE_create()
    raise ValueError(f"unknown feature source {kind!r}; expected 'orb' or 'akaze'")


def feature_homography(reference: F32, roi: Roi, current: F32, kind: FeatureKind) -> F64 | None:
    """RANSAC homography (det 1) from features of the reference ROI to the current image, or None."""
    x, y, w, h = roi
    mask = np.zeros(reference.shape, np.uint8)
    mask[y : y + h, x : x + w] = 255
    det = _detector(kind)
    k1, d1 = det.detectAndCompute(np.clip(reference, 0, 255).astype(np.uint8), mask)
    k2, d2 = det.detectAndCompute(np.clip(current, 0, 255).astype(np.uint8), None)
    if d1 is None or d2 is None or len(k1) < MIN_INLIERS or len(k2) < MIN_INLIERS:
        return None
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(d1, d2, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < 0.8 * p[1].distance]
    if len(good) < MIN_INLIERS:
        return None
    src = np.float32([k1[m.queryIdx].pt for m in good])
    dst = np.float32([k2[m.trainIdx].pt for m in good])
    H, inliers = cv2.findHomography(src, dst, cv2.RANSAC, 3.0)
    if H is None or int(inliers.sum()) < MIN_INLIERS:
        return None
    d = float(np.linalg.det(H))
    if not np.isfinite(d) or d <= 0:
        return None
    return H / np.cbrt(d)
