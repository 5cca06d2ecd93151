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

from ddvs_service.registration.global_cost import PhotometricScore, photometric_scores, sample_through
from ddvs_service.registration.images import build_pyramid, level_matrix
from kernels.exclusive import GATE
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
    scale_range: tuple[float, float] = (0.6, 1.6)  # apparent ROI scale (current / reference) of the log-polar peaks
    rotation_scale_peaks: int = 3  # (θ mod π, s) peaks kept
    translation_peaks: int = 2  # translation peaks kept per (θ, s)
    context: float = 2.5  # reference spectrum window = ROI grown by this factor (clipped to the image)
    whitening_floor: float = 1e-2  # phase correlation: X / (|X| + floor · max|X|)
    search_width: int = 160  # search on the pyramid level that brings the current image to at most this width …
    min_search_roi: int = 32  # … unless the ROI would fall below this many pixels a side there
    grid_rotations: int = 18  # uniform rotation grid over 360° added to the log-polar peaks
    # The grid's scales, log-spaced strictly inside grid_scale_range (0.72, 0.95, 1.25, 1.66): wider than the peaks'
    # range, for the views the spectrum peaks miss — a camera 0.4 m closer to a target 1 m away, and tilted, sees it
    # magnified ~1.8× (the screening takes a grid start within ~15 % of the scale into its basin). The peaks' range
    # stays narrower: wider, a peak of a wrong warp can win under a large occluder (tests/test_global_init.py).
    grid_scales: int = 4
    grid_scale_range: tuple[float, float] = (0.55, 2.2)
    max_hypotheses: int = 36  # best translation peaks (by correlation height) scored at the search level

    @property
    def max_scale(self) -> float:
        """The largest apparent scale any stage searches (the translation search's template box)."""
        return max(self.scale_range[1], self.grid_scale_range[1])


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
    GATE.checkpoint()
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


def log_polar_spectrum(image: F32, cfg: FourierMellinConfig) -> F32:
    """The log-polar resampling (`log_polar`) of the image's high-pass weighted log-magnitude spectrum."""
    return log_polar(log_spectrum(image), cfg)


def rotation_scale_peaks(lp_ref: F32, lp_cur: F32, cfg: FourierMellinConfig) -> list[tuple[float, float]]:
    """(θ mod π radians, s) candidates from the log-polar spectra (`log_polar_spectrum`) of a reference window and
    of the current image: current ≈ reference rotated by θ and scaled by s."""
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


def rotation_scale_candidates(
    reference_window: F32, current: F32, cfg: FourierMellinConfig
) -> list[tuple[float, float]]:
    """(θ mod π radians, s) candidates for `current` ≈ `reference_window` rotated by θ and scaled by s."""
    return rotation_scale_peaks(log_polar_spectrum(reference_window, cfg), log_polar_spectrum(current, cfg), cfg)


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


def dft_size(n: int) -> int:
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


@dataclass(frozen=True)
class TranslationPeak:
    """A translation peak of the template turned by `theta` (radians) and scaled by `scale`: its NCC `value` and
    where the template centre lands in the current image (`centre`, search pixels)."""

    value: float
    theta: float
    scale: float
    centre: tuple[float, float]


class TranslationSearch:
    """Normalised cross-correlation of rotated/scaled disc templates against the zero-padded current image, by FFT.

    Every (θ, s) template is rendered in one Taichi launch into a small odd-sized box (the template centre at the box
    centre), and all are correlated in one batched FFT. The template is the disc inscribed in the ROI, so the current
    image's local sums under it depend only on the scale: computed once per scale. Positions whose local variance is
    below `(0.05 σ_I)²` per pixel (flat or empty areas) are not trusted."""

    def __init__(self, current: F32, template: F32, max_scale: float) -> None:
        h, w = template.shape
        self.template = np.ascontiguousarray(template, np.float32)
        self.radius = 0.5 * min(w, h)
        half = int(np.ceil(max_scale * self.radius)) + 1
        self.box = 2 * half + 1
        self.box_centre = float(half)
        self.margin = half
        Hc, Wc = current.shape
        self.shape = (dft_size(Hc + 2 * half), dft_size(Wc + 2 * half))
        padded = np.zeros(self.shape, np.float32)
        padded[half : half + Hc, half : half + Wc] = current - current.mean()
        self.spectrum = np.fft.rfft2(padded)
        GATE.checkpoint()  # a frame waiting for Taichi goes first after each transform (`kernels.exclusive`)
        self.spectrum_sq = np.fft.rfft2(padded * padded)
        self.var_floor = (0.05 * float(current.std())) ** 2
        self._local_std: dict[float, F32] = {}

    def _masks(self, scales: F64) -> F32:
        """Disc masks (N, box, box) of radius `s · radius` around the box centre."""
        v, u = np.mgrid[0 : self.box, 0 : self.box] - self.box_centre
        r2 = (u * u + v * v)[None]
        return (r2 <= (scales[:, None, None] * self.radius) ** 2).astype(np.float32)

    def _local_std_for(self, scale: float, mask: F32) -> F32:
        """Local standard deviation × √N of the current image under the disc of this scale at every shift."""
        if scale not in self._local_std:
            F = np.conj(np.fft.rfft2(mask, s=self.shape))
            n = float(mask.sum())
            s1 = np.fft.irfft2(self.spectrum * F, s=self.shape)
            GATE.checkpoint()
            s2 = np.fft.irfft2(self.spectrum_sq * F, s=self.shape)
            self._local_std[scale] = np.sqrt(np.maximum(s2 - s1 * s1 / n, n * self.var_floor)).astype(np.float32)
        return self._local_std[scale]

    def peaks(self, rotations_scales: list[tuple[float, float]], k: int) -> list[TranslationPeak]:
        """Up to k translation peaks for each (θ, s): the template turned by θ and scaled by s."""
        h, w = self.template.shape
        c = self.box_centre
        to_template = np.stack([np.linalg.inv(similarity(t, s, ((w - 1) / 2.0, (h - 1) / 2.0), (c, c)))
                                for t, s in rotations_scales])
        boxes, valid = sample_through(self.template, to_template, (self.box, self.box), (0.0, 0.0))
        scales = np.array([s for _, s in rotations_scales])
        inside = self._masks(scales) * valid
        count = np.maximum(inside.sum(axis=(1, 2)), 1.0)
        boxes = (boxes - ((boxes * inside).sum(axis=(1, 2)) / count)[:, None, None]) * inside
        norms = np.sqrt((boxes * boxes).sum(axis=(1, 2)))
        ch, cw = self.shape
        found = []
        for i, (theta, scale) in enumerate(rotations_scales):
            GATE.checkpoint()  # one candidate's transforms between checkpoints, not all of them
            if norms[i] == 0.0:
                continue
            # one candidate at a time: the batched transform is slower (its complex arrays leave the cache)
            corr = np.fft.irfft2(self.spectrum * np.conj(np.fft.rfft2(boxes[i], s=self.shape)), s=self.shape)
            ncc = corr / (norms[i] * self._local_std_for(scale, self._masks(scales[i : i + 1])[0]))
            for r, col in peaks(ncc, k, radius=max(2, int(0.5 * scale * self.radius))):
                # cyclic shift (r, col) puts the box centre at padded pixel (c + col, c + r) mod the canvas
                value = float(ncc[round(r) % ch, round(col) % cw])
                centre = ((c + col) % cw - self.margin, (c + r) % ch - self.margin)
                found.append(TranslationPeak(value, theta, scale, (float(centre[0]), float(centre[1]))))
        return found


def level_roi(roi: Roi, level: int) -> Roi:
    """The ROI `(x, y, w, h)` at pyramid `level`: the level pixels whose footprint lies inside it (the planar
    engine's level ROI)."""
    x, y, w, h = roi
    k = 2**level
    u0, v0 = -(-x // k), -(-y // k)
    u1, v1 = (x + w) // k - 1, (y + h) // k - 1
    return u0, v0, u1 - u0 + 1, v1 - v0 + 1


@dataclass(frozen=True)
class SearchReference:
    """The reference side of the search, computed once per (reference, ROI): the search pyramid `level`
    (`images.build_pyramid`, `D` = full-resolution → level pixels), the reference there (`image`) and one level
    coarser (`coarse`, where the screening starts), the ROI at the search level (`roi`), its `template`, and the
    log-polar spectrum of the reference window around it (`spectrum`)."""

    level: int
    D: F64
    image: F32
    coarse: F32
    roi: Roi
    template: F32
    spectrum: F32

    @staticmethod
    def build(reference: F32, roi: Roi, cfg: FourierMellinConfig) -> SearchReference:
        """The coarsest level at which the ROI keeps `cfg.min_search_roi` pixels a side, and no coarser than needed
        to bring the image down to `cfg.search_width` pixels wide."""
        w, h = roi[2], roi[3]
        level = 0
        while (min(w, h) >> (level + 1)) >= cfg.min_search_roi and (reference.shape[1] >> level) > cfg.search_width:
            level += 1
        pyramid = build_pyramid(reference, level + 2)
        sroi = level_roi(roi, level)
        u0, v0, sw, sh = sroi
        template = np.ascontiguousarray(pyramid[level][v0 : v0 + sh, u0 : u0 + sw])
        spectrum = log_polar_spectrum(reference_window(pyramid[level], sroi, cfg.context), cfg)
        return SearchReference(level, level_matrix(level), pyramid[level], pyramid[level + 1], sroi, template,
                               spectrum)


@dataclass(frozen=True)
class SearchPair:
    """The reference side and the current image at the search level (`current`) and one level coarser
    (`coarse`). Hypotheses are searched and ranked at the search level."""

    reference: SearchReference
    current: F32
    coarse: F32

    @staticmethod
    def build(reference: SearchReference, current: F32) -> SearchPair:
        """The current image's pyramid down to one level below the search level (same size as the reference)."""
        pyramid = build_pyramid(current, reference.level + 2)
        GATE.checkpoint()
        return SearchPair(reference, pyramid[reference.level], pyramid[reference.level + 1])

    @property
    def roi(self) -> Roi:
        return self.reference.roi

    @property
    def template(self) -> F32:
        return self.reference.template

    def to_level(self, G: F64) -> F64:
        """A full-resolution warp expressed in level pixels (`D G D⁻¹`)."""
        D = self.reference.D
        return D @ G @ np.linalg.inv(D)

    def to_full(self, G_level: F64) -> F64:
        """A level warp expressed in full-resolution pixels (`D⁻¹ G D`), det 1."""
        D = self.reference.D
        G = np.linalg.inv(D) @ G_level @ D
        return G / np.cbrt(np.linalg.det(G))

    def scores(self, Gs: list[F64]) -> list[PhotometricScore]:
        """Robust photometric scores (`global_cost`) of full-resolution warps, evaluated at this level."""
        if not Gs:
            return []
        x, y, w, h = self.roi
        sampled, valid = sample_through(self.current, np.stack([self.to_level(G) for G in Gs]), (h, w), (x, y))
        return photometric_scores(self.template, sampled, valid)


def rotation_scale_grid(cfg: FourierMellinConfig) -> list[tuple[float, float]]:
    """Uniform (θ, s) grid over ±180° and `grid_scale_range`: guarantees coverage where the spectrum peaks miss."""
    lo, hi = cfg.grid_scale_range
    thetas = np.arange(cfg.grid_rotations) * (2.0 * np.pi / max(cfg.grid_rotations, 1))
    scales = np.exp(np.linspace(np.log(lo), np.log(hi), cfg.grid_scales + 2)[1:-1])
    return [(float(t), float(s)) for t in thetas for s in scales]


def rotation_scale_stages(search: SearchPair, cfg: FourierMellinConfig) -> list[list[tuple[float, float]]]:
    """(θ, s) candidates in two stages: the log-polar peaks (θ and θ + π), then the uniform grid (the fallback
    where the spectrum peaks miss; the initialiser searches it only when the first stage gave no clear winner)."""
    peaks_mod_pi = rotation_scale_peaks(search.reference.spectrum, log_polar_spectrum(search.current, cfg), cfg)
    return [[(t, s) for t_mod_pi, s in peaks_mod_pi for t in (t_mod_pi, t_mod_pi + np.pi)], rotation_scale_grid(cfg)]


def translation_hypotheses(
    search: SearchPair, translation: TranslationSearch, candidates: list[tuple[float, float]], cfg: FourierMellinConfig
) -> list[Hypothesis]:
    """Similarity hypotheses (full-resolution `G`, lowest photometric cost first) for (θ, s) `candidates`: every
    candidate's translation peaks are ranked by correlation height and the best `cfg.max_hypotheses` are scored
    photometrically at the search level."""
    x, y, w, h = search.roi
    ranked = sorted(translation.peaks(candidates, cfg.translation_peaks), key=lambda p: -p.value)
    centre = (x + (w - 1) / 2.0, y + (h - 1) / 2.0)
    Gs = [search.to_full(similarity(p.theta, p.scale, centre, p.centre)) for p in ranked[: cfg.max_hypotheses]]
    found = [Hypothesis(G=G, source="fourier-mellin", score=s) for G, s in zip(Gs, search.scores(Gs), strict=True)]
    return sorted(found, key=lambda hyp: hyp.score.cost)


def fourier_mellin_hypotheses(search: SearchPair, cfg: FourierMellinConfig) -> list[Hypothesis]:
    """Every stage's hypotheses at once (lowest photometric cost first)."""
    translation = TranslationSearch(search.current, search.template, cfg.max_scale)
    found = [h for stage in rotation_scale_stages(search, cfg) for h in translation_hypotheses(search, translation,
                                                                                                  stage, cfg)]
    return sorted(found, key=lambda hyp: hyp.score.cost)
