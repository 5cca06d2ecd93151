"""Robust photometric cost of warp hypotheses over the reference ROI (ranks and selects global hypotheses).

For the reference template `t` (ROI pixels) and the current image sampled at the warped ROI pixels `c` (bilinear,
through `kernels/global_warp.py`), an affine photometric model `t ≈ a·c + b` (the gain/bias of (4), one global gain)
is fitted by least squares over the visible pixels with `a ≥ 0`. Each residual `r = t − (a·c + b)` is scaled by the
template's standard deviation `σ_t` and costs `ρ(x) = x² / (x² + κ²)` (Geman–McClure, bounded by 1).
`cost` is the mean over all ROI pixels, those outside the current image costing 1 (ranks hypotheses: one that pushes
the ROI out of the image is not rewarded); `cost_visible` is the mean over the visible pixels only (the quality of
the match itself, whatever the visible fraction). Both are 0 for a perfect match, ≈ 0.8 for an unrelated patch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from kernels.exclusive import GATE
from kernels.global_warp import sample_points, warp_homographies

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
MIN_VISIBLE_PIXELS = 16
SCORE_CHUNK = 1 << 16  # sampled values scored between two checkpoints of the Taichi gate (about a millisecond)


@dataclass(frozen=True)
class PhotometricScore:
    """`cost` and `cost_visible` ∈ [0, 1] (lower is better, module docstring), zero-mean normalised correlation
    `zncc` over the visible ROI pixels, and the `visible` fraction of the ROI inside the current image."""

    cost: float
    cost_visible: float
    zncc: float
    visible: float


def sample_through(image: F32, H: F64, shape: tuple[int, int], offset: tuple[float, float]) -> tuple[F32, F32]:
    """Sample `image` at `H · [c + offset_u, r + offset_v, 1]` for an output of `shape` (one Taichi launch).
    `H` is one 3×3 matrix (returns (values, valid) of `shape`) or a stack (N, 3, 3) (returns (N, *shape) arrays)."""
    Hs = np.asarray(H, dtype=np.float32)
    single = Hs.ndim == 2
    Hs = np.ascontiguousarray(Hs.reshape(-1, 9))
    out = np.empty((len(Hs), *shape), np.float32)
    valid = np.empty_like(out)
    GATE.checkpoint()  # a frame waiting for Taichi goes first (`kernels.exclusive`)
    warp_homographies(np.ascontiguousarray(image, np.float32), out, valid, Hs, float(offset[0]), float(offset[1]))
    return (out[0], valid[0]) if single else (out, valid)


def sample_at(image: F32, points: F64, shape: tuple[int, int]) -> tuple[F32, F32]:
    """Sample `image` at the (N, 2) pixel points `(u, v)` (one Taichi launch), returned as (values, valid) arrays of
    `shape` (N = h·w, row-major)."""
    xy = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 2)
    out = np.empty(len(xy), np.float32)
    valid = np.empty_like(out)
    GATE.checkpoint()
    sample_points(np.ascontiguousarray(image, np.float32), xy, out, valid)
    return out.reshape(shape), valid.reshape(shape)


def photometric_scores(template: F32, sampled: F32, valid: F32, kappa: float = 0.5) -> list[PhotometricScore]:
    """Scores of a stack of current-image samplings `sampled` (N, h, w) with masks `valid` against `template` (h, w),
    `SCORE_CHUNK` sampled values at a time (each sampling's score is its own: the chunks change no figure)."""
    if sampled.ndim != 3 or sampled.shape[1:] != template.shape or valid.shape != sampled.shape:
        raise ValueError(f"expected sampled and valid of shape (N, {template.shape}), "
                         f"got sampled {sampled.shape}, valid {valid.shape}")
    rows = max(1, SCORE_CHUNK // template.size)
    scores: list[PhotometricScore] = []
    for start in range(0, len(sampled), rows):
        GATE.checkpoint()  # a frame waiting for Taichi goes first between chunks (`kernels.exclusive`)
        scores += _scores(template, sampled[start : start + rows], valid[start : start + rows], kappa)
    return scores


def _scores(template: F32, sampled: F32, valid: F32, kappa: float) -> list[PhotometricScore]:
    """`photometric_scores` of one chunk of samplings (shapes checked)."""
    n = template.size
    m = (valid > 0.5).reshape(len(sampled), n).astype(np.float64)
    t = template.reshape(1, n).astype(np.float64)
    c = sampled.reshape(len(sampled), n).astype(np.float64)
    n_vis = m.sum(axis=1)
    safe = np.maximum(n_vis, 1.0)
    tc = (t - (m * t).sum(axis=1, keepdims=True) / safe[:, None]) * m
    cc = (c - (m * c).sum(axis=1, keepdims=True) / safe[:, None]) * m
    var_t, var_c, cov = (tc * tc).sum(axis=1), (cc * cc).sum(axis=1), (tc * cc).sum(axis=1)
    gain = np.where(var_c > 0, np.maximum(cov, 0.0) / np.where(var_c > 0, var_c, 1.0), 0.0)
    r = (tc - gain[:, None] * cc) / max(float(template.std()), 1e-6)
    rho = (r * r / (r * r + kappa * kappa) * m).sum(axis=1)
    denom = np.sqrt(var_t * var_c)
    zncc = np.where(denom > 0, cov / np.where(denom > 0, denom, 1.0), 0.0)
    scores = []
    for k in range(len(sampled)):
        if n_vis[k] < MIN_VISIBLE_PIXELS:
            scores.append(PhotometricScore(cost=1.0, cost_visible=1.0, zncc=0.0, visible=float(n_vis[k]) / n))
        else:
            scores.append(PhotometricScore(cost=float(rho[k] + n - n_vis[k]) / n, cost_visible=float(rho[k] / n_vis[k]),
                                           zncc=float(zncc[k]), visible=float(n_vis[k]) / n))
    return scores


def photometric_score(template: F32, sampled: F32, valid: F32, kappa: float = 0.5) -> PhotometricScore:
    """Score one current-image sampling `sampled` (with `valid` mask) against the reference `template` (same shape)."""
    if template.shape != sampled.shape or template.shape != valid.shape:
        raise ValueError(f"shapes differ: template {template.shape}, sampled {sampled.shape}, valid {valid.shape}")
    return photometric_scores(template, sampled[None], valid[None], kappa)[0]


@dataclass(frozen=True)
class OccludedScore:
    """The match of the best-fitting `kept` fraction of the visible ROI pixels (`trimmed_score`): `cost` ∈ [0, 1] as
    `cost_visible` over those pixels only, and `coherence` ∈ [0, 1] of the pixels left out — the mean, over them, of
    the fraction of their `COHERENCE_BOX` neighbourhood also left out (about 1 for a foreign object covering part
    of the ROI, lower for residuals scattered over the texture, as a wrong warp leaves)."""

    cost: float
    coherence: float
    kept: float


COHERENCE_BOX = 7  # pixels, side of the neighbourhood of `OccludedScore.coherence`


def trimmed_score(template: F32, sampled: F32, valid: F32, kept: float, kappa: float = 0.5) -> OccludedScore:
    """Score of one sampling (shapes as `photometric_score`) on the `kept` fraction of the visible pixels that the
    affine photometric model fits best: the model is fitted on every visible pixel, then twice again on the `kept`
    best of the previous fit (a foreign object's pixels must not set the gain), and the Geman–McClure cost of the
    module docstring is averaged over the last `kept` set."""
    if template.shape != sampled.shape or template.shape != valid.shape:
        raise ValueError(f"shapes differ: template {template.shape}, sampled {sampled.shape}, valid {valid.shape}")
    if not 0.0 < kept <= 1.0:
        raise ValueError(f"kept must be in (0, 1], got {kept}")
    visible = valid > 0.5
    n_visible = int(visible.sum())
    if n_visible < MIN_VISIBLE_PIXELS:
        return OccludedScore(cost=1.0, coherence=0.0, kept=kept)
    t = template.astype(np.float64)
    c = sampled.astype(np.float64)
    use = visible
    n_keep = max(MIN_VISIBLE_PIXELS, round(kept * n_visible))
    r = np.zeros_like(t)
    for _ in range(3):
        GATE.checkpoint()
        tm, cm = t[use].mean(), c[use].mean()
        var_c = float(((c[use] - cm) ** 2).sum())
        gain = max(float(((t[use] - tm) * (c[use] - cm)).sum()), 0.0) / var_c if var_c > 0 else 0.0
        r = np.where(visible, np.abs(t - tm - gain * (c - cm)), np.inf)
        cut = np.partition(r[visible], n_keep - 1)[n_keep - 1]
        use = visible & (r <= cut)
    x = r[use] / max(float(template.std()), 1e-6)
    cost = float(np.mean(x * x / (x * x + kappa * kappa)))
    out = (visible & ~use).astype(np.float32)
    if not out.any():
        return OccludedScore(cost=cost, coherence=1.0, kept=kept)
    GATE.checkpoint()
    box = np.ones(COHERENCE_BOX) / COHERENCE_BOX
    near = np.apply_along_axis(np.convolve, 0, np.apply_along_axis(np.convolve, 1, out, box, "same"), box, "same")
    return OccludedScore(cost=cost, coherence=float(near[out > 0].mean()), kept=kept)
