"""Input images of the registration engine: checks, grey conversion, irradiance and pyramids.

Images are `[row, col]` arrays; inside the engine they are float32 grey levels (uint8 values kept as 0…255).
Level-l pixel coordinates relate to full-resolution ones by `p_l = D_l p_0` with
`D_l = [[2⁻ˡ, 0, (2⁻ˡ − 1)/2], [0, 2⁻ˡ, (2⁻ˡ − 1)/2], [0, 0, 1]]` (pixel centres; see `kernels.pyramid`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

F32 = NDArray[np.float32]


def to_grey(image: ArrayLike) -> F32:
    """Grey float32 image from a 2-D array or an H×W×3 BGR (OpenCV order) / H×W×4 BGRA array (ITU-R BT.601)."""
    img = np.asarray(image)
    if img.ndim == 2:
        return img.astype(np.float32, copy=False)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        b, g, r = (img[..., k].astype(np.float32) for k in range(3))
        return (0.114 * b + 0.587 * g + 0.299 * r).astype(np.float32)
    raise ValueError(f"expected a 2-D grey image or an H×W×3/4 colour image, got shape {img.shape}")


def checked_grey(image: ArrayLike, name: str) -> F32:
    """`image` as a contiguous float32 2-D array; refuses colour, tiny, NaN or infinite images with a clear error."""
    return np.ascontiguousarray(checked_image(image, name), dtype=np.float32)


def checked_image(image: ArrayLike, name: str) -> NDArray[Any]:
    """`checked_grey`'s checks without its copy: an integer image (a camera's uint8 frame) as it is — finite by its
    type, not scanned, and converted to float32 by whoever copies it (`reference.CurrentPyramid.load`, in the same
    pass) — any other as float32 (scanned for NaN and infinities after the conversion, which can overflow)."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"{name} must be a 2-D grey image, got shape {img.shape} (convert colour with to_grey)")
    if img.shape[0] < 8 or img.shape[1] < 8:
        raise ValueError(f"{name} is {img.shape[1]}×{img.shape[0]} pixels, expected at least 8×8")
    if img.dtype.kind in "biu":
        return img
    out = np.ascontiguousarray(img, dtype=np.float32)
    if not np.isfinite(out).all():
        bad = int((~np.isfinite(out)).sum())
        raise ValueError(f"{name} contains {bad} NaN/Inf pixels; expected finite grey levels")
    return out


def level_matrix(level: int) -> NDArray[np.float64]:
    """`D_l`: full-resolution pixel coordinates → level-`level` pixel coordinates (module docstring)."""
    k = 0.5**level
    return np.array([[k, 0.0, 0.5 * (k - 1.0)], [0.0, k, 0.5 * (k - 1.0)], [0.0, 0.0, 1.0]])


def build_pyramid(image: F32, levels: int) -> list[F32]:
    """`[full resolution, ½, ¼, …]`, `levels` images, each made by `kernels.pyramid.downsample2` from the previous."""
    from kernels.backend import init
    from kernels.pyramid import downsample2

    init()
    pyramid = [image]
    for _ in range(1, levels):
        src = pyramid[-1]
        dst = np.empty((src.shape[0] // 2, src.shape[1] // 2), dtype=np.float32)
        downsample2(src, dst)
        pyramid.append(dst)
    return pyramid


def irradiance(image: F32, gamma: float, defocus_px: float = 0.0) -> F32:
    """`image` (float32 grey levels, not modified) as the engine compares it: linearised by the camera response
    `255 (I / 255)^gamma`, then blurred by a uniform disk of radius `defocus_px` pixels
    (`kernels.image_formation`; `RegistrationConfig.gamma`, `.defocus_px`). A new array, or `image` itself when
    `gamma` is 1 and `defocus_px` 0."""
    from kernels.backend import init
    from kernels.image_formation import defocus_kernel, disk_blur, linearise

    if gamma == 1.0 and defocus_px == 0.0:
        return image
    init()
    out = image.copy()
    if gamma != 1.0:
        linearise(out, gamma)
    if defocus_px > 0.0:
        sharp = out.copy()
        disk_blur(sharp, out, defocus_kernel(defocus_px))
    return out
