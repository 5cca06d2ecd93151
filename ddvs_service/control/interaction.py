"""Interaction matrices of the control errors at the equilibrium and the closed-loop spectrum (analysis only:
they need the metric quantities `z*` and `q*'` that the controller never knows).

Convention: `dε/dt = L v`, with `v = [v; ω]` the *current* camera's body twist (OpenCV axes, m/s and rad/s).
`m_star` = `m*'` (normalised control point), `z_star` = `z*` its depth (m), `q_star` = `q*' = Kᵀ q*`: for the
reference plane `n*ᵀ X* = 1` (scaled normal `n*`, 1/m) in the gauge where `G ∝ K (R + t n*ᵀ) K⁻¹`, `q*' = n*`.

Note (checked in tests/test_control_interaction.py): (20) holds when `H` carries the Euclidean scale. With
`G ∈ SL(3)` the determinant normalisation adds `m*' q*'ᵀ / 3` to the translational block `L'_vv` at first order.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.lie import skew

F64 = NDArray[np.float64]


def _inputs(m_star: ArrayLike, q_star: ArrayLike, z_star: float) -> tuple[F64, F64, float]:
    m = np.asarray(m_star, dtype=np.float64).reshape(3)
    q = np.asarray(q_star, dtype=np.float64).reshape(3)
    z = float(z_star)
    if not z > 0.0:
        raise ValueError(f"z_star (depth of the control point) must be positive metres, got {z_star!r}")
    return m, q, z


def L_prime_equilibrium(m_star: ArrayLike, q_star: ArrayLike, z_star: float) -> F64:
    """(20) `L'|₀ = −[[I/z*, −[m*']×], [[q*']×, 2I]]`: interaction matrix of `ε'` (13) at `ε' = 0`."""
    m, q, z = _inputs(m_star, q_star, z_star)
    L = np.zeros((6, 6))
    L[:3, :3] = np.eye(3) / z
    L[:3, 3:] = -skew(m)
    L[3:, :3] = skew(q)
    L[3:, 3:] = 2.0 * np.eye(3)
    return -L


def L_bar_equilibrium(m_star: ArrayLike, q_star: ArrayLike, z_star: float, c_star: ArrayLike) -> F64:
    """(19) `L̄|₀ = −[[(2/z*) I + [m*']×[q*']×, 0], [−(1/z*)[c*']× + [q*']×, 2I + [c*']×[m*']×]]`:
    interaction matrix of `ε̄` (14) at `ε̄ = 0`, block lower-triangular (equal to `M L'|₀`)."""
    m, q, z = _inputs(m_star, q_star, z_star)
    c = np.asarray(c_star, dtype=np.float64).reshape(3)
    L = np.zeros((6, 6))
    L[:3, :3] = 2.0 / z * np.eye(3) + skew(m) @ skew(q)
    L[3:, :3] = -skew(c) / z + skew(q)
    L[3:, 3:] = 2.0 * np.eye(3) + skew(c) @ skew(m)
    return -L


def closed_loop_matrix(L: ArrayLike, gains: ArrayLike) -> F64:
    """(29)/(30) `A = L Λ` of the linearised closed loop `dε/dt = L Λ ε` for the law `v = Λ ε`."""
    g = np.broadcast_to(np.asarray(gains, dtype=np.float64), (6,))
    return np.asarray(L, dtype=np.float64) @ np.diag(g)


def theorem_3_2_spectrum(
    m_star: ArrayLike, q_star: ArrayLike, z_star: float, c_star: ArrayLike, gains: ArrayLike
) -> F64:
    """Theorem 3.2's closed-loop eigenvalues of the decoupled law (25) (1/s), in the order
    `{−λ1 a, −λ2 a, −2λ3/z*, −λ4 b, −λ5 b, −2λ6}` with `a = 2/z* − m*'ᵀq*'` and `b = 2 − m*'ᵀc*'`."""
    m, q, z = _inputs(m_star, q_star, z_star)
    c = np.asarray(c_star, dtype=np.float64).reshape(3)
    lam = np.broadcast_to(np.asarray(gains, dtype=np.float64), (6,))
    a = 2.0 / z - m @ q
    b = 2.0 - m @ c
    return -np.array([lam[0] * a, lam[1] * a, 2.0 * lam[2] / z, lam[3] * b, lam[4] * b, 2.0 * lam[5]])
