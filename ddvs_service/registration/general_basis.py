"""Smooth parametrisation of the parallax field ρ*(p*) of eq. (2) over the ROI, with the plane gauge built in.

`ρ*(p*) = Σ_k c_k φ_k(p*)`, `φ_k` polynomials of the normalised reference coordinates `(x, y) = (p* − c) / s`
(`c` the ROI centre, `s` half its larger side, full-resolution pixels): all monomials `x^i y^j`, `0 ≤ i, j ≤ degree`
(biquadratic for degree 2, bicubic for degree 3), Gram–Schmidt orthonormalised over the ROI's pixel centres after
`1, x, y`, which are then dropped. Hence every `ρ*` in the span has zero mean and zero first moments over the ROI
and `RMS(φ_k) = 1`: the plane freedom `(G, e, ρ*) ~ (G + e aᵀ, e, ρ* − aᵀp*)` of (2) is fixed by construction (the
reference plane is the least-squares plane of the scene over the ROI, in the projective sense of (2)).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]
DEGREES = (2, 3)


def coefficient_count(degree: int) -> int:
    """Number of coefficients `c_k` of the basis of `degree`: every monomial `x^i y^j`, `0 ≤ i, j ≤ degree`, but
    `1, x, y` (6 for degree 2, 13 for degree 3)."""
    return (degree + 1) ** 2 - 3


def _monomials(x: F64, y: F64, degree: int) -> F64:
    """(N, (degree + 1)²) values of `x^i y^j`, column `i·(degree + 1) + j`."""
    return np.stack([x**i * y**j for i in range(degree + 1) for j in range(degree + 1)], axis=1)


@dataclass(frozen=True)
class ParallaxBasis:
    """The basis over `roi = (x, y, w, h)` (reference pixels): `B` (n × (degree + 1)²) maps monomial values to basis
    values, `centre` and `half_size` define `(x, y)`."""

    roi: tuple[int, int, int, int]
    degree: int
    B: F64
    centre: tuple[float, float]
    half_size: float

    @classmethod
    def over(cls, roi: tuple[int, int, int, int], degree: int = 2) -> ParallaxBasis:
        if degree not in DEGREES:
            raise ValueError(f"parallax basis degree must be one of {DEGREES}, got {degree}")
        x0, y0, w, h = roi
        centre = (x0 + 0.5 * (w - 1), y0 + 0.5 * (h - 1))
        half = 0.5 * max(w - 1, h - 1)
        x = (np.arange(x0, x0 + w, dtype=np.float64) - centre[0]) / half
        y = (np.arange(y0, y0 + h, dtype=np.float64) - centre[1]) / half
        # Gram matrix of the monomials over the ROI's pixel centres, mean of x^(i+k) y^(j+l): the grid is a product
        # of its rows and columns, so each entry is a product of two 1-D power means.
        mean_x = np.array([np.mean(x**k) for k in range(2 * degree + 1)])
        mean_y = np.array([np.mean(y**k) for k in range(2 * degree + 1)])
        i, j = np.divmod(np.arange((degree + 1) ** 2), degree + 1)  # monomial m = i·(degree + 1) + j
        gram = mean_x[i[:, None] + i[None, :]] * mean_y[j[:, None] + j[None, :]]
        # Modified Gram–Schmidt in the order 1, y, x, …, on coefficient vectors (inner product `aᵀ gram b`): the first
        # three orthonormal functions span {1, x, y}.
        first = [0, 1, degree + 1]
        order = first + [m for m in range(gram.shape[0]) if m not in first]
        coeffs: list[F64] = []
        for m in order:
            c = np.zeros(gram.shape[0])
            c[m] = 1.0
            for cq in coeffs:
                c -= float(cq @ gram @ c) * cq
            coeffs.append(c / float(np.sqrt(c @ gram @ c)))
        return cls(roi, degree, np.array(coeffs[3:]), centre, half)

    @property
    def size(self) -> int:
        """Number of coefficients `c_k`."""
        return self.B.shape[0]

    def coordinates(self, p: ArrayLike) -> tuple[F64, F64]:
        """Normalised `(x, y)` of reference pixels `p` (N × 2, full resolution)."""
        q = np.asarray(p, dtype=np.float64).reshape(-1, 2)
        return (q[:, 0] - self.centre[0]) / self.half_size, (q[:, 1] - self.centre[1]) / self.half_size

    def values(self, p: ArrayLike) -> F64:
        """(N, n) basis values `φ_k` at reference pixels `p` (N × 2)."""
        return _monomials(*self.coordinates(p), self.degree) @ self.B.T

    def rho(self, coeffs: ArrayLike, p: ArrayLike) -> F64:
        """ρ*(p*) at reference pixels `p` (N × 2) for coefficients `coeffs` (gauge units, module docstring)."""
        return self.values(p) @ np.asarray(coeffs, dtype=np.float64).reshape(self.size)

    def monomial_coefficients(self, coeffs: ArrayLike) -> F64:
        """`a = Bᵀ c`: ρ* as coefficients of the monomials `x^i y^j` (what the kernels evaluate)."""
        return self.B.T @ np.asarray(coeffs, dtype=np.float64).reshape(self.size)

    def level_norm(self, D: F64) -> tuple[float, float, float]:
        """`(cx, cy, s)` such that `(x, y) = (p_l − c_l) / s_l` for level pixels `p_l = D p` (`D` of `images`)."""
        k = float(D[0, 0])
        return k * self.centre[0] + float(D[0, 2]), k * self.centre[1] + float(D[1, 2]), k * self.half_size
