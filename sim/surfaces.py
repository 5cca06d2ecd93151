"""Analytic textured target surfaces: a plane in any pose and the hyperbolic paraboloid ("horse saddle").

Each surface lives in its own local frame, placed in the world by `T_world_surface` (4×4, metres):
- `Plane`: local `z = 0`, normal along local +z.
- `Saddle`: local `z = (x² − y²)/a` (`a` in metres); the paper's target is the saddle with identity rotation and
  centre `[0, 0, 1]` in the reference camera frame, i.e. `Z = 1 + (X² − Y²)/a` (the notes use `a = 1 m`).
The texture is glued by the local `(x, y)` coordinates (orthographic along local z): the image spans
`[−w/2, w/2] × [−h/2, h/2]` metres (`extent = (w, h)`), columns along +x, rows along +y. By default the target is
finite: outside its extent the surface carries a backdrop (a uniform grey or a second texture, see
`sim.freeflyer.render_view`), like a poster on a wall. With `tiled=True` the texture repeats mirrored over the whole
surface instead (a target that fills any view; it has twin poses: mirrored copies of the goal's view). The
float64 intersection here is the exact reference (ground truth); `kernels/raycast.py` renders the same surfaces in
float32 (tests compare the two).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.lie import pose_inv

F64 = NDArray[np.float64]

PLANE_KIND = 0
SADDLE_KIND = 1


def _check_pose(T: ArrayLike) -> F64:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9):
        raise ValueError(f"T_world_surface must be a rigid 4×4 transform, got {T!r}")
    return T


@dataclass(frozen=True)
class Surface(ABC):
    """Common part: pose of the local frame in the world, textured extent `(w, h)` in metres, and `tiled` (the
    texture repeats mirrored over the whole surface instead of a finite target on a backdrop)."""

    T_world_surface: F64
    extent: tuple[float, float]
    tiled: bool = field(default=False, kw_only=True)

    def __post_init__(self) -> None:
        object.__setattr__(self, "T_world_surface", _check_pose(self.T_world_surface))
        w, h = (float(v) for v in self.extent)
        if not (w > 0.0 and h > 0.0):
            raise ValueError(f"texture extent must be positive metres, got {self.extent}")
        object.__setattr__(self, "extent", (w, h))

    @property
    @abstractmethod
    def kind(self) -> int:
        """Surface code for the kernel (`PLANE_KIND`, `SADDLE_KIND`)."""

    @property
    def shape_parameter(self) -> float:
        """The kernel's shape parameter (`a` for the saddle, unused for the plane)."""
        return 0.0

    def camera_in_surface(self, T_world_cam: ArrayLike) -> tuple[F64, F64]:
        """`(R_surface_cam, o)`: rotation taking camera-frame directions to the local frame, and the camera centre
        in the local frame (metres)."""
        T = pose_inv(self.T_world_surface) @ np.asarray(T_world_cam, dtype=np.float64)
        return T[:3, :3], T[:3, 3]

    @abstractmethod
    def _local_roots(self, o: F64, d: F64) -> F64:
        """Smallest positive ray parameter `s` of `o + s d` on the surface (local frame), `inf` when none."""

    def intersect(self, T_world_cam: ArrayLike, m: ArrayLike) -> F64:
        """Depth (camera-frame Z, metres) at which the rays `m` (N×3, camera frame, third component 1) first hit
        the surface in front of the camera; `inf` where they miss."""
        R, o = self.camera_in_surface(T_world_cam)
        d = np.asarray(m, dtype=np.float64).reshape(-1, 3) @ R.T
        return self._local_roots(o, d)

    @abstractmethod
    def reference_plane(self, T_world_ref: ArrayLike) -> F64:
        """Scaled normal `n*` (1/m, `n*ᵀ X* = 1`) of the gauge plane in the reference camera frame."""


def _first_positive(s1: F64, s2: F64) -> F64:
    s1 = np.where(s1 > 0.0, s1, np.inf)
    s2 = np.where(s2 > 0.0, s2, np.inf)
    return np.minimum(s1, s2)


@dataclass(frozen=True)
class Plane(Surface):
    """Textured plane `z = 0` of its local frame. Gauge plane: the target plane itself."""

    @property
    def kind(self) -> int:
        return PLANE_KIND

    def _local_roots(self, o: F64, d: F64) -> F64:
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -o[2] / d[:, 2]
        return np.where(np.isfinite(s) & (s > 0.0), s, np.inf)

    def reference_plane(self, T_world_ref: ArrayLike) -> F64:
        T = pose_inv(np.asarray(T_world_ref, dtype=np.float64)) @ self.T_world_surface
        normal, point = T[:3, 2], T[:3, 3]
        offset = float(normal @ point)
        if abs(offset) < 1e-12:
            raise ValueError("the reference camera centre lies on the target plane: no plane gauge n*ᵀX* = 1")
        return normal / offset


@dataclass(frozen=True)
class Saddle(Surface):
    """Hyperbolic paraboloid `z = (x² − y²)/a` of its local frame (`a` > 0, metres). Gauge plane: through the
    saddle centre, fronto-parallel to the reference camera (`n* = [0, 0, 1/Z_c]`, `Z = 1 m` for the paper)."""

    a: float = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.a > 0.0:
            raise ValueError(f"saddle parameter a must be positive metres, got {self.a}")

    @property
    def kind(self) -> int:
        return SADDLE_KIND

    @property
    def shape_parameter(self) -> float:
        return float(self.a)

    def _local_roots(self, o: F64, d: F64) -> F64:
        # (o + s d) on the surface: A s² + B s + C = 0.
        A = d[:, 0] ** 2 - d[:, 1] ** 2
        B = 2.0 * (o[0] * d[:, 0] - o[1] * d[:, 1]) - self.a * d[:, 2]
        C = o[0] ** 2 - o[1] ** 2 - self.a * o[2]
        disc = B**2 - 4.0 * A * C
        with np.errstate(divide="ignore", invalid="ignore"):
            q = -0.5 * (B + np.copysign(np.sqrt(np.maximum(disc, 0.0)), B))
            quadratic = _first_positive(q / A, C / q)
            linear = np.where(B != 0.0, -C / B, np.inf)
        s = np.where(np.abs(A) > 1e-12 * np.maximum(np.abs(B), 1.0), quadratic, _first_positive(linear, linear))
        return np.where(disc >= 0.0, s, np.inf)

    def reference_plane(self, T_world_ref: ArrayLike) -> F64:
        centre = (pose_inv(np.asarray(T_world_ref, dtype=np.float64)) @ self.T_world_surface)[:3, 3]
        if not centre[2] > 0.0:
            raise ValueError(f"the saddle centre must be in front of the reference camera, got Z = {centre[2]}")
        return np.array([0.0, 0.0, 1.0 / centre[2]])


def paper_saddle(
    depth: float = 1.0, a: float = 1.0, extent: tuple[float, float] = (1.0, 0.75), tiled: bool = False
) -> Saddle:
    """The paper's target: saddle centred `depth` metres in front of the reference camera (world = reference frame)."""
    T = np.eye(4)
    T[2, 3] = depth
    return Saddle(T, extent, a, tiled=tiled)
