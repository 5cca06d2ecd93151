"""Pinhole camera model.

Pixel convention (whole project): 0-based pixel *centres*, u to the right (columns), v downwards (rows); the
centre of the top-left pixel is (0, 0). Camera frame: OpenCV axes (x right, y down, z forward), metres.
Normalised points `m = K⁻¹ p` with `p = [u, v, 1]`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels (`fx`, `fy` focal lengths, `cx`, `cy` principal point, no distortion)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    skew: float = 0.0

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if not (self.width > 0 and self.height > 0):
            raise ValueError(f"image size must be positive, got {self.width}×{self.height}")

    @classmethod
    def centred(cls, f: float, width: int, height: int) -> Intrinsics:
        """Square pixels, principal point at the image centre ((W − 1)/2, (H − 1)/2) in pixel-centre coordinates."""
        return cls(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)

    @classmethod
    def from_matrix(cls, K: ArrayLike, width: int, height: int) -> Intrinsics:
        K = np.asarray(K, dtype=np.float64)
        return cls(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height, K[0, 1])

    @property
    def K(self) -> NDArray[np.float64]:
        """3×3 intrinsic matrix."""
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def K_inv(self) -> NDArray[np.float64]:
        return np.asarray(np.linalg.inv(self.K), dtype=np.float64)

    def normalize(self, p: ArrayLike) -> NDArray[np.float64]:
        """Normalised homogeneous point `K⁻¹ [u, v, 1]` of a pixel (u, v)."""
        u, v = np.asarray(p, dtype=np.float64).reshape(-1)[:2]
        return self.K_inv @ np.array([u, v, 1.0])
