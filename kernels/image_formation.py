"""How a camera forms the grey levels the engine compares: its response curve and a defocused lens's blur.

- `linearise`: a camera encodes irradiance `E` (0…255 scale) as `I = 255 (E / 255)^(1/γ)` (γ ≈ 2.2 for sRGB-like
  outputs); `E = 255 (max(I, 0) / 255)^γ` undoes it, in place. Blur and exposure act on `E`, not on `I`: a blurred
  bright edge in `I` is not the blur of the sharp edge in `I`, and the difference shifts the optimum of a photometric
  cost (`benchmarks/cost_optimum.py`).
- `disk_blur`: convolution with a normalised kernel (the uniform disk of a defocused lens, weights from
  `defocus_kernel`), taps beyond the border clamped to it.

Images are float32 `[row, col]` arrays; pixel centres at integer coordinates.
"""

import math

import numpy as np
import taichi as ti

DISK_SUBSAMPLES = 8  # per pixel and axis, for the disk's area over each pixel


def defocus_kernel(radius: float) -> np.ndarray:
    """Normalised `(2n + 1, 2n + 1)` float32 kernel of a uniform disk of `radius` pixels centred on a pixel
    (`n = ceil(radius)`): each weight is the disk's area over that pixel (DISK_SUBSAMPLES² samples); radius 0 is
    the 1×1 identity kernel."""
    if not radius >= 0.0:
        raise ValueError(f"defocus radius must be ≥ 0 pixels, got {radius}")
    n = math.ceil(radius)
    offsets = (np.arange(DISK_SUBSAMPLES) + 0.5) / DISK_SUBSAMPLES - 0.5
    x = (np.arange(-n, n + 1)[:, None] + offsets[None, :]).ravel()
    inside = (x[:, None] ** 2 + x[None, :] ** 2 <= radius**2).astype(np.float64)
    area = inside.reshape(2 * n + 1, DISK_SUBSAMPLES, 2 * n + 1, DISK_SUBSAMPLES).mean(axis=(1, 3))
    if area.sum() == 0.0:  # a radius below the sampling step still covers the centre pixel
        area[n, n] = 1.0
    return (area / area.sum()).astype(np.float32)


@ti.kernel
def linearise(image: ti.types.ndarray(dtype=ti.f32, ndim=2), gamma: ti.f32):
    """`image ← 255 (max(image, 0) / 255)^gamma`, in place (module docstring)."""
    for r, c in ti.ndrange(image.shape[0], image.shape[1]):
        image[r, c] = 255.0 * ti.pow(ti.max(image[r, c], 0.0) / 255.0, gamma)


@ti.kernel
def disk_blur(
    src: ti.types.ndarray(dtype=ti.f32, ndim=2),
    dst: ti.types.ndarray(dtype=ti.f32, ndim=2),
    weights: ti.types.ndarray(dtype=ti.f32, ndim=2),
):
    """`dst = weights ⊛ src` (same shape as `src`; `weights` square, odd-sized, centred), taps clamped to the
    border."""
    h, w = src.shape[0], src.shape[1]
    n = weights.shape[0] // 2
    for r, c in ti.ndrange(h, w):
        acc = 0.0
        for i in range(2 * n + 1):
            row = ti.min(ti.max(r + i - n, 0), h - 1)
            for j in range(2 * n + 1):
                acc += weights[i, j] * src[row, ti.min(ti.max(c + j - n, 0), w - 1)]
        dst[r, c] = acc
