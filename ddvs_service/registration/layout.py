"""Parameter layout of the registration unknowns: named contiguous blocks of the Gauss-Newton vector.

The planar problem uses `G` (8 sl(3) coordinates), `S` (one gain per grid node, row-major) and `beta` (1), in
that order, which is the column order of the Jacobian built by `kernels.planar_step`. The non-planar extension
appends blocks (epipole `e`, parallax coefficients) without disturbing the existing offsets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class ParamLayout:
    """Ordered `(name, size)` blocks of the parameter vector."""

    blocks: tuple[tuple[str, int], ...]

    @classmethod
    def planar(cls, grid_rows: int, grid_cols: int) -> ParamLayout:
        return cls((("G", 8), ("S", grid_rows * grid_cols), ("beta", 1)))

    @property
    def size(self) -> int:
        return sum(n for _, n in self.blocks)

    def slice(self, name: str) -> slice:
        """Index range of block `name` in the parameter vector."""
        start = 0
        for block, n in self.blocks:
            if block == name:
                return slice(start, start + n)
            start += n
        raise KeyError(f"no parameter block {name!r}; blocks are {[b for b, _ in self.blocks]}")

    def split(self, x: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
        """The blocks of a parameter (or update) vector, by name."""
        if x.shape != (self.size,):
            raise ValueError(f"parameter vector has shape {x.shape}, expected ({self.size},)")
        return {name: x[self.slice(name)] for name, _ in self.blocks}
