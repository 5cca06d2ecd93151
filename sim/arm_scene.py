"""Description of the simulated arm scene: robot + camera mount, textured targets, illumination script.

Everything here is plain data and geometry (numpy, OpenCV for image files); `sim/arm.py` turns it into a SAPIEN scene.

Frames: the world frame is the robot base frame (URDF root link, z up). A *target frame* has its origin at the
centre of the textured surface, x along the texture's columns (image right), y along its rows (image down) and z
pointing *into* the surface, away from the viewer: a camera at `pose(I, [0, 0, −d])` in the target frame (OpenCV axes)
sees the texture upright and fronto-parallel at distance d metres. Poses in JSON are `{"t": metres, "r_deg": θu}`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.kinematics import pose_from_dict

F64 = NDArray[np.float64]
TARGET_KINDS = ("poster", "saddle")
# Procedural textures get this many texels per metre of target: ~1.1–1.4 texels per pixel for f ≈ 420 px at 0.5–0.7 m.
TEXELS_PER_METRE = 800


@dataclass(frozen=True)
class TargetMesh:
    """Triangle mesh in its target frame: vertices (N, 3) metres, triangles (M, 3), unit normals (N, 3), UVs (N, 2)."""

    vertices: NDArray[np.float32]
    triangles: NDArray[np.uint32]
    normals: NDArray[np.float32]
    uvs: NDArray[np.float32]


def surface_mesh(width: float, height: float, curvature: float, cells: int) -> TargetMesh:
    """Grid mesh of `z = curvature · (x² − y²)` (metres, curvature in 1/m) over a width × height rectangle.

    `curvature = 0` is a flat poster; otherwise the hyperbolic paraboloid of `sim/surfaces.py::Saddle` with
    `a = 1/curvature`, texture glued by (x, y) the same way, so its exact ground truth applies. UV (0, 0) is the
    texture's top-left corner at (−width/2, −height/2). Triangles wind counter-clockwise as seen from the viewer side
    (z < 0), so the textured face is the one a camera in front of the target sees; normals point to the viewer.
    """
    if width <= 0 or height <= 0 or cells < 1:
        raise ValueError(f"need width, height > 0 and cells ≥ 1, got {width}, {height}, {cells}")
    s = np.linspace(0.0, 1.0, cells + 1)
    uu, vv = np.meshgrid(s, s)  # [row = v, col = u]
    x, y = (uu - 0.5) * width, (vv - 0.5) * height
    z = curvature * (x**2 - y**2)
    # Normal towards the viewer (−z side) of the surface z = f(x, y): (f_x, f_y, −1) normalised.
    n = np.stack([2 * curvature * x, -2 * curvature * y, -np.ones_like(x)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    idx = np.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1)
    tl, tr, bl, br = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    # (br − tl) × (tr − tl) points to −z, i.e. towards the viewer: counter-clockwise as seen from the camera.
    tris = np.concatenate([np.stack([tl, br, tr], -1).reshape(-1, 3), np.stack([tl, bl, br], -1).reshape(-1, 3)])
    return TargetMesh(
        vertices=np.stack([x, y, z], -1).reshape(-1, 3).astype(np.float32),
        triangles=tris.astype(np.uint32),
        normals=n.reshape(-1, 3).astype(np.float32),
        uvs=np.stack([uu, vv], -1).reshape(-1, 2).astype(np.float32),
    )


def procedural_texture(width: int, height: int, seed: int) -> NDArray[np.uint8]:
    """Grey texture of smooth random blobs at three scales (good gradients for direct methods), values 20..235."""
    rng = np.random.default_rng(seed)
    image = np.zeros((height, width), np.float64)
    for cell, weight in ((64, 1.0), (16, 0.6), (4, 0.25)):
        coarse = rng.uniform(-1.0, 1.0, (max(2, height // cell), max(2, width // cell)))
        image += weight * cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
    image -= image.min()
    image *= 215.0 / max(float(image.max()), 1e-12)
    return (image + 20.0).astype(np.uint8)


def load_texture(path: str | None, seed: int = 0, size: tuple[int, int] = (640, 480)) -> NDArray[np.uint8]:
    """Grey uint8 texture [row, col]: any image file OpenCV reads (colour converted to grey), or, when `path` is None,
    a `procedural_texture` of `size` (width, height) from `seed`."""
    if path is None:
        return procedural_texture(size[0], size[1], seed)
    image = cv2.imread(str(Path(path).expanduser()), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise FileNotFoundError(f"cannot read texture image {path!r} (missing file or format OpenCV cannot decode)")
    return np.asarray(image, dtype=np.uint8)


@dataclass(frozen=True)
class TargetSpec:
    """A textured target: `kind` "poster" (flat) or "saddle" (`z = curvature (x² − y²)`, curvature in 1/m), size in
    metres, `T_world_target` its pose, `texture` an image path (None: procedural from `seed`), `cells` per side."""

    kind: str
    width: float
    height: float
    T_world_target: F64
    curvature: float = 0.0
    texture: str | None = None
    seed: int = 0
    cells: int = 1

    def __post_init__(self) -> None:
        if self.kind not in TARGET_KINDS:
            raise ValueError(f"target kind {self.kind!r} unknown; expected one of {TARGET_KINDS}")
        if self.kind == "poster" and self.curvature != 0.0:
            raise ValueError("a poster is flat: curvature must be 0 (use kind 'saddle' for a curved target)")

    def mesh(self) -> TargetMesh:
        return surface_mesh(self.width, self.height, self.curvature, self.cells)

    def texture_image(self) -> NDArray[np.uint8]:
        """The grey texture: the image file, or a procedural one at `TEXELS_PER_METRE`."""
        size = (round(self.width * TEXELS_PER_METRE), round(self.height * TEXELS_PER_METRE))
        return load_texture(self.texture, self.seed, size)


@dataclass(frozen=True)
class IlluminationRamp:
    """Scripted illumination change: image gain 1 until `t_start`, linear to `gain` at `t_end`, then `gain` (seconds
    of simulated time). Applied to the rendered grey levels (saturating at 255), like a global light/exposure change."""

    gain: float
    t_start: float
    t_end: float

    def __post_init__(self) -> None:
        if self.gain < 0 or self.t_end < self.t_start:
            raise ValueError(f"need gain ≥ 0 and t_end ≥ t_start, got {self}")

    def at(self, t: float) -> float:
        if t <= self.t_start:
            return 1.0
        if t >= self.t_end:
            return self.gain
        return 1.0 + (self.gain - 1.0) * (t - self.t_start) / (self.t_end - self.t_start)


@dataclass(frozen=True)
class LightSpec:
    """A directional light (a SAPIEN light entity, rendered by SAPIEN's `minimal` shader) shining along `direction`
    (world frame, normalised here), its intensity scripted by `ramp` over simulated time (None: constant 1).

    Units: at intensity 1 a Lambertian surface facing the light shows its texture's grey levels (the light's
    radiance is π · intensity, the shader's BRDF albedo/π); the camera's response is linear (the shader's 1/2.2
    encoding is undone), so grey levels scale with the intensity and with the cosine of the incidence angle."""

    direction: tuple[float, float, float]
    ramp: IlluminationRamp | None = None

    def __post_init__(self) -> None:
        d = np.asarray(self.direction, dtype=np.float64)
        if d.shape != (3,) or not np.linalg.norm(d) > 0.0:
            raise ValueError(f"light direction must be a non-zero 3-vector (world frame), got {self.direction}")
        object.__setattr__(self, "direction", tuple(float(v) for v in d / np.linalg.norm(d)))

    def intensity(self, t: float) -> float:
        return 1.0 if self.ramp is None else self.ramp.at(t)


@dataclass(frozen=True)
class OccluderSpec:
    """A flat textured plate (`width` × `height` m, `texture` image path or procedural `seed`) moved into view: in
    the frame of target `target` it rests at `T_target_plate` (plate frame as a target frame: z away from the viewer)
    translated by `offset` (m, target frame) until `t_start`, slides linearly to `T_target_plate` by `t_end`, then
    stays (seconds of simulated time). A render-only SAPIEN entity, lit as the targets are."""

    width: float
    height: float
    T_target_plate: F64
    offset: tuple[float, float, float]
    t_start: float
    t_end: float
    target: int = 0
    texture: str | None = None
    seed: int = 1

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0 or self.t_end < self.t_start:
            raise ValueError(f"occluder needs width, height > 0 and t_end ≥ t_start, got {self.width}, {self.height}, "
                             f"{self.t_start}, {self.t_end}")

    def plate(self) -> TargetSpec:
        """The plate as a poster `TargetSpec` (its pose the identity: `T_target_plate_at` places it)."""
        return TargetSpec("poster", self.width, self.height, np.eye(4), texture=self.texture, seed=self.seed)

    def T_target_plate_at(self, t: float) -> F64:
        """The plate's pose in the target frame at simulated time `t` (s)."""
        span = self.t_end - self.t_start
        s = 1.0 if t >= self.t_end else 0.0 if t <= self.t_start or span <= 0.0 else (t - self.t_start) / span
        T = np.asarray(self.T_target_plate, dtype=np.float64).copy()
        T[:3, 3] += (1.0 - s) * np.asarray(self.offset, dtype=np.float64)
        return T


@dataclass(frozen=True)
class CameraSpec:
    """Camera intrinsics (OpenCV, pixel centres), clipping planes (metres) and mount `T_link_cam` on `link`.

    Image formation (`sim/arm.py` `ArmSim.render`): `oversample` 1 point-samples the scene at each pixel centre
    (SAPIEN's raster); `oversample` k > 1 renders k×k sub-pixels per pixel and averages them (the pixel's area, as a
    sensor integrates), after a Gaussian optical blur of `psf_sigma` output pixels (0: none)."""

    intrinsics: Intrinsics
    link: str
    T_link_cam: F64
    near: float = 0.02
    far: float = 10.0
    oversample: int = 1
    psf_sigma: float = 0.0

    def __post_init__(self) -> None:
        if not (isinstance(self.oversample, int) and self.oversample >= 1):
            raise ValueError(f"camera oversample must be a positive number of sub-pixels per side, got "
                             f"{self.oversample!r}")
        if not self.psf_sigma >= 0.0:
            raise ValueError(f"camera psf_sigma must be a non-negative standard deviation in pixels, got "
                             f"{self.psf_sigma}")


@dataclass(frozen=True)
class StartPose:
    """Initial camera pose: `T_target_ref` (reference camera in the frame of target `target`) composed with the
    displacement `T_ref_init` (initial camera in the reference camera frame, as the paper reports it)."""

    target: int
    T_target_ref: F64
    T_ref_init: F64


@dataclass(frozen=True)
class ArmSceneConfig:
    """Whole scene: robot URDF (plain path or `package://`), its home joint positions (IK seed), the camera, the
    targets, physics rate (Hz), optional illumination ramp (a gain on the rendered grey levels), optional start pose,
    whether robot meshes are drawn, an optional directional `light` (None: ambient light only, unlit albedo) and
    `occluders` moved into view."""

    urdf: str
    home: tuple[float, ...]
    camera: CameraSpec
    targets: tuple[TargetSpec, ...]
    physics_hz: float = 240.0
    illumination: IlluminationRamp | None = None
    start: StartPose | None = None
    show_robot: bool = True
    light: LightSpec | None = None
    occluders: tuple[OccluderSpec, ...] = ()


def _intrinsics(spec: dict) -> Intrinsics:
    w, h = int(spec["width"]), int(spec["height"])
    fx = float(spec["fx"])
    fy = float(spec.get("fy", fx))
    return Intrinsics(fx, fy, float(spec.get("cx", (w - 1) / 2.0)), float(spec.get("cy", (h - 1) / 2.0)), w, h)


def scene_config_from_dict(config: dict) -> ArmSceneConfig:
    """Parse a `configs/arm/*.json` scene mapping (see configs/arm/README.md for the keys)."""
    robot, cam = config["robot"], config["camera"]
    camera = CameraSpec(
        intrinsics=_intrinsics(cam),
        link=robot["camera_link"],
        T_link_cam=pose_from_dict(robot.get("mount", {})),
        near=float(cam.get("near", 0.02)),
        far=float(cam.get("far", 10.0)),
        oversample=int(cam.get("oversample", 1)),
        psf_sigma=float(cam.get("psf_sigma", 0.0)),
    )
    targets = tuple(
        TargetSpec(
            kind=t["kind"], width=float(t["width"]), height=float(t["height"]),
            T_world_target=pose_from_dict(t.get("pose", {})), curvature=float(t.get("curvature", 0.0)),
            texture=t.get("texture"), seed=int(t.get("seed", 0)), cells=int(t.get("cells", 1)),
        )
        for t in config.get("targets", [])
    )
    ramp = config.get("illumination")
    start = config.get("start")
    light = config.get("light")
    return ArmSceneConfig(
        urdf=robot["urdf"],
        home=tuple(float(v) for v in robot["home"]),
        camera=camera,
        targets=targets,
        physics_hz=float(config.get("physics_hz", 240.0)),
        illumination=IlluminationRamp(**ramp) if ramp else None,
        start=StartPose(
            int(start.get("target", 0)), pose_from_dict(start["reference"]), pose_from_dict(start["displacement"])
        )
        if start
        else None,
        show_robot=bool(config.get("show_robot", True)),
        light=LightSpec(tuple(light["direction"]), IlluminationRamp(**light["ramp"]) if light.get("ramp") else None)
        if light
        else None,
        occluders=tuple(_occluder(o) for o in config.get("occluders", [])),
    )


def _occluder(spec: dict) -> OccluderSpec:
    offset = [float(v) for v in spec.get("offset", (0.0, 0.0, 0.0))]
    if len(offset) != 3:
        raise ValueError(f"occluder offset must be 3 numbers (m, target frame), got {offset}")
    return OccluderSpec(
        width=float(spec["width"]), height=float(spec["height"]), T_target_plate=pose_from_dict(spec.get("pose", {})),
        offset=(offset[0], offset[1], offset[2]), t_start=float(spec["t_start"]),
        t_end=float(spec["t_end"]), target=int(spec.get("target", 0)), texture=spec.get("texture"),
        seed=int(spec.get("seed", 1)),
    )


def load_scene_config(path: str | Path) -> ArmSceneConfig:
    """Read and parse a JSON scene file."""
    with open(path, encoding="utf-8") as f:
        return scene_config_from_dict(json.load(f))
