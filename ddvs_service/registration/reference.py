"""A reference prepared once, and the per-call workspace of the engines that register images against it.

As Pinocchio separates a robot's `Model` (fixed) from its `Data` (scratch space for one computation):
- `PreparedReference` is immutable: the grey reference, the ROI, the reference's pyramid (irradiance, defocus and
  mask applied, `RegistrationConfig.gamma`, `.defocus_px`) and the fixed geometry of each level (`Level`). The
  planar and general engines, the trackers and the global initialiser's refiners of one servo share one.
- `CurrentPyramid` is the workspace: the current image's pyramid in fixed buffers shaped like the reference's
  levels, so that every engine prepares its kernel launches on them once (`kernels.launch.Prepared`). Engines that
  run one after the other (a tracker and the initialiser that re-acquires for it) share one.

Pixels: full-image 0-based pixel centres; `roi = (x, y, w, h)` covers columns x … x + w − 1 and rows y … y + h − 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.registration.config import RegistrationConfig
from ddvs_service.registration.images import F32, build_pyramid, checked_grey, irradiance, level_matrix
from kernels.launch import Prepared

F64 = NDArray[np.float64]
Roi = tuple[int, int, int, int]
# The settings a prepared reference depends on; the others (iterations, tolerances, robust loss) are the solver's.
PREPARATION_FIELDS = ("levels", "min_level_size", "gamma", "defocus_px")


@dataclass(frozen=True)
class Level:
    """Fixed geometry of one pyramid level: ROI bounds (inclusive), gain-grid span, normalisation `N` (level pixels →
    `q = (p − c) / s`), `D` (full-resolution → level pixels), ROI corners."""

    index: int
    bounds: tuple[int, int, int, int]
    span: tuple[float, float, float, float]
    norm: tuple[float, float, float]
    n_pixels: int
    D: F64
    D_inv: F64
    N: F64
    N_inv: F64
    corners: F64  # homogeneous ROI corners (3×4), level pixels

    @property
    def size(self) -> float:
        u0, v0, u1, v1 = self.bounds
        return float(max(u1 - u0, v1 - v0))


def normalisation(bounds: tuple[int, int, int, int]) -> tuple[tuple[float, float, float], F64]:
    """`(cx, cy, s)` and the matrix `N` of the normalisation `q = (p − c) / s` about the centre of the inclusive
    pixel bounds `(u0, v0, u1, v1)`, `s` half the larger side: the sl(3) increments of every engine are taken in it."""
    u0, v0, u1, v1 = bounds
    cx, cy, s = 0.5 * (u0 + u1), 0.5 * (v0 + v1), 0.5 * max(u1 - u0, v1 - v0)
    return (cx, cy, s), np.array([[1.0 / s, 0.0, -cx / s], [0.0, 1.0 / s, -cy / s], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, eq=False)
class PreparedReference:
    """The reference side of eq. (5), prepared once (module docstring). `image`: the grey reference as given
    (float32); `pyramid`: what the engines compare against, level 0 at full resolution; `config`: the settings it
    was prepared with (`PREPARATION_FIELDS` matter)."""

    image: F32
    roi: Roi
    config: RegistrationConfig
    levels: tuple[Level, ...]
    pyramid: tuple[F32, ...]

    @property
    def shape(self) -> tuple[int, int]:
        h, w = self.image.shape
        return h, w

    @classmethod
    def prepare(
        cls,
        reference: ArrayLike,
        roi: Roi | None = None,
        mask: ArrayLike | None = None,
        config: RegistrationConfig = RegistrationConfig(),  # noqa: B008 - frozen, immutable default
    ) -> PreparedReference:
        """Check the reference, ROI and mask (True where reference pixels may be used) and build the levels whose
        ROI keeps at least `config.min_level_size` pixels a side (at most `config.levels`). Raises ValueError on bad
        input, naming what was expected."""
        from kernels.backend import init
        from kernels.planar_step import MASKED

        init()
        image = checked_grey(reference, "reference").copy()
        ref = irradiance(image, config.gamma, config.defocus_px).copy()
        checked = _validate_roi(roi, ref.shape)
        if mask is not None:
            m = np.asarray(mask)
            if m.shape != ref.shape:
                raise ValueError(f"mask has shape {m.shape}, expected the reference's {ref.shape}")
            ref[~m.astype(bool)] = MASKED
        levels = _make_levels(build_pyramid(ref, config.levels), checked, config.min_level_size)
        pyramid = tuple(build_pyramid(ref, len(levels)))
        for array in (image, *pyramid):
            array.setflags(write=False)
        return cls(image, checked, config, levels, pyramid)

    def check_config(self, config: RegistrationConfig) -> None:
        """Refuse solver settings whose preparation fields differ from those this reference was prepared with."""
        differ = [f for f in PREPARATION_FIELDS if getattr(config, f) != getattr(self.config, f)]
        if differ:
            raise ValueError(f"settings {differ} differ from those the reference was prepared with "
                             f"({', '.join(f'{f}={getattr(self.config, f)!r}' for f in differ)})")


class CurrentPyramid:
    """The workspace for the current image (module docstring): `load` fills the fixed buffers, which the next call
    overwrites."""

    def __init__(self, reference: PreparedReference) -> None:
        self.reference = reference
        self.buffers = [np.empty_like(level) for level in reference.pyramid]
        self.loads = 0  # images loaded so far: a copy of the buffers knows whether it is the newest frame's
        self._downsamples: dict[int, Prepared] = {}
        self._linearise: Prepared | None = None

    def load(self, cur: NDArray[Any], n_levels: int) -> list[F32]:
        """Copy `cur` (checked, reference-sized; float32, or integers that the copy converts:
        `images.checked_image`) into the level-0 buffer, linearise it there when the reference's `config.gamma` ≠ 1
        (`images.irradiance`; the reference's defocus is not applied to the current image) and downsample it into the
        next `n_levels − 1` buffers (`images.build_pyramid`'s filter)."""
        from kernels.image_formation import linearise
        from kernels.pyramid import downsample2

        gamma = self.reference.config.gamma
        np.copyto(self.buffers[0], cur)
        self.loads += 1
        if gamma != 1.0:
            if self._linearise is None:
                self._linearise = Prepared(linearise, self.buffers[0], gamma)
            self._linearise()
        for index in range(1, n_levels):
            if index not in self._downsamples:
                self._downsamples[index] = Prepared(downsample2, self.buffers[index - 1], self.buffers[index])
            self._downsamples[index]()
        return self.buffers


def _validate_roi(roi: Roi | None, shape: tuple[int, ...]) -> Roi:
    h, w = shape
    if roi is None:
        return 0, 0, w, h
    if len(roi) != 4:
        raise ValueError(f"roi must be (x, y, w, h), got {roi!r}")
    x, y, rw, rh = (int(v) for v in roi)
    if rw < 8 or rh < 8:
        raise ValueError(f"roi {roi} is {rw}×{rh} pixels, expected at least 8×8")
    if x < 0 or y < 0 or x + rw > w or y + rh > h:
        raise ValueError(f"roi (x={x}, y={y}, w={rw}, h={rh}) is not inside the {w}×{h} reference image")
    return x, y, rw, rh


def _make_levels(pyramid: list[F32], roi: Roi, min_level_size: int) -> tuple[Level, ...]:
    """Levels 0 … L − 1 whose ROI keeps at least `min_level_size` pixels per side; refuses an all-masked ROI."""
    from kernels.planar_step import MASK_LIMIT

    x, y, w, h = roi
    levels = []
    for index, ref in enumerate(pyramid):
        k = 2**index
        u0, v0 = math.ceil(x / k), math.ceil(y / k)
        u1 = min(math.floor((x + w) / k) - 1, ref.shape[1] - 1)
        v1 = min(math.floor((y + h) / k) - 1, ref.shape[0] - 1)
        if index > 0 and min(u1 - u0 + 1, v1 - v0 + 1) < min_level_size:
            break
        n_pixels = int((ref[v0 : v1 + 1, u0 : u1 + 1] > MASK_LIMIT).sum())
        if n_pixels == 0:
            if index == 0:
                raise ValueError("the mask excludes every pixel of the ROI; expected some pixels to register")
            break
        D = level_matrix(index)
        sx0, sx1 = D[0, 0] * np.array([x, x + w - 1]) + D[0, 2]
        sy0, sy1 = D[1, 1] * np.array([y, y + h - 1]) + D[1, 2]
        norm, N = normalisation((u0, v0, u1, v1))
        levels.append(Level(
            index=index, bounds=(u0, v0, u1, v1), span=(float(sx0), float(sy0), float(sx1), float(sy1)), norm=norm,
            n_pixels=n_pixels, D=D, D_inv=np.asarray(np.linalg.inv(D), dtype=np.float64), N=N,
            N_inv=np.asarray(np.linalg.inv(N), dtype=np.float64),
            corners=np.array([[u0, u1, u1, u0], [v0, v0, v1, v1], [1.0, 1.0, 1.0, 1.0]]),
        ))
    return tuple(levels)
