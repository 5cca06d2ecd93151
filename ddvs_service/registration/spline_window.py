"""The current image's cubic B-spline coefficients (`kernels.bspline`), prefiltered only where they are sampled.

The general engine samples the full-resolution current image through its interpolating cubic B-spline
(`GeneralConfig.interpolation`). Prefiltering the whole image would take most of a tracked frame's budget
(docs/performance.md) while the warped ROI covers a fraction of it. `SplineWindow.covering(image, box)` prefilters a
window around `box` (the warped ROI's bounding box) widened by `margin_px`, so that the iterations of a frame can
move without leaving it, and keeps it for the frame: a later `box` inside the domain reuses the coefficients, one
outside it prefilters a new window. Samples outside `domain` must be treated as invalid (the general kernel does,
`kernels.general_step.PARAMS_DOMAIN`): the buffer there holds another window's or another frame's values.

Coordinates: full-resolution pixels of the current image, 0-based pixel centres, `box = (x_lo, y_lo, x_hi, y_hi)`
(x = column, y = row).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from kernels.launch import Prepared

F32 = NDArray[np.float32]
Box = tuple[float, float, float, float]
UNRESTRICTED: Box = (-1e30, -1e30, 1e30, 1e30)


class SplineWindow:
    """Coefficient buffer of one image size, the window prefiltered last and the domain where it is exact."""

    def __init__(self, shape: tuple[int, int], margin_px: float) -> None:
        if not margin_px >= 0.0:
            raise ValueError(f"margin_px must be ≥ 0 pixels, got {margin_px}")
        self.margin_px = margin_px
        self.buffer = np.zeros(shape, dtype=np.float32)
        self.domain: Box | None = None  # None: nothing valid (no image yet, or a new one)
        self._window = np.zeros(4, dtype=np.int32)
        self._launch: tuple[F32, Prepared] | None = None  # the prefilter bound to its source image buffer

    def invalidate(self) -> None:
        """A new image was loaded into the source buffer: the coefficients are stale everywhere."""
        self.domain = None

    def covering(self, image: F32, box: Box) -> F32:
        """The coefficients of `image` (the same buffer, reloaded in place, between `invalidate` calls), exact for
        every sample in `self.domain`, which contains `box` (the whole image when `box` is not finite)."""
        from kernels.backend import compile_settings
        from kernels.bspline import bspline_coefficients, check_buffers, window_for

        d = self.domain
        if d is not None and d[0] <= box[0] and d[1] <= box[1] and box[2] <= d[2] and box[3] <= d[3]:
            return self.buffer
        m = self.margin_px
        finite = all(math.isfinite(v) for v in box)  # a diverged state: the whole image, its samples fail anyway
        domain = (box[0] - m, box[1] - m, box[2] + m, box[3] + m) if finite else UNRESTRICTED
        self._window[:] = window_for(image.shape, *domain)
        if self._launch is None or self._launch[0] is not image:
            check_buffers(image, self.buffer, self._window)
            with compile_settings(advanced=True):  # its first preparation compiles it (`kernels.bspline`)
                self._launch = image, Prepared(bspline_coefficients, image, self.buffer, self._window)
        self._launch[1]()
        self.domain = domain
        return self.buffer
