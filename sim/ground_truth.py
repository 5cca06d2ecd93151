"""Ground-truth projective parameters `G`, `e`, `ρ*` of (2) from the reference and current camera poses and the
scene (simulation and tests only; the controller never sees poses or depth).

Gauge (fixes the freedoms of (2), as in docs/plane-parallax-estimation.md):
- plane gauge: the reference plane is the surface's `reference_plane` — the target plane itself for a `Plane`, the
  plane fronto-parallel to the reference camera through the saddle centre (`Z = 1 m` in the paper) for a `Saddle`.
  With its scaled normal `n*` (`n*ᵀ X* = 1`, 1/m) and the relative pose `X = R X* + t` (current from reference
  camera frame): `H_E = R + t n*ᵀ`, `G = K H_E K⁻¹ / s`, `e = K t / s`, `ρ*(p*) = 1/Z*(p*) − n*ᵀ m*'` (1/m), so
  `q*' = n*` and `p ∝ G p* + ρ* e` exactly.
- scale gauge: `scaling="sl3"` takes `s = det(H_E)^(1/3)` (`det G = 1`, what an estimator on SL(3) returns);
  `scaling="euclidean"` takes `s = 1` (`H` carries the Euclidean scale, `ε_v = (R − I) m*' + t/z*`).
  `ρ*` does not depend on the current pose in either gauge.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.lie import pose_inv
from sim.surfaces import Surface

F64 = NDArray[np.float64]

SCALINGS = ("sl3", "euclidean")


@dataclass(frozen=True)
class GroundTruth:
    """`G` (3×3, pixels), `e` (3, pixels, homogeneous, same scale as `G`), `rho` (ρ* of the control point, 1/m),
    `z_star` (depth of the control point in the reference frame, m), `q_star` (`q*' = n*`, 1/m) and the relative
    pose `T_cur_ref` (maps reference-frame coordinates to the current frame: `X = R X* + t`)."""

    G: F64
    e: F64
    rho: float
    z_star: float
    q_star: F64
    T_cur_ref: F64


def homography_and_epipole(
    T_cur_ref: ArrayLike, n_ref: ArrayLike, K: ArrayLike, scaling: str = "sl3"
) -> tuple[F64, F64]:
    """`(G, e)` of the plane `n_refᵀ X* = 1` for the relative pose `T_cur_ref`, in the gauge described above."""
    if scaling not in SCALINGS:
        raise ValueError(f"unknown scaling {scaling!r}; expected one of {SCALINGS}")
    T = np.asarray(T_cur_ref, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    H = R + np.outer(t, np.asarray(n_ref, dtype=np.float64).reshape(3))
    det = float(np.linalg.det(H))
    if not det > 0.0:
        raise ValueError(f"det(R + t n*ᵀ) = {det:.3g}: the current camera is not on the reference side of the plane")
    s = np.cbrt(det) if scaling == "sl3" else 1.0
    return K @ H @ np.linalg.inv(K) / s, K @ t / s


def parallax(m: ArrayLike, depth: ArrayLike, n_ref: ArrayLike) -> F64:
    """`ρ* = 1/Z* − n*ᵀ m*'` (1/m) of reference rays `m` (N×3, third component 1) seen at depths `Z*` (m)."""
    m = np.asarray(m, dtype=np.float64).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        return 1.0 / np.asarray(depth, dtype=np.float64).reshape(-1) - m @ np.asarray(n_ref, dtype=np.float64)


def parallax_map(surface: Surface, intrinsics: Intrinsics, T_world_ref: ArrayLike) -> F64:
    """ρ* (1/m) of every reference pixel, shape (height, width); `−n*ᵀm*'` (1/Z* = 0) where the ray misses."""
    u, v = np.meshgrid(np.arange(intrinsics.width, dtype=np.float64), np.arange(intrinsics.height, dtype=np.float64))
    p = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)
    m = p @ intrinsics.K_inv.T
    rho = parallax(m, surface.intersect(T_world_ref, m), surface.reference_plane(T_world_ref))
    return rho.reshape(intrinsics.height, intrinsics.width)


def ground_truth(
    surface: Surface,
    intrinsics: Intrinsics,
    T_world_ref: ArrayLike,
    T_world_cur: ArrayLike,
    p_star: ArrayLike | None = None,
    scaling: str = "sl3",
) -> GroundTruth:
    """Exact `G`, `e`, `ρ*` of the control pixel `p_star` (default principal point) for the current pose."""
    T_cur_ref = pose_inv(np.asarray(T_world_cur, dtype=np.float64)) @ np.asarray(T_world_ref, dtype=np.float64)
    n_ref = surface.reference_plane(T_world_ref)
    p = (intrinsics.cx, intrinsics.cy) if p_star is None else p_star
    m = intrinsics.normalize(p)
    z = float(surface.intersect(T_world_ref, m)[0])
    if not np.isfinite(z):
        raise ValueError(f"the control pixel {np.asarray(p).tolist()} does not see the surface from the reference pose")
    G, e = homography_and_epipole(T_cur_ref, n_ref, intrinsics.K, scaling)
    return GroundTruth(G, e, float(parallax(m, [z], n_ref)[0]), z, n_ref, T_cur_ref)
