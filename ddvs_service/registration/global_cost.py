"""Robust photometric cost of a warp hypothesis over the reference ROI (ranks and selects global hypotheses).

For the reference template `t` (ROI pixels) and the current image sampled at the warped ROI pixels `c` (bilinear,
through `kernels/global_warp.py`), an affine photometric model `t ≈ a·c + b` (the gain/bias of (4), one global gain)
is fitted by least squares with `a ≥ 0`. Each residual `r = t − (a·c + b)` is scaled by the template's standard
deviation `σ_t` and costs `ρ(x) = x² / (x² + κ²)` (Geman–McClure, bounded by 1); ROI pixels that fall outside the
current image cost 1. The cost is the mean over all ROI pixels: 0 for a perfect match, ≈ 0.8 for an unrelated patch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from kernels.global_warp import warp_homography

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


@dataclass(frozen=True)
class PhotometricScore:
    """`cost` ∈ [0, 1] (lower is better), zero-mean normalised correlation `zncc` over the visible ROI pixels, and
    the `visible` fraction of the ROI inside the current image."""

    cost: float
    zncc: float
    visible: float


def sample_through(image: F32, H: F64, shape: tuple[int, int], offset: tuple[float, float]) -> tuple[F32, F32]:
    """Sample `image` at `H · [c + offset_u, r + offset_v, 1]` for an output of `shape`; return (values, valid)."""
    out = np.empty(shape, np.float32)
    valid = np.empty(shape, np.float32)
    warp_homography(image, out, valid, np.ascontiguousarray(H, np.float32).ravel(), float(offset[0]), float(offset[1]))
    return out, valid


def photometric_score(template: F32, sampled: F32, valid: F32, kappa: float = 0.5) -> PhotometricScore:
    """Score current-image values `sampled` (with `valid` mask) against the reference `template` (same shape)."""
    if template.shape != sampled.shape or template.shape != valid.shape:
        raise ValueError(f"shapes differ: template {template.shape}, sampled {sampled.shape}, valid {valid.shape}")
    n = template.size
    mask = valid > 0.5
    visible = float(mask.sum()) / n
    if mask.sum() < 16:
        return PhotometricScore(cost=1.0, zncc=0.0, visible=visible)
    t = template[mask].astype(np.float64)
    c = sampled[mask].astype(np.float64)
    sigma_t = max(float(template.std()), 1e-6)
    tc, cc = t - t.mean(), c - c.mean()
    var_c = float(cc @ cc)
    gain = max(float(tc @ cc) / var_c, 0.0) if var_c > 0 else 0.0
    r = (tc - gain * cc) / sigma_t
    rho = r * r / (r * r + kappa * kappa)
    cost = (float(rho.sum()) + (n - len(t))) / n
    denom = np.sqrt(float(tc @ tc) * var_c)
    zncc = float(tc @ cc) / denom if denom > 0 else 0.0
    return PhotometricScore(cost=cost, zncc=zncc, visible=visible)
