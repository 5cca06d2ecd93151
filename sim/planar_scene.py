"""Synthetic planar scenes with exact ground-truth homographies (proofs and sweeps of the global initialiser).

A textured poster lies on the plane `n*ᵀ X* = d*` with `n* = [0, 0, 1]` (fronto-parallel to the reference camera)
at distance `d*` metres. Pose convention: the current camera pose is given *in the reference camera frame*,
`T_ref_cur = (R_c, t_c)` (OpenCV axes, metres), i.e. a point maps as `X = R_cᵀ (X* − t_c)`. The true homography from
reference pixels to current pixels is then `H = K (R + t n*ᵀ/d*) K⁻¹` with `R = R_cᵀ`, `t = −R_cᵀ t_c`
(docs/equations.md, "Euclidean meaning"). Both images are rendered from the same texture with
`cv2.warpPerspective` (bilinear), so the only reference/current mismatch is interpolation.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.lie import so3_exp
from ddvs_service.registration.warp_distance import roi_grid

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]

POSTER_BLUR_SIGMA = 1.0  # texels: the Gaussian that limits aliasing when a poster texture is rendered smaller


def plane_homography(K: F64, R_c: F64, t_c: F64, depth: float) -> F64:
    """`K (R + t n*ᵀ/d*) K⁻¹` for the plane Z* = depth, current pose `(R_c, t_c)` in the reference frame; H[2,2]=1."""
    R = R_c.T
    t = -R_c.T @ np.asarray(t_c, dtype=np.float64)
    H = K @ (R + np.outer(t, [0.0, 0.0, 1.0 / depth])) @ np.linalg.inv(K)
    return H / H[2, 2]


@dataclass(frozen=True)
class PlanarScene:
    """A poster of `texture` at `depth` m covering `extent` × the reference image width (centred on the axis)."""

    intrinsics: Intrinsics
    texture: F32
    depth: float = 0.7
    extent: float = 2.5

    @property
    def texture_to_reference(self) -> F64:
        """Homography from texture pixels to reference-image pixels (a scale and a shift)."""
        cam = self.intrinsics
        h_t, w_t = self.texture.shape
        a = self.extent * cam.width / w_t
        return np.array([[a, 0.0, cam.cx - a * (w_t - 1) / 2.0], [0.0, a, cam.cy - a * (h_t - 1) / 2.0], [0, 0, 1.0]])

    def render(self, H: F64 | None = None) -> F32:
        """The image seen through the reference-to-current homography `H` (identity: the reference image)."""
        cam = self.intrinsics
        M = (np.eye(3) if H is None else H) @ self.texture_to_reference
        image = cv2.warpPerspective(
            self.texture, M, (cam.width, cam.height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
        )
        return np.asarray(image, dtype=np.float32)

    def homography(self, R_c: F64, t_c: F64) -> F64:
        """Ground truth reference→current homography for the current pose `(R_c, t_c)` in the reference frame."""
        return plane_homography(self.intrinsics.K, R_c, t_c, self.depth)


def visible_fraction(H: F64, roi: tuple[int, int, int, int], width: int, height: int) -> float:
    """Fraction of the ROI pixels that H sends inside a width×height image (and in front of the camera)."""
    p = roi_grid(roi)
    q = np.c_[p, np.ones(len(p))] @ H.T
    front = q[:, 2] > 0
    u, v = q[:, 0] / q[:, 2], q[:, 1] / q[:, 2]
    inside = front & (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
    return float(np.mean(inside))


@dataclass(frozen=True)
class Displacement:
    """A random current pose: roll about the optical axis, tilt of the axis, scale (d*/depth) and ROI image shift."""

    roll: float  # radians, about the current optical axis
    tilt: float  # radians, angle between the optical axis and the plane normal
    tilt_axis: float  # radians, direction of the tilt axis in the image plane
    scale: float  # apparent scale of the ROI: reference depth / current depth of its centre
    shift: tuple[float, float]  # pixels, where the ROI centre lands relative to the image centre

    def pose(self, scene: PlanarScene, roi_centre: tuple[float, float]) -> tuple[F64, F64]:
        """`(R_c, t_c)` of the current camera in the reference frame realising this displacement."""
        cam = scene.intrinsics
        X0 = scene.depth * cam.normalize(roi_centre)  # ROI centre on the plane, reference frame
        axis = np.array([np.cos(self.tilt_axis), np.sin(self.tilt_axis), 0.0])
        R_c = so3_exp(self.tilt * axis) @ so3_exp([0.0, 0.0, self.roll])
        target = np.array([cam.cx + self.shift[0], cam.cy + self.shift[1]])
        X0_cur = (scene.depth / self.scale) * cam.normalize(target)
        return R_c, X0 - R_c @ X0_cur


def random_displacement(
    rng: np.random.Generator,
    width: int,
    height: int,
    max_tilt_deg: float = 40.0,
    scale_range: tuple[float, float] = (0.7, 1.4),
    max_shift_fraction: float = 0.5,
) -> Displacement:
    """Uniform roll in ±180°, tilt ≤ max_tilt_deg, log-uniform scale, shift ≤ max_shift_fraction of the image size."""
    return Displacement(
        roll=float(rng.uniform(-np.pi, np.pi)),
        tilt=float(np.radians(max_tilt_deg) * np.sqrt(rng.uniform())),
        tilt_axis=float(rng.uniform(0.0, 2.0 * np.pi)),
        scale=float(np.exp(rng.uniform(np.log(scale_range[0]), np.log(scale_range[1])))),
        shift=(
            float(rng.uniform(-1, 1) * max_shift_fraction * width),
            float(rng.uniform(-1, 1) * max_shift_fraction * height),
        ),
    )
