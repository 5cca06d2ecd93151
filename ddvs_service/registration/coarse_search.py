"""Cold-start search of the planar engine: where, and about how turned, the ROI lies in the current image at the
coarsest level.

Gauss-Newton from identity only finds a shift within its basin (a few level pixels); a larger shift under a strong
blur difference (Oxford bikes 1→4: 43 px, 5.4 px at the coarsest level of a 200×150 ROI) lies outside it. This
search turns the reference ROI and its usable-pixel map by each angle of `ROTATIONS_DEG` (`global_cost.
sample_through`, one batched bilinear launch each), scores every shift of the turned ROI up to `REACH` × the ROI's
larger side along each axis by masked normalised cross-correlation (Padfield, "Masked object registration in the
Fourier domain", IEEE TIP 2012: three correlations by FFT per angle), and returns the rigid warp of the best score,
its shift refined to sub-pixel by a parabola (`global_fourier_mellin.peaks`). The engine's translation-only, then
similarity Gauss-Newton continues from there. Without the angles, an ROI turned by 16–24° correlates best at a wrong
shift (measured), where Gauss-Newton from identity would have converged.

Only shifts that keep the whole turned ROI inside the searched window are scored: `global_fourier_mellin.
TranslationSearch` zero-pads instead, and its floored variance over the padding can rank a shift half outside the
image first.

Coordinates: level pixels of one pyramid level, 0-based pixel centres (u = column, v = row); `bounds = (u0, v0, u1,
v1)` inclusive. Angles turn from +u towards +v.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from ddvs_service.registration.global_cost import sample_through
from ddvs_service.registration.global_fourier_mellin import dft_size, peaks, similarity
from kernels.planar_step import MASK_LIMIT

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
ROTATIONS_DEG = (-20.0, -10.0, 0.0, 10.0, 20.0)  # the similarity Gauss-Newton then covers ±5° around each
REACH = 0.5  # searched shifts: up to this fraction of the ROI's larger side (level pixels) along each axis
VARIANCE_FLOOR = 0.05  # a window position whose standard deviation is below this × the window's is not trusted
FULL = 1.0 - 1e-4  # a sampled usable-map value at least this: all four bilinear neighbours usable


def usable_pixels(reference: F32, bounds: tuple[int, int, int, int]) -> F32:
    """1 on the ROI's pixels whose 3×3 neighbourhood is unmasked, else 0 (level-sized). A filtered pixel next to a
    masked one can hold a mixture above `MASK_LIMIT` (measured at levels 3 and 4, never further than one pixel)."""
    u0, v0, u1, v1 = bounds
    unmasked = np.pad(reference, 1, mode="edge")[v0 : v1 + 3, u0 : u1 + 3] > MASK_LIMIT
    usable = np.zeros(reference.shape, dtype=np.float32)
    usable[v0 : v1 + 1, u0 : u1 + 1] = sliding_window_view(unmasked, (3, 3)).all(axis=(2, 3))
    return usable


def coarse_alignment(reference: F32, current: F32, bounds: tuple[int, int, int, int]) -> F64 | None:
    """The rigid warp (3×3, level pixels of the reference → of the current image; angle from `ROTATIONS_DEG`, shift
    sub-pixel) that best aligns the reference ROI `bounds` with `current` (same level, same size) by masked normalised
    cross-correlation, over shifts of the ROI centre of up to `REACH` × the ROI's larger side (module docstring).
    Masked reference pixels (≤ `MASK_LIMIT`) and their neighbours take no part. `None` when the ROI or the window is
    flat."""
    from kernels.backend import init

    init()
    u0, v0, u1, v1 = bounds
    if not (0 <= u0 <= u1 < reference.shape[1] and 0 <= v0 <= v1 < reference.shape[0]):
        raise ValueError(f"ROI bounds {bounds} are not inside the {reference.shape[1]}×{reference.shape[0]} level")
    if current.shape != reference.shape:
        raise ValueError(f"current level is {current.shape[1]}×{current.shape[0]}, expected the reference's "
                         f"{reference.shape[1]}×{reference.shape[0]}")
    centre = (0.5 * (u0 + u1), 0.5 * (v0 + v1))
    thetas = np.deg2rad(ROTATIONS_DEG)
    # One box holds every turned ROI, centred on the box centre `half`.
    half = (math.ceil(max(0.5 * (u1 - u0) * abs(math.cos(t)) + 0.5 * (v1 - v0) * abs(math.sin(t)) for t in thetas)),
            math.ceil(max(0.5 * (u1 - u0) * abs(math.sin(t)) + 0.5 * (v1 - v0) * abs(math.cos(t)) for t in thetas)))
    box = (2 * half[1] + 1, 2 * half[0] + 1)
    # Box pixel → reference pixel: the inverse of turning by θ about `centre` onto the box centre `half`.
    to_reference = np.stack([similarity(-t, 1.0, (float(half[0]), float(half[1])), centre) for t in thetas])
    usable = usable_pixels(reference, bounds)
    values, _ = sample_through(np.ascontiguousarray(reference * usable), to_reference, box, (0.0, 0.0))
    cover, _ = sample_through(usable, to_reference, box, (0.0, 0.0))
    masks = (cover >= FULL).astype(np.float64)
    n = masks.sum(axis=(1, 2))
    if not n.min() > 1.0:
        return None
    templates = (values - ((values * masks).sum(axis=(1, 2)) / n)[:, None, None]) * masks
    energy = (templates * templates).sum(axis=(1, 2))

    reach = math.ceil(REACH * max(u1 - u0, v1 - v0))
    x0, y0 = max(0, math.floor(centre[0]) - half[0] - reach), max(0, math.floor(centre[1]) - half[1] - reach)
    x1 = min(current.shape[1], math.ceil(centre[0]) + half[0] + reach + 1)
    y1 = min(current.shape[0], math.ceil(centre[1]) + half[1] + reach + 1)
    window = current[y0:y1, x0:x1].astype(np.float64)
    window -= window.mean()
    spread = float(window.std())
    if not (energy.min() > 0.0 and spread > 0.0):
        return None
    shape = (dft_size(window.shape[0]), dft_size(window.shape[1]))

    def correlate(image_spectrum: NDArray[np.complex128], kernels: F64) -> F64:
        """Σ_q kernel_k(q) · image(q + d) for every kernel k and cyclic shift d of the canvas."""
        return np.fft.irfft2(image_spectrum * np.conj(np.fft.rfft2(kernels, s=shape)), s=shape)

    spectrum, spectrum_sq = np.fft.rfft2(window, s=shape), np.fft.rfft2(window * window, s=shape)
    s1 = correlate(spectrum, masks)
    variance = np.maximum(correlate(spectrum_sq, masks) - s1 * s1 / n[:, None, None],
                          n[:, None, None] * (VARIANCE_FLOOR * spread) ** 2)
    ncc = correlate(spectrum, templates) / np.sqrt(energy[:, None, None] * variance)
    # Shifts d (box pixel q lands on window pixel q + d) that keep every masked pixel inside the window: rows
    # lo … hi, negative ones at the end of the cyclic canvas.
    allowed = np.zeros(ncc.shape, dtype=bool)
    ranges = []
    for k, mask in enumerate(masks):
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        ranges.append((window.shape[0] - 1 - rows[-1], window.shape[1] - 1 - cols[-1]))
        allowed[k][np.ix_(np.arange(-rows[0], ranges[k][0] + 1) % shape[0],
                          np.arange(-cols[0], ranges[k][1] + 1) % shape[1])] = True
    best = int(np.argmax(np.where(allowed, ncc, -np.inf).reshape(len(thetas), -1).max(axis=1)))
    (r, c), = peaks(ncc[best].astype(np.float32), 1, radius=1, allowed=allowed[best])
    r = r - shape[0] if r > ranges[best][0] + 0.5 else r
    c = c - shape[1] if c > ranges[best][1] + 0.5 else c
    return similarity(float(thetas[best]), 1.0, centre, (x0 + c + half[0], y0 + r + half[1]))
