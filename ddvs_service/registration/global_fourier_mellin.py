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

import cv2
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
    search_width: int = 160  # hypotheses are searched on images downsampled to at most this width
    grid_rotations: int = 18  # uniform rotation grid over 360° added to the log-polar peaks
    grid_scales: int = 3  # scales of the grid, log-spaced strictly inside scale_range
    max_hypotheses: int = 12  # best translation peaks (by correlation height) scored at full resolution


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


def rotation_scale_candidates(
    reference_window: F32, current: F32, cfg: FourierMellinConfig
) -> list[tuple[float, float]]:
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
    x0, x1 = max(0, round(cx - hw)), min(W, round(cx + hw))
    y0, y1 = max(0, round(cy - hh)), min(H, round(cy + hh))
    return reference[y0:y1, x0:x1]


def _dft_size(n: int) -> int:
    """Smallest 2^a·3^b·5^c ≥ n (fast FFT length)."""
    m = n
    while True:
        k = m
        for f in (2, 3, 5):
            while k % f == 0:
                k //= f
        if k == 1:
            return m
        m += 1


def disc(shape: tuple[int, int], centre: tuple[float, float], radius: float) -> F32:
    """1 inside the disc of `radius` pixels around `centre` (u, v), 0 outside."""
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]]
    return ((u - centre[0]) ** 2 + (v - centre[1]) ** 2 <= radius * radius).astype(np.float32)


class TranslationSearch:
    """Normalised cross-correlation of a rotated/scaled disc template against the zero-padded current image, by FFT.

    The template is the disc inscribed in the ROI, so the current image's local sums under it depend only on the
    scale: they are computed once per scale and reused for every rotation. Positions whose local variance is below
    `(0.05 σ_I)²` per pixel (flat or empty areas) are not trusted."""

    def __init__(self, current: F32, margin: int, radius: float) -> None:
        Hc, Wc = current.shape
        self.shape = (_dft_size(Hc + 2 * margin), _dft_size(Wc + 2 * margin))
        self.margin = margin
        self.radius = radius
        padded = np.zeros(self.shape, np.float32)
        padded[margin : margin + Hc, margin : margin + Wc] = current - current.mean()
        self.spectrum = np.fft.rfft2(padded)
        self.spectrum_sq = np.fft.rfft2(padded * padded)
        self.var_floor = (0.05 * float(current.std())) ** 2
        self.centre = (float(self.shape[1] // 2), float(self.shape[0] // 2))
        self._local_std: dict[float, tuple[F32, F32]] = {}

    def _disc_stats(self, scale: float) -> tuple[F32, F32]:
        """(disc mask at the canvas centre, local standard deviation × √N of the current image under it)."""
        if scale not in self._local_std:
            mask = disc(self.shape, self.centre, scale * self.radius)
            F = np.conj(np.fft.rfft2(mask))
            n = float(mask.sum())
            s1 = np.fft.irfft2(self.spectrum * F, s=self.shape)
            s2 = np.fft.irfft2(self.spectrum_sq * F, s=self.shape)
            var = np.maximum(s2 - s1 * s1 / n, n * self.var_floor)
            self._local_std[scale] = (mask, np.sqrt(var).astype(np.float32))
        return self._local_std[scale]

    def peaks(
        self, template: F32, theta: float, scale: float, k: int
    ) -> list[tuple[float, tuple[float, float]]]:
        """Up to k (NCC value, where the template centre lands in the current image) for the template turned by θ
        and scaled by s."""
        h, w = template.shape
        mask, local_std = self._disc_stats(scale)
        to_patch = np.linalg.inv(similarity(theta, scale, ((w - 1) / 2.0, (h - 1) / 2.0), self.centre))
        canvas = np.empty(self.shape, np.float32)
        valid = np.empty(self.shape, np.float32)
        warp_homography(template, canvas, valid, np.ascontiguousarray(to_patch, np.float32).ravel(), 0.0, 0.0)
        inside = mask * valid
        canvas = (canvas - float((canvas * inside).sum()) / max(float(inside.sum()), 1.0)) * inside
        norm = float(np.sqrt((canvas * canvas).sum()))
        if norm == 0.0:
            return []
        ncc = np.fft.irfft2(self.spectrum * np.conj(np.fft.rfft2(canvas)), s=self.shape) / (norm * local_std)
        ch, cw = self.shape
        found = []
        for r, c in peaks(ncc.astype(np.float32), k, radius=max(2, int(0.5 * scale * self.radius))):
            dr = r if r < ch / 2 else r - ch
            dc = c if c < cw / 2 else c - cw
            value = float(ncc[round(r) % ch, round(c) % cw])
            found.append((value, (self.centre[0] + dc - self.margin, self.centre[1] + dr - self.margin)))
        return found


def _rescale_pixels(factor: float) -> F64:
    """Homography from full-resolution pixel centres to those of an image downsampled by `factor`."""
    return np.array([[1.0 / factor, 0.0, 0.5 / factor - 0.5], [0.0, 1.0 / factor, 0.5 / factor - 0.5], [0, 0, 1.0]])


def rotation_scale_grid(cfg: FourierMellinConfig) -> list[tuple[float, float]]:
    """Uniform (θ, s) grid over ±180° and the scale range: guarantees coverage where the spectrum peaks miss."""
    lo, hi = cfg.scale_range
    thetas = np.arange(cfg.grid_rotations) * (2.0 * np.pi / cfg.grid_rotations)
    scales = np.exp(np.linspace(np.log(lo), np.log(hi), cfg.grid_scales + 2)[1:-1])
    return [(float(t), float(s)) for t in thetas for s in scales]


def fourier_mellin_hypotheses(reference: F32, roi: Roi, current: F32, cfg: FourierMellinConfig) -> list[Hypothesis]:
    """Ranked similarity hypotheses (lowest photometric cost first) for the reference ROI in the current image.

    Search runs on images downsampled so the current one is at most `cfg.search_width` wide; (θ, s) candidates are
    the log-polar peaks (θ and θ + π) followed by the uniform grid; every candidate's translation peaks are ranked by
    correlation height and the best `cfg.max_hypotheses` are scored photometrically at full resolution."""
    x, y, w, h = roi
    factor = max(1.0, current.shape[1] / cfg.search_width)
    D = _rescale_pixels(factor)
    small_ref = cv2.resize(reference, None, fx=1.0 / factor, fy=1.0 / factor, interpolation=cv2.INTER_AREA)
    small_cur = cv2.resize(current, None, fx=1.0 / factor, fy=1.0 / factor, interpolation=cv2.INTER_AREA)
    sx0, sy0 = D[0, 0] * x + D[0, 2], D[1, 1] * y + D[1, 2]
    sx, sy = int(np.floor(sx0 + 0.5)), int(np.floor(sy0 + 0.5))
    sw, sh = max(8, round(w / factor)), max(8, round(h / factor))
    sroi = (sx, sy, sw, sh)
    template = np.ascontiguousarray(small_ref[sy : sy + sh, sx : sx + sw])
    window = reference_window(small_ref, sroi, cfg.context)
    peaks_mod_pi = rotation_scale_candidates(window, small_cur, cfg)
    candidates = [(t, s) for t_mod_pi, s in peaks_mod_pi for t in (t_mod_pi, t_mod_pi + np.pi)]
    candidates += rotation_scale_grid(cfg)
    radius = 0.5 * min(sw, sh)
    search = TranslationSearch(small_cur, int(np.ceil(cfg.scale_range[1] * radius)) + 1, radius)
    ranked = []
    for theta, scale in candidates:
        for value, centre in search.peaks(template, theta, scale, cfg.translation_peaks):
            ranked.append((value, theta, scale, centre))
    ranked.sort(key=lambda item: -item[0])
    small_centre = (sx + (sw - 1) / 2.0, sy + (sh - 1) / 2.0)
    full_template = reference[y : y + h, x : x + w]
    out = []
    for _, theta, scale, centre in ranked[: cfg.max_hypotheses]:
        G = np.linalg.inv(D) @ similarity(theta, scale, small_centre, centre) @ D
        G /= np.cbrt(np.linalg.det(G))
        sampled, valid = sample_through(current, G, (h, w), (x, y))
        out.append(Hypothesis(G=G, source="fourier-mellin", score=photometric_score(full_template, sampled, valid)))
    out.sort(key=lambda hyp: hyp.score.cost)
    return out
