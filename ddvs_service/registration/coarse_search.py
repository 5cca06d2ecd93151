"""Cold-start translation search of the planar engine: where the ROI lies in the current image at the coarsest level.

Gauss-Newton from identity only finds a shift within its basin (a few level pixels); a larger shift under a strong
blur difference (Oxford bikes 1→4: 43 px, 5.4 px at the coarsest level of a 200×150 ROI) lies outside it. This search
scores every shift of the reference ROI up to `REACH` × the ROI's larger side along each axis by masked normalised
cross-correlation (Padfield, "Masked object registration in the Fourier domain", IEEE TIP 2012: three correlations by
FFT), and returns the best one, refined to sub-pixel by a parabola (`global_fourier_mellin.peaks`). The engine's
translation-only Gauss-Newton continues from there.

Only shifts that keep the whole ROI inside the searched window are scored: `global_fourier_mellin.TranslationSearch`
zero-pads instead, and its floored variance over the padding can rank a shift half outside the image first.

Coordinates: level pixels of one pyramid level, 0-based pixel centres; `bounds = (u0, v0, u1, v1)` inclusive.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from ddvs_service.registration.global_fourier_mellin import _dft_size, peaks
from kernels.planar_step import MASK_LIMIT

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
REACH = 0.5  # searched shifts: up to this fraction of the ROI's larger side (level pixels) along each axis
VARIANCE_FLOOR = 0.05  # a window position whose standard deviation is below this × the window's is not trusted


def coarse_translation(reference: F32, current: F32, bounds: tuple[int, int, int, int]) -> F64 | None:
    """The translation (3×3, level pixels of the reference → of the current image) that best aligns the reference ROI
    `bounds` with `current` (same level, same size) by masked normalised cross-correlation over shifts of up to
    `REACH` × the ROI's larger side; masked reference pixels (≤ `MASK_LIMIT`) and their neighbours take no part.
    `None` when the ROI or the window is flat."""
    u0, v0, u1, v1 = bounds
    if not (0 <= u0 <= u1 < reference.shape[1] and 0 <= v0 <= v1 < reference.shape[0]):
        raise ValueError(f"ROI bounds {bounds} are not inside the {reference.shape[1]}×{reference.shape[0]} level")
    if current.shape != reference.shape:
        raise ValueError(f"current level is {current.shape[1]}×{current.shape[0]}, expected the reference's "
                         f"{reference.shape[1]}×{reference.shape[0]}")
    template = reference[v0 : v1 + 1, u0 : u1 + 1].astype(np.float64)
    # A filtered pixel next to a masked one can hold a mixture above MASK_LIMIT (measured at levels 3 and 4,
    # never further than one pixel away): a reference pixel counts when its whole 3×3 neighbourhood is unmasked.
    unmasked = np.pad(reference, 1, mode="edge")[v0 : v1 + 3, u0 : u1 + 3] > MASK_LIMIT
    mask = sliding_window_view(unmasked, (3, 3)).all(axis=(2, 3)).astype(np.float64)
    n = float(mask.sum())
    t = (template - float((template * mask).sum()) / max(n, 1.0)) * mask
    t_energy = float((t * t).sum())
    reach = math.ceil(REACH * max(u1 - u0, v1 - v0))
    x0, y0 = max(0, u0 - reach), max(0, v0 - reach)
    window = current[y0 : min(current.shape[0], v1 + 1 + reach), x0 : min(current.shape[1], u1 + 1 + reach)]
    window = window.astype(np.float64) - float(window.mean())
    spread = float(window.std())
    if not (t_energy > 0.0 and spread > 0.0):
        return None
    shape = (_dft_size(window.shape[0]), _dft_size(window.shape[1]))  # no wrap-around for the scored shifts

    def correlate(image_spectrum: NDArray[np.complex128], kernel: F64) -> F64:
        """Σₓ kernel(x) · image(x + d) at every cyclic shift d of the canvas."""
        return np.fft.irfft2(image_spectrum * np.conj(np.fft.rfft2(kernel, s=shape)), s=shape)

    spectrum, spectrum_sq = np.fft.rfft2(window, s=shape), np.fft.rfft2(window * window, s=shape)
    s1 = correlate(spectrum, mask)
    variance = np.maximum(correlate(spectrum_sq, mask) - s1 * s1 / n, n * (VARIANCE_FLOOR * spread) ** 2)
    ncc = correlate(spectrum, t) / np.sqrt(t_energy * variance)
    allowed = np.zeros(shape, dtype=bool)
    allowed[: window.shape[0] - template.shape[0] + 1, : window.shape[1] - template.shape[1] + 1] = True
    (r, c), = peaks(ncc.astype(np.float32), 1, radius=1, allowed=allowed)
    T = np.eye(3)
    T[:2, 2] = x0 + c - u0, y0 + r - v0  # the ROI's top-left corner lands at window pixel (c, r)
    return T
