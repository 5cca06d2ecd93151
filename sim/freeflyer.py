"""Free-flying camera plant: the camera pose integrates the commanded body twist exactly over each sampling period
(`T_world_cam ← T_world_cam · se3_exp(twist · dt)`), and each observation is a ray-cast frame of an analytic
textured surface with its ground truth relative to the reference pose. Deterministic (the sensor noise is a
counter-based hash of the seed, the frame index and the pixel). No I/O: a Zenoh node wraps it elsewhere.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.lie import se3_exp
from sim.ground_truth import GroundTruth, ground_truth, parallax_map
from sim.surfaces import Surface

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]


@dataclass(frozen=True)
class Appearance:
    """Photometry of the rendered frames: `gain` = the 6 coefficients of the gain field
    `S = g0 + g1 x + g2 y + g3 x² + g4 x y + g5 y²` over normalised image coordinates `(x, y) = K⁻¹p`, `bias` β
    (grey levels), Gaussian noise of standard deviation `noise` (grey levels) seeded by `seed`, `background` albedo
    (grey level under unit gain) of the uniform backdrop around a finite target and where no surface is seen, and
    `quantize` (round and clip to [0, 255]). The illumination lights the backdrop as it lights the target."""

    gain: tuple[float, float, float, float, float, float] = (1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    bias: float = 0.0
    noise: float = 0.0
    seed: int = 0
    background: float = 128.0
    quantize: bool = False

    def __post_init__(self) -> None:
        if len(self.gain) != 6:
            raise ValueError(f"gain needs the 6 coefficients of a quadratic field, got {self.gain!r}")
        if not self.noise >= 0.0:
            raise ValueError(f"noise must be a non-negative standard deviation, got {self.noise}")


@dataclass(frozen=True)
class Frame:
    """One observation: `index` (0 at the start), `time` (s), `T_world_cam`, `image` and `depth` (float32 (H, W),
    grey levels and camera-frame Z in metres, `inf` where nothing is seen; `None` when not rendered) and `truth`
    (G, e, ρ* of the control point relative to the reference pose)."""

    index: int
    time: float
    T_world_cam: F64
    image: F32 | None
    depth: F32 | None
    truth: GroundTruth


def frame_key(seed: int, index: int) -> int:
    """uint32 noise key of frame `index` for `seed` (deterministic, distinct per frame)."""
    return int((np.uint64(seed) * np.uint64(0x9E3779B1) + np.uint64(index) * np.uint64(0x85EBCA77)) & 0xFFFFFFFF)


def render_view(
    surface: Surface,
    texture: F32,
    intrinsics: Intrinsics,
    T_world_cam: ArrayLike,
    appearance: Appearance = Appearance(),
    index: int = 0,
    backdrop: ArrayLike | None = None,
) -> tuple[F32, F32]:
    """Ray-cast `(image, depth)` of `surface` textured with `texture` (2-D grey array) seen from `T_world_cam`.

    Around a finite target (`surface.tiled` false) the surface shows `backdrop`, a second 2-D grey image repeated
    mirrored with one copy per target extent (distractors), or the uniform `appearance.background` when `None`;
    edges are anti-aliased (`kernels/raycast.py`)."""
    # Taichi is imported on first render only: exact-geometry runs (no images) never load it.
    from kernels import raycast
    from kernels.backend import init

    init()
    R, o = surface.camera_in_surface(T_world_cam)
    Ki = intrinsics.K_inv
    p = np.zeros(raycast.P_SIZE, dtype=np.float32)
    p[raycast.P_KINV : raycast.P_KINV + 5] = [Ki[0, 0], Ki[0, 1], Ki[0, 2], Ki[1, 1], Ki[1, 2]]
    p[raycast.P_R : raycast.P_R + 9] = R.ravel()
    p[raycast.P_O : raycast.P_O + 3] = o
    p[raycast.P_KIND] = surface.kind
    p[raycast.P_A] = surface.shape_parameter
    p[raycast.P_EXTENT : raycast.P_EXTENT + 2] = surface.extent
    p[raycast.P_GAIN : raycast.P_GAIN + 6] = appearance.gain
    p[raycast.P_BIAS] = appearance.bias
    p[raycast.P_NOISE] = appearance.noise
    p[raycast.P_BACKGROUND] = appearance.background
    p[raycast.P_QUANTIZE] = float(appearance.quantize)
    p[raycast.P_TILED] = float(surface.tiled)
    image = np.empty((intrinsics.height, intrinsics.width), dtype=np.float32)
    depth = np.empty_like(image)
    tex = np.ascontiguousarray(texture, dtype=np.float32)
    back = np.full((1, 1), appearance.background, np.float32) if backdrop is None else np.ascontiguousarray(
        backdrop, dtype=np.float32)
    for name, arr in (("texture", tex), ("backdrop", back)):
        if arr.ndim != 2 or arr.size == 0:
            raise ValueError(f"{name} must be a non-empty 2-D grey image, got shape {arr.shape}")
    raycast.render(p, tex, back, image, depth, frame_key(appearance.seed, index))
    return image, depth


def render_camera(
    surface: Surface,
    texture: F32,
    intrinsics: Intrinsics,
    T_world_cam: ArrayLike,
    psf_sigma: float = 0.5,
    oversample: int = 4,
) -> F32:
    """Noise-free grey image of `surface` (unit gain, no bias) as a camera forms it, float32 (H, W): the scene
    through a Gaussian optical blur of standard deviation `psf_sigma` (output pixels; 0: none), integrated over each
    pixel's square area, read at the pixel grid. `render_view` point-samples instead (one ray per pixel centre), which
    aliases texture detail finer than the pixel grid: no interpolation of such frames reproduces a sub-pixel motion.

    Computed by ray casting at `oversample`× the resolution (`render_view` with the intrinsics of the sub-pixel grid,
    `oversample²` rays per pixel on a regular grid over its area), a Gaussian blur of `psf_sigma · oversample`
    sub-pixels (mirrored border) and the mean of each `oversample × oversample` block. Pixel-centre coordinates:
    output pixel `u` covers `[u − ½, u + ½]`, whose sub-pixel `j` is centred at `u − ½ + (j + ½)/oversample`."""
    if not (isinstance(oversample, int) and oversample >= 1):
        raise ValueError(f"oversample must be a positive number of sub-pixels per pixel side, got {oversample!r}")
    if not psf_sigma >= 0.0:
        raise ValueError(f"psf_sigma must be a non-negative standard deviation in pixels, got {psf_sigma}")
    import cv2

    k = oversample
    S = np.array([[k, 0.0, 0.5 * (k - 1)], [0.0, k, 0.5 * (k - 1)], [0.0, 0.0, 1.0]])  # pixel → sub-pixel grid
    fine = Intrinsics.from_matrix(S @ intrinsics.K, k * intrinsics.width, k * intrinsics.height)
    image = render_view(surface, texture, fine, T_world_cam)[0]
    if psf_sigma > 0.0:
        image = np.asarray(cv2.GaussianBlur(image, (0, 0), psf_sigma * k, borderType=cv2.BORDER_REFLECT), np.float32)
    blocks = image.reshape(intrinsics.height, k, intrinsics.width, k)
    return blocks.mean(axis=(1, 3), dtype=np.float64).astype(np.float32)


class FreeFlyer:
    """A camera flying freely in front of `surface`, sampled every `dt` seconds.

    `T_world_ref` is the reference camera pose and `T_world_start` the initial one (4×4, OpenCV camera axes).
    `texture` is needed only to render images; `backdrop` is the second texture around a finite target (see
    `render_view`; `None`: uniform `appearance.background`). `p_star` is the control pixel of the ground truth
    (default principal point); `scaling` its scale gauge ("sl3" or "euclidean", see `sim.ground_truth`).
    """

    def __init__(
        self,
        surface: Surface,
        intrinsics: Intrinsics,
        T_world_ref: ArrayLike,
        T_world_start: ArrayLike,
        dt: float,
        texture: ArrayLike | None = None,
        appearance: Appearance = Appearance(),
        backdrop: ArrayLike | None = None,
        p_star: tuple[float, float] | None = None,
        scaling: str = "sl3",
    ) -> None:
        if not dt > 0.0:
            raise ValueError(f"the sampling period dt must be positive seconds, got {dt}")
        self.surface = surface
        self.intrinsics = intrinsics
        self.T_world_ref = np.asarray(T_world_ref, dtype=np.float64).copy()
        self.T_world_cam = np.asarray(T_world_start, dtype=np.float64).copy()
        self.dt = float(dt)
        self.texture = None if texture is None else np.ascontiguousarray(texture, dtype=np.float32)
        self.appearance = appearance
        self.backdrop = None if backdrop is None else np.ascontiguousarray(backdrop, dtype=np.float32)
        self.p_star = p_star
        self.scaling = scaling
        self.index = 0

    def move(self, twist: ArrayLike) -> None:
        """Apply the body twist `[v; ω]` (m/s, rad/s, current camera frame) for one period, exactly."""
        xi = np.asarray(twist, dtype=np.float64).reshape(6)
        if not np.all(np.isfinite(xi)):
            raise ValueError(f"twist must be 6 finite numbers, got {xi}")
        self.T_world_cam = self.T_world_cam @ se3_exp(xi * self.dt)
        self.index += 1

    def observe(self, render: bool = True) -> Frame:
        """The current frame: ground truth always, image and depth when `render` (needs a texture)."""
        truth = ground_truth(
            self.surface, self.intrinsics, self.T_world_ref, self.T_world_cam, self.p_star, self.scaling
        )
        image = depth = None
        if render:
            if self.texture is None:
                raise ValueError("rendering needs a texture: build the FreeFlyer with texture=<2-D grey image>")
            image, depth = render_view(
                self.surface, self.texture, self.intrinsics, self.T_world_cam, self.appearance, self.index,
                self.backdrop,
            )
        return Frame(self.index, self.index * self.dt, self.T_world_cam.copy(), image, depth, truth)

    def step(self, twist: ArrayLike, render: bool = True) -> Frame:
        """`move(twist)` then `observe(render)`."""
        self.move(twist)
        return self.observe(render)

    @cached_property
    def rho_map(self) -> F64:
        """ρ* (1/m) of every reference pixel, (H, W); constant over time (see `sim.ground_truth`)."""
        return parallax_map(self.surface, self.intrinsics, self.T_world_ref)
