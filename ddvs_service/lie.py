"""Small, pure Lie-group helpers: so(3)/SO(3), se(3)/SE(3) and sl(3)/SL(3).

Conventions (shared by the whole project):
- Rotation vectors `r = θ u` (radians), OpenCV camera axes (x right, y down, z forward).
- A twist `xi = [v; ω]` (6-vector, metres/second and radians/second, or metres and radians once integrated) is
  expressed in the *body* (current camera) frame, so a pose advances as `T ← T · exp(xi · dt)`.
- Poses are 4×4 homogeneous matrices `T_a_b` mapping coordinates in frame b to frame a.
- `sl(3)` uses the 8 generators `A_1..A_8` of `SL3_GENERATORS` (translation x/y, rotation, anisotropic scale,
  isotropic-vs-z scale, shear and the two projective terms); `G ← G · expm(Σ xᵢ Aᵢ)`.
"""

from __future__ import annotations

import bisect
import functools
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]


def skew(w: ArrayLike) -> F64:
    """Return the 3×3 skew matrix `[w]×` such that `[w]× x = w × x`."""
    x, y, z = np.asarray(w, dtype=np.float64).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def vex(S: ArrayLike) -> F64:
    """Inverse of `skew` for the skew part of `S`: `vex(S) = [S21 − S12, S02 − S20, S10 − S01] / 2`."""
    S = np.asarray(S, dtype=np.float64)
    return 0.5 * np.array([S[2, 1] - S[1, 2], S[0, 2] - S[2, 0], S[1, 0] - S[0, 1]])


def so3_exp(r: ArrayLike) -> F64:
    """Rodrigues: rotation matrix of the rotation vector `r = θ u` (radians)."""
    r = np.asarray(r, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(r))
    K = skew(r)
    if theta < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(theta) / theta * K + (1.0 - np.cos(theta)) / theta**2 * K @ K


def so3_log(R: ArrayLike) -> F64:
    """Rotation vector `θ u` (θ ∈ [0, π]) of a rotation matrix."""
    R = np.asarray(R, dtype=np.float64)
    cos_t = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = float(np.arccos(cos_t))
    w = 2.0 * vex(R)  # = 2 sin θ u
    if theta < 1e-8:
        return 0.5 * w
    if np.pi - theta < 1e-4:
        # Near π the skew part vanishes: take the axis from the symmetric part R + I = 2 u uᵀ (+ O(π − θ)).
        B = 0.5 * (R + np.eye(3))
        k = int(np.argmax(np.diag(B)))
        u = B[:, k] / np.sqrt(max(B[k, k], 1e-300))
        if np.dot(u, w) < 0:
            u = -u
        return theta * u / np.linalg.norm(u)
    return theta / (2.0 * np.sin(theta)) * w


def se3_exp(xi: ArrayLike) -> F64:
    """4×4 pose `exp([v; ω]^)` of a body twist integrated over unit time (exact, no first-order approximation)."""
    xi = np.asarray(xi, dtype=np.float64).reshape(6)
    v, w = xi[:3], xi[3:]
    theta = float(np.linalg.norm(w))
    W = skew(w)
    if theta < 1e-8:
        V = np.eye(3) + 0.5 * W + W @ W / 6.0
    else:
        V = (
            np.eye(3)
            + (1.0 - np.cos(theta)) / theta**2 * W
            + (theta - np.sin(theta)) / theta**3 * W @ W
        )
    T = np.eye(4)
    T[:3, :3] = so3_exp(w)
    T[:3, 3] = V @ v
    return T


def pose(R: ArrayLike, t: ArrayLike) -> F64:
    """4×4 homogeneous matrix from a rotation matrix and a translation (metres)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def pose_inv(T: ArrayLike) -> F64:
    """Inverse of a rigid 4×4 transform."""
    T = np.asarray(T, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    return pose(R.T, -R.T @ t)


def _generators() -> F64:
    A = np.zeros((8, 3, 3))
    A[0, 0, 2] = 1.0  # translation along x
    A[1, 1, 2] = 1.0  # translation along y
    A[2, 0, 1], A[2, 1, 0] = -1.0, 1.0  # in-plane rotation
    A[3, 0, 0], A[3, 1, 1] = 1.0, -1.0  # anisotropic scale
    A[4, 0, 0], A[4, 1, 1], A[4, 2, 2] = 1.0, 1.0, -2.0  # isotropic scale (vs. z)
    A[5, 0, 1], A[5, 1, 0] = 1.0, 1.0  # shear
    A[6, 2, 0] = 1.0  # projective x
    A[7, 2, 1] = 1.0  # projective y
    return A


SL3_GENERATORS: F64 = _generators()
"""The 8 traceless generators `A_i` of sl(3), shape (8, 3, 3)."""


_SL3_FLAT: F64 = SL3_GENERATORS.reshape(8, 9)


def sl3_hat(x: ArrayLike) -> F64:
    """`Σ xᵢ Aᵢ` for an 8-vector x."""
    return (np.asarray(x, dtype=np.float64).reshape(8) @ _SL3_FLAT).reshape(3, 3)


_EXPM_MAX_TERMS = 12  # degree cap: at ‖X‖₁ = 0.5 the first omitted term is 0.5¹³ / 13! ≈ 2e-14
_UNIT_ROUNDOFF = 2.0**-53
# `_TAYLOR_LIMITS[k]`: the largest 1-norm for which `k` Taylor terms leave a first omitted term
# `norm^(k+1) / (k+1)!` at or below the double-precision unit roundoff (increasing in k).
_TAYLOR_LIMITS = tuple((math.factorial(k + 1) * _UNIT_ROUNDOFF) ** (1.0 / (k + 1)) for k in range(_EXPM_MAX_TERMS))


def _taylor_terms(norm: float) -> int:
    """Fewest Taylor terms `k` with `norm^(k+1) / (k+1)! ≤ 2⁻⁵³` (the first omitted term below the double-precision
    unit roundoff), at most `_EXPM_MAX_TERMS`; `norm` is the 1-norm of the scaled matrix (≤ 0.5)."""
    return bisect.bisect_left(_TAYLOR_LIMITS, norm)


@functools.lru_cache(maxsize=8)
def _identity(n: int) -> F64:
    """`np.eye(n)`, read-only, made once per size (`np.eye` costs more than a 3×3 product)."""
    identity = np.eye(n)
    identity.setflags(write=False)
    return identity


def expm(A: ArrayLike) -> F64:
    """Matrix exponential of a small square matrix: scaling and squaring (the scaled matrix has ‖X‖₁ ≤ 0.5) with a
    Taylor series truncated where the next term is below the double-precision roundoff (at most degree 12; a
    Gauss-Newton increment of ~1e-3 needs 5 terms), evaluated in Horner form `I + X (I + X/2 (I + … X/k))`.
    Written for few numpy calls: it runs once per Gauss-Newton iteration."""
    A = np.asarray(A, dtype=np.float64)
    norm = float(np.abs(A).sum(axis=0).max())
    s = max(0, math.ceil(math.log2(norm)) + 1) if norm > 0.5 else 0
    X = A * 0.5**s if s else A  # (A · 1 is A)
    identity = _identity(A.shape[0])
    E = identity.copy()
    for k in range(_taylor_terms(norm * 0.5**s), 0, -1):
        E = X @ E
        E /= k
        E += identity
    for _ in range(s):
        E = E @ E
    return E


def sl3_exp(x: ArrayLike) -> F64:
    """`expm(Σ xᵢ Aᵢ)` ∈ SL(3) (determinant 1 because every generator is traceless)."""
    return expm(sl3_hat(x))


def det3(G: ArrayLike) -> float:
    """Determinant of a 3×3 matrix by the rule of Sarrus (no LAPACK call: the trackers take several per frame)."""
    a, b, c, d, e, f, g, h, i = np.asarray(G, dtype=np.float64).reshape(9).tolist()
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


def inv3(G: ArrayLike) -> F64:
    """Inverse of a 3×3 matrix: its adjugate over its determinant (no LAPACK call; a well-conditioned matrix such as
    one of SL(3) is inverted to round-off, as by an LU solve). A singular matrix gives infinities or NaN, no error."""
    a, b, c, d, e, f, g, h, i = np.asarray(G, dtype=np.float64).reshape(9).tolist()
    A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * A + b * B + c * C
    return np.array([[A, c * h - b * i, b * f - c * e], [B, a * i - c * g, c * d - a * f],
                     [C, b * g - a * h, a * e - b * d]]) / det


def sl3_normalize(G: ArrayLike) -> F64:
    """Scale a 3×3 matrix with positive determinant to determinant 1 (SL(3))."""
    G = np.asarray(G, dtype=np.float64)
    d = det3(G)
    if not math.isfinite(d) or d <= 0.0:
        raise ValueError(f"cannot normalise to SL(3): determinant is {d}, expected a positive finite value")
    return G / np.cbrt(d)
