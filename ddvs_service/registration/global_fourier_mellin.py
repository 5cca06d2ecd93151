"""Direct (intensity-based) hypotheses for the global initialiser: Fourier–Mellin registration.

1. Rotation and scale. The magnitude spectrum is invariant to translation; a similarity `p = s R(θ) p* + t` of the
   image (pixels, R(θ) rotates from +u towards +v) rotates the magnitude spectrum by θ and shrinks it by 1/s. In
   log-polar coordinates (`kernels/logpolar.py`: log radius in cycles/pixel, angle over [0, π) because |F(−f)| = |F(f)|)
   this is a shift `(−log s, θ)`, found by phase correlation. Each peak gives θ mod π, so both θ and θ + π are kept
   (the 180° ambiguity). Spectra are high-pass weighted log-magnitudes of zero-mean, Hann-windowed images.
2. Translation. For each (θ, s) the reference ROI, zero-mean and Hann-weighted, is rotated and scaled into a canvas
   and phase-correlated with the zero-padded current image (so a ROI partly outside the image is still found); each
   correlation peak gives a similarity homography `G` from reference to current pixels.

Every returned hypothesis carries its robust photometric cost (`global_cost.py`) before refinement.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ddvs_service.registration.global_cost import PhotometricScore, photometric_score, sample_through
from kernels.global_warp import warp_homography
from kernels.logpolar import logpolar_resample

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
Roi = tuple[int, int, int, int]


@dataclass(frozen=True)
class FourierMellinConfig:
    """Sampling and search parameters of the Fourier–Mellin hypothesis generator."""

    n_theta: int = 180  # angle bins over [0, π) → 1° per bin
    n_rho: int = 96  # log-radius bins over rho_range
    rho_range: tuple[float, float] = (0.03, 0.45)  # cycles per pixel
    scale_range: tuple[float, float] = (0.6, 1.6)  # apparent ROI scale searched (current / reference)
    rotation_scale_peaks: int = 3  # (θ mod π, s) peaks kept
    translation_peaks: int = 2  # translation peaks kept per (θ, s)
    context: float = 2.5  # reference spectrum window = ROI grown by this factor (clipped to the image)
    whitening_floor: float = 1e-2  # phase correlation: X / (|X| + floor · max|X|)


@dataclass(frozen=True)
class Hypothesis:
    """A starting warp `G` (3×3, reference pixels → current pixels, det 1) and where it came from."""

    G: F64
    source: str
    score: PhotometricScore


def hann2d(h: int, w: int) -> F32:
    """Separable Hann window (h, w), float32."""
    return np.outer(np.hanning(h), np.hanning(w)).astype(np.float32)


def _highpass(h: int, w: int) -> F32:
    """Reddy–Chatterji high-pass emphasis on a centred frequency grid (0 at DC, ≈ 2 at the corners)."""
    fy = np.cos(np.pi * (np.arange(h) - h // 2) / h)
    fx = np.cos(np.pi * (np.arange(w) - w // 2) / w)
    x = np.outer(fy, fx)
    return ((1.0 - x) * (2.0 - x)).astype(np.float32)


def log_spectrum(image: F32) -> F32:
    """High-pass weighted log-magnitude spectrum (fft-shifted) of a zero-mean Hann-windowed image."""
    h, w = image.shape
    windowed = (image - image.mean()) * hann2d(h, w)
    mag = np.abs(np.fft.fftshift(np.fft.fft2(windowed)))
    return (np.log1p(mag) * _highpass(h, w)).astype(np.float32)


def log_polar(spectrum: F32, cfg: FourierMellinConfig) -> F32:
    """Log-polar resampling (n_rho × n_theta) of a centred spectrum, zero-mean with a Hann taper along log-radius."""
    lo, hi = cfg.rho_range
    dlog = np.log(hi / lo) / (cfg.n_rho - 1)
    out = np.empty((cfg.n_rho, cfg.n_theta), np.float32)
    logpolar_resample(np.ascontiguousarray(spectrum), out, float(np.log(lo)), float(dlog), float(np.pi / cfg.n_theta))
    out -= out.mean(axis=1, keepdims=True)
    return out * np.hanning(cfg.n_rho).astype(np.float32)[:, None]


def phase_correlation(a: F32, b: F32, floor: float) -> F32:
    """Correlation surface whose peak sits at the cyclic shift d with b(x) ≈ a(x − d) (arrays of equal shape)."""
    X = np.fft.fft2(b) * np.conj(np.fft.fft2(a))
    mag = np.abs(X)
    return np.fft.ifft2(X / (mag + floor * mag.max() + 1e-30)).real.astype(np.float32)


def _subpixel(surface: F32, r: int, c: int) -> tuple[float, float]:
    """Parabolic refinement of a peak at (r, c) (cyclic neighbours)."""
    h, w = surface.shape

    def offset(m: float, z: float, p: float) -> float:
        d = m - 2.0 * z + p
        return 0.5 * (m - p) / d if d < 0 else 0.0

    dr = offset(surface[(r - 1) % h, c], surface[r, c], surface[(r + 1) % h, c])
    dc = offset(surface[r, (c - 1) % w], surface[r, c], surface[r, (c + 1) % w])
    return r + dr, c + dc


def peaks(surface: F32, k: int, radius: int, allowed: NDArray[np.bool_] | None = None) -> list[tuple[float, float]]:
    """Up to k strongest peaks (sub-pixel row, col), each suppressing a cyclic (2·radius+1)² neighbourhood."""
    s = surface.copy()
    if allowed is not None:
        s[~allowed] = -np.inf
    h, w = s.shape
    found = []
    for _ in range(k):
        idx = int(np.argmax(s))
        r, c = divmod(idx, w)
        if not np.isfinite(s[r, c]):
            break
        found.append(_subpixel(surface, r, c))
        rows = np.arange(r - radius, r + radius + 1) % h
        cols = np.arange(c - radius, c + radius + 1) % w
        s[np.ix_(rows, cols)] = -np.inf
    return found


def rotation_scale_candidates(reference_window: F32, current: F32, cfg: FourierMellinConfig) -> list[tuple[float, float]]:
    """(θ mod π radians, s) candidates for `current` ≈ `reference_window` rotated by θ and scaled by s."""
    lp_ref = log_polar(log_spectrum(reference_window), cfg)
    lp_cur = log_polar(log_spectrum(current), cfg)
    n_rho = cfg.n_rho
    pad = np.zeros((2 * n_rho, cfg.n_theta), np.float32)
    a, b = pad.copy(), pad.copy()
    a[:n_rho], b[:n_rho] = lp_ref, lp_cur
    surface = phase_correlation(a, b, cfg.whitening_floor)
    dlog = np.log(cfg.rho_range[1] / cfg.rho_range[0]) / (n_rho - 1)
    shifts = np.arange(2 * n_rho)
    shifts = np.where(shifts >= n_rho, shifts - 2 * n_rho, shifts)  # signed log-radius shift in bins
    scales = np.exp(-shifts * dlog)
    allowed = ((scales >= cfg.scale_range[0]) & (scales <= cfg.scale_range[1]))[:, None] & np.ones(
        (1, cfg.n_theta), bool
    )
    found = []
    for r, c in peaks(surface, cfg.rotation_scale_peaks, radius=2, allowed=allowed):
        shift = r if r < n_rho else r - 2 * n_rho
        found.append((float(c * np.pi / cfg.n_theta) % np.pi, float(np.exp(-shift * dlog))))
    return found


def similarity(theta: float, scale: float, src_centre: tuple[float, float], dst_centre: tuple[float, float]) -> F64:
    """Homography `p = s R(θ) (p* − src_centre) + dst_centre` normalised to det 1."""
    c, s = np.cos(theta), np.sin(theta)
    A = np.array([[scale * c, -scale * s, 0.0], [scale * s, scale * c, 0.0], [0.0, 0.0, 1.0]])
    T_src = np.array([[1.0, 0, -src_centre[0]], [0, 1.0, -src_centre[1]], [0, 0, 1.0]])
    T_dst = np.array([[1.0, 0, dst_centre[0]], [0, 1.0, dst_centre[1]], [0, 0, 1.0]])
    G = T_dst @ A @ T_src
    return G / np.cbrt(np.linalg.det(G))


def reference_window(reference: F32, roi: Roi, context: float) -> F32:
    """The reference image around the ROI, grown by `context` and clipped to the image."""
    x, y, w, h = roi
    H, W = reference.shape
    cx, cy, hw, hh = x + w / 2.0, y + h / 2.0, context * w / 2.0, context * h / 2.0
    x0, x1 = max(0, int(round(cx - hw))), min(W, int(round(cx + hw)))
    y0, y1 = max(0, int(round(cy - hh))), min(H, int(round(cy + hh)))
    return reference[y0:y1, x0:x1]


def translation_hypotheses(
    template: F32, roi: Roi, current: F32, theta: float, scale: float, cfg: FourierMellinConfig
) -> list[F64]:
    """Similarity warps (θ, s fixed) whose translation comes from phase correlation of the warped template."""
    x, y, w, h = roi
    Hc, Wc = current.shape
    m = int(np.ceil(0.5 * scale * np.hypot(w, h))) + 1  # margin: a ROI half outside the image is still found
    ch, cw = Hc + 2 * m, Wc + 2 * m
    canvas_centre = ((cw - 1) / 2.0, (ch - 1) / 2.0)
    weighted = ((template - template.mean()) * hann2d(h, w)).astype(np.float32)
    patch_centre = ((w - 1) / 2.0, (h - 1) / 2.0)
    to_patch = np.linalg.inv(similarity(theta, scale, patch_centre, canvas_centre))
    canvas = np.empty((ch, cw), np.float32)
    valid = np.empty((ch, cw), np.float32)
    warp_homography(weighted, canvas, valid, np.ascontiguousarray(to_patch, np.float32).ravel(), 0.0, 0.0)
    padded = np.zeros((ch, cw), np.float32)
    padded[m : m + Hc, m : m + Wc] = current - current.mean()
    surface = phase_correlation(canvas, padded, cfg.whitening_floor)
    roi_centre = (x + patch_centre[0], y + patch_centre[1])
    hypotheses = []
    for r, c in peaks(surface, cfg.translation_peaks, radius=max(2, int(0.25 * scale * min(w, h)))):
        dr = r if r < ch / 2 else r - ch
        dc = c if c < cw / 2 else c - cw
        centre_in_current = (canvas_centre[0] + dc - m, canvas_centre[1] + dr - m)
        hypotheses.append(similarity(theta, scale, roi_centre, centre_in_current))
    return hypotheses


def fourier_mellin_hypotheses(reference: F32, roi: Roi, current: F32, cfg: FourierMellinConfig) -> list[Hypothesis]:
    """All Fourier–Mellin hypotheses (θ and θ + π for each rotation/scale peak, several translations each), scored."""
    x, y, w, h = roi
    template = reference[y : y + h, x : x + w]
    window = reference_window(reference, roi, cfg.context)
    out = []
    for theta_mod_pi, scale in rotation_scale_candidates(window, current, cfg):
        for theta in (theta_mod_pi, theta_mod_pi + np.pi):
            for G in translation_hypotheses(template, roi, current, theta, scale, cfg):
                sampled, valid = sample_through(current, G, (h, w), (x, y))
                out.append(Hypothesis(G=G, source="fourier-mellin", score=photometric_score(template, sampled, valid)))
    return out
