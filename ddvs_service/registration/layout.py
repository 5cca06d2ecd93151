"""Parameter layout of the registration unknowns: named contiguous blocks of the Gauss-Newton vector.

The planar problem uses `G` (8 sl(3) coordinates), `S` (one gain per grid node, row-major) and `beta` (1), in
that order, which is the column order of the Jacobian built by `kernels.planar_step`. The general problem of eq. (2)
inserts the epipole `e` (3) and the parallax coefficients `rho` (the basis size, or none when ρ* is held fixed)
after `G`: the column order of `kernels.general_step`. The engines index their unknowns only through a layout.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class ParamLayout:
    """Ordered `(name, size)` blocks of the parameter vector."""

    blocks: tuple[tuple[str, int], ...]

    @classmethod
    def planar(cls, grid_rows: int, grid_cols: int) -> ParamLayout:
        return cls((("G", 8), ("S", grid_rows * grid_cols), ("beta", 1)))

    @classmethod
    def general(cls, grid_rows: int, grid_cols: int, n_rho: int) -> ParamLayout:
        """Eq. (2)'s unknowns; `n_rho` = 0 when ρ* is not among them."""
        return cls((("G", 8), ("e", 3), ("rho", n_rho), ("S", grid_rows * grid_cols), ("beta", 1)))

    @cached_property
    def size(self) -> int:
        return sum(n for _, n in self.blocks)

    @cached_property
    def _slices(self) -> dict[str, slice]:
        """Index range of each block (computed once: the solvers look blocks up on every iteration)."""
        slices, start = {}, 0
        for block, n in self.blocks:
            slices[block] = slice(start, start + n)
            start += n
        return slices

    def slice(self, name: str) -> slice:
        """Index range of block `name` in the parameter vector."""
        if name not in self._slices:
            raise KeyError(f"no parameter block {name!r}; blocks are {[b for b, _ in self.blocks]}")
        return self._slices[name]

    def indices(self, *names: str) -> NDArray[np.intp]:
        """Positions of the blocks `names` in the parameter vector, in layout order."""
        return np.concatenate([np.arange(self.size)[self.slice(b)] for b, _ in self.blocks if b in names])

    def split(self, x: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
        """The blocks of a parameter (or update) vector, by name."""
        if x.shape != (self.size,):
            raise ValueError(f"parameter vector has shape {x.shape}, expected ({self.size},)")
        return {name: x[s] for name, s in self._slices.items()}
