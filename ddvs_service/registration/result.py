"""The outcome of one registration: the planar model's, which the general model's result extends
(`general_result.GeneralResult`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray


@dataclass
class RegistrationResult:
    """Estimated geometry and photometry of eq. (5), and how the iteration ended.

    - `G`: 3×3, det 1 (SL(3)), maps reference pixels (full-image, 0-based pixel centres) to current pixels.
    - `S`: gain-grid node values, shape `gain_grid` (eq. (4)); `beta`: bias β in grey levels.
    - `iterations`: Gauss-Newton iterations per pyramid level, coarse → fine.
    - `residual_rms`: RMS of `S·I(w(G, p*)) + β − I*(p*)` over the valid ROI
      pixels at the last evaluation (grey levels).
    - `inlier_ratio`: fraction of the ROI's pixels with |r| ≤ 4.685 σ; `scale`: the robust scale σ (grey levels).
    - `converged` and `reason`: why the iteration stopped; `failed`: a level failed (diverged, degenerate, non-finite,
      given up) and the estimate is unusable even as a start — a solve that only ran out of iterations or inliers
      is not failed.
    - `covariance`: 12×12, the Gauss-Newton covariance of [vec(G) (row-major), e] (the general model's epipole;
      the planar model's rows and columns of `e` are zero; det G = 1 removes one more direction) that the image
      noise alone causes, σ² J (JᵀWJ)⁻¹ Jᵀ with σ = `scale`, `JᵀWJ` the last full-resolution step's over the
      unknowns it solved (marginal over the photometric ones and ρ*) and J the map from the engine's coordinates to
      these entries; None where not evaluated (a solve that did not end at full resolution).
    """

    G: NDArray[np.float64]
    S: NDArray[np.float64]
    beta: float
    iterations: list[int] = field(default_factory=list)
    residual_rms: float = float("nan")
    inlier_ratio: float = 0.0
    converged: bool = False
    reason: str = ""
    failed: bool = False
    scale: float = float("nan")
    covariance: NDArray[np.float64] | None = None

    @property
    def H(self) -> NDArray[np.float64]:
        """The homography normalised so that `H[2, 2] = 1`."""
        return self.G / self.G[2, 2]

    def to_json_dict(self) -> dict[str, Any]:
        """Plain-JSON view (lists and floats): `H` (H[2,2] = 1), `G`, `S`, `beta`, iterations, RMS, inliers, status."""
        return {
            "H": self.H.tolist(),
            "G": self.G.tolist(),
            "S": np.asarray(self.S).tolist(),
            "beta": float(self.beta),
            "iterations": [int(i) for i in self.iterations],
            "residual_rms": float(self.residual_rms),
            "inlier_ratio": float(self.inlier_ratio),
            "scale": float(self.scale),
            "converged": bool(self.converged),
            "reason": self.reason,
        }
