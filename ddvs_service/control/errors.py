"""Control errors of the DVS and of the decoupled DVS, computed from the projective parameters only.

Inputs are the estimated `G ∈ SL(3)` (pixels → pixels homography of the reference plane), the pixel epipole `e`
(homogeneous 3-vector, same scale gauge as `ρ*`), the projective parallax `ρ*` of the control point and the
intrinsics `K`. Never depth or pose. `m_star` (`m*'`) and `c_star` (`c*'`) are normalised points `K⁻¹ p`
(third component 1 for a pixel). Equation numbers refer to the paper (`docs/equations.md`).

Frames: every error is expressed in the current camera frame (OpenCV axes); with `v` the current camera's body
twist `[v; ω]`, `dε/dt = L v` (see `interaction`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.lie import skew

F64 = NDArray[np.float64]


def _vector3(x: ArrayLike, name: str) -> F64:
    a = np.asarray(x, dtype=np.float64)
    if a.size != 3 or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be a finite 3-vector, got {np.asarray(x)!r}")
    return a.reshape(3)


def _matrix3(x: ArrayLike, name: str) -> F64:
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (3, 3) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be a finite 3×3 matrix, got shape {a.shape} / values {a!r}")
    return a


def _scalar(x: float, name: str) -> float:
    v = float(x)
    if not np.isfinite(v):
        raise ValueError(f"{name} must be a finite number, got {x!r}")
    return v


def _normalised(G: ArrayLike, e: ArrayLike, K: ArrayLike) -> tuple[F64, F64]:
    """(8) `H = K⁻¹ G K`, the homography in normalised coordinates (maps `m*'` to `m'`, up to scale), and the
    normalised epipole `e' = K⁻¹ e`; the inputs validated once."""
    K = _matrix3(K, "K")
    K_inv = np.linalg.inv(K)
    return K_inv @ _matrix3(G, "G") @ K, K_inv @ _vector3(e, "e")


def _translation(H: F64, e_n: F64, rho: float, m_star: F64) -> F64:
    """`(H − I) m*' + ρ* e'` on validated inputs (see `translation_error`)."""
    return H @ m_star - m_star + rho * e_n


_LOWER = [7, 2, 3]  # H21, H02, H10 in a row-major 3×3
_UPPER = [5, 6, 1]  # H12, H20, H01


def vex_antisymmetric(H: F64) -> F64:
    """`vex(H − Hᵀ)` of a 3×3 `H`: `[H21 − H12, H02 − H20, H10 − H01]`, bit for bit (each entry of `H − Hᵀ` is
    a rounded difference d and its mirror exactly −d, so `½ (d − (−d))` is d), in two numpy operations instead of
    a dozen: the reduced and decoupled errors take it on every frame."""
    flat = np.ascontiguousarray(H).reshape(9)
    return flat[_LOWER] - flat[_UPPER]


def translation_error(H: ArrayLike, e_n: ArrayLike, rho: float, m_star: ArrayLike) -> F64:
    """Translational error of (7)/(13): `ε_v = (H − I) m*' + ρ* e'` with `e' = K⁻¹ e` the normalised epipole.

    Under the Euclidean scaling (`H = R + t n*ᵀ`, `e' = t`, `X = R X* + t`) it equals `(R − I) m*' + t/z*`.
    """
    return _translation(_matrix3(H, "H"), _vector3(e_n, "e_n"), _scalar(rho, "rho"), _vector3(m_star, "m_star"))


def rotation_vector_dvs(H: ArrayLike) -> F64:
    """DVS rotational error `θ μ` from (9)–(11): `r = ½ vex(H − Hᵀ)`, `θ = asin‖r‖` (`π − asin‖r‖` when
    `tr H < 1`), `μ = r/‖r‖` (`[0, 0, 1]` when `r = 0`). `asin` takes its real part: `π/2` for `‖r‖ > 1`.

    For a rotation `H = R` this is the rotation vector of `R` (radians)."""
    H = _matrix3(H, "H")
    r = 0.5 * vex_antisymmetric(H)
    norm = float(np.linalg.norm(r))
    theta = float(np.arcsin(min(norm, 1.0)))
    if np.trace(H) < 1.0:
        theta = np.pi - theta
    mu = r / norm if norm > 0.0 else np.array([0.0, 0.0, 1.0])
    return theta * mu


def dvs_error(G: ArrayLike, e: ArrayLike, rho: float, K: ArrayLike, m_star: ArrayLike) -> F64:
    """(7) full DVS error `ε = [(H − I) m*' + ρ* e'; θ μ]` (6-vector), with (8)–(11)."""
    H, e_n = _normalised(G, e, K)
    return dvs_error_normalised(H, e_n, _scalar(rho, "rho"), _vector3(m_star, "m_star"))


def reduced_error(G: ArrayLike, e: ArrayLike, rho: float, K: ArrayLike, m_star: ArrayLike) -> F64:
    """(13) reduced DVS error `ε' = [(H − I) m*' + ρ* e'; vex(H − Hᵀ)]` (6-vector); `ε'_ω ≈ 2 θ μ` near 0."""
    H, e_n = _normalised(G, e, K)
    return reduced_error_normalised(H, e_n, _scalar(rho, "rho"), _vector3(m_star, "m_star"))


def dvs_error_normalised(H: F64, e_n: F64, rho: float, m_star: F64) -> F64:
    """`dvs_error` from the normalised homography `H = K⁻¹ G K` (3×3) and epipole `e' = K⁻¹ e` (3), not validated
    (`ControlLaw`'s per-frame path, which validates only an error that came out non-finite)."""
    return np.concatenate([_translation(H, e_n, rho, m_star), rotation_vector_dvs(H)])


def reduced_error_normalised(H: F64, e_n: F64, rho: float, m_star: F64) -> F64:
    """`reduced_error` from the normalised `H` and `e'`, not validated (as `dvs_error_normalised`)."""
    return np.concatenate([_translation(H, e_n, rho, m_star), vex_antisymmetric(H)])


def check_inputs(G: ArrayLike, e: ArrayLike, rho: float) -> None:
    """Raise ValueError naming the first of `G` (finite 3×3), `e` (finite 3-vector) and `rho` (finite) that is not."""
    _matrix3(G, "G")
    _vector3(e, "e")
    _scalar(rho, "rho")


def decoupling_matrix(m_star: ArrayLike, c_star: ArrayLike) -> F64:
    """(15) `M = [[2I, [m*']×], [−[c*']×, I]]` (constant 6×6); `det M = 2 (2 − m*'ᵀc*')²`, singular iff (17) fails."""
    M = np.eye(6)
    M[:3, :3] = 2.0 * np.eye(3)
    M[:3, 3:] = skew(_vector3(m_star, "m_star"))
    M[3:, :3] = -skew(_vector3(c_star, "c_star"))
    return M


def decoupled_error(G: ArrayLike, e: ArrayLike, rho: float, K: ArrayLike, m_star: ArrayLike, c_star: ArrayLike) -> F64:
    """(14)/(16) decoupled error `ε̄ = M ε'`:
    `ε̄_v = 2 ε'_v + [m*']× vex(H − Hᵀ)`, `ε̄_ω = vex(H − Hᵀ) − [c*']× ε'_v`."""
    return decoupling_matrix(m_star, c_star) @ reduced_error(G, e, rho, K, m_star)
