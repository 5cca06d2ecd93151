"""The estimate of eq. (2) + (4) for one frame (`GeneralResult`) and the warp of eq. (2)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.registration.general_basis import ParallaxBasis
from ddvs_service.registration.general_config import FLAG_DIVERGED, FLAG_LOW_TEXTURE, FLAG_OCCLUSION
from ddvs_service.registration.result import RegistrationResult

F64 = NDArray[np.float64]


@dataclass(kw_only=True)
class GeneralResult(RegistrationResult):
    """Estimate of eq. (2)+(4) for one frame: the planar `RegistrationResult` (`G`, `S`, `beta`, `iterations`,
    `residual_rms`, `inlier_ratio`, `scale`, `converged`, `reason`) and the parallax of eq. (2).

    - `G` (3×3, det 1) and `e` (3, same scale as `G`): reference pixels → current pixels, `p ∝ G p* + ρ*(p*) e`.
    - `rho_coeffs`: ρ* coefficients in `basis` (gauge of the module docstring); `rho_at(p)` evaluates ρ*.
    - `rho_information`: Fisher information of `rho_coeffs` given `e` (accumulated over the frames by the tracker),
      `(JᵀWJ)/σ²` with the other unknowns marginalised; `parallax_px`: RMS over the ROI of the displacement due to
      `ρ* e` in this frame; `margin`: relative cost gap to the best different parallax field (estimation frames);
      `epipole_wald`: how significant the frame finds `e` ≠ 0 (`general` module docstring, held epipole; nan when
      not evaluated: no parallax field, a failed frame).
    - `flags` (`FLAG_*`): what went wrong with `converged` and `reason`, never silent.
    """

    e: F64
    rho_coeffs: F64
    basis: ParallaxBasis
    rho_information: F64
    parallax_px: float = 0.0
    margin: float = float("nan")
    epipole_wald: float = float("nan")
    flags: list[str] = field(default_factory=list)

    def rho_at(self, p: ArrayLike) -> float:
        """ρ* at one reference pixel `p = (u, v)` (e.g. the control point), gauge units."""
        return float(self.basis.rho(self.rho_coeffs, np.asarray(p, dtype=np.float64).reshape(1, 2))[0])

    def warp(self, p: ArrayLike) -> F64:
        """Current pixels (N × 2) of reference pixels `p` (N × 2) under eq. (2)."""
        return warp_points(self.G, self.e, self.basis, self.rho_coeffs, p)

    def rho_std(self) -> F64:
        """Standard errors of `rho_coeffs` (inf where the information is singular)."""
        return std_from_information(self.rho_information)

    def to_json_dict(self) -> dict[str, Any]:
        """Plain-JSON view: the planar result's keys, then `e`, ρ* (`rho_coeffs`, `rho_degree`, `rho_std`),
        `parallax_px`, `margin`, `flags`."""
        return {
            **super().to_json_dict(), "e": self.e.tolist(), "rho_coeffs": self.rho_coeffs.tolist(),
            "rho_degree": self.basis.degree, "rho_std": [float(x) for x in self.rho_std()],
            "parallax_px": float(self.parallax_px), "margin": float(self.margin), "flags": self.flags,
        }


def std_from_information(info: F64) -> F64:
    w, V = np.linalg.eigh(info)
    inv_w = np.where(w > 1e-12 * max(float(w.max(initial=0.0)), 1e-300), 1.0 / np.maximum(w, 1e-300), np.inf)
    with np.errstate(invalid="ignore"):
        var = (V**2) @ inv_w
    return np.sqrt(np.where(np.isnan(var), np.inf, var))


def warp_points(G: F64, e: F64, basis: ParallaxBasis, coeffs: F64, p: ArrayLike) -> F64:
    """`π(G p* + ρ*(p*) e)` for reference pixels `p` (N × 2), full resolution."""
    q = np.asarray(p, dtype=np.float64).reshape(-1, 2)
    return warp_homogeneous(np.c_[q, np.ones(len(q))], basis.rho(coeffs, q), G, e)


def warp_homogeneous(p_h: F64, rho: F64, G: F64, e: F64) -> F64:
    """Eq. (2) dehomogenised, `π(G p* + ρ* e)`, for homogeneous reference pixels `p_h` (N × 3) and their ρ* (N)."""
    P = p_h @ G.T + np.outer(rho, e)
    return P[:, :2] / P[:, 2:3]


def flags_for(reason: str) -> list[str]:
    """Failure flags from a reason string of the planar or general solver."""
    if "degenerate" in reason:
        return [FLAG_LOW_TEXTURE]
    if "inlier" in reason:
        return [FLAG_OCCLUSION]
    if "diverged" in reason or "non-finite" in reason:
        return [FLAG_DIVERGED]
    return []
