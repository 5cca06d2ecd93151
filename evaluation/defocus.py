"""Synthetic defocus of a real image: warp and blur in irradiance (the image formation that
`RegistrationConfig.gamma` and `.defocus_px` model), for tests and benchmarks of the defocus model."""

from __future__ import annotations

import cv2
import numpy as np

from kernels.image_formation import defocus_kernel


def defocused(image: np.ndarray, H: np.ndarray, radius: float, gamma: float = 1.0) -> np.ndarray:
    """`image` warped by `H` (cubic) and blurred by a uniform disk of `radius` px, in irradiance decoded with
    `gamma` (1: the grey levels themselves), encoded again: what a γ-encoding camera records through a defocused lens.
    """
    E = 255.0 * (np.maximum(image, 0.0) / 255.0) ** gamma
    moved = cv2.warpPerspective(E.astype(np.float32), H, (image.shape[1], image.shape[0]), flags=cv2.INTER_CUBIC)
    blurred = cv2.filter2D(moved, -1, defocus_kernel(radius), borderType=cv2.BORDER_REPLICATE)
    return (255.0 * (np.maximum(blurred, 0.0) / 255.0) ** (1.0 / gamma)).astype(np.float32)
