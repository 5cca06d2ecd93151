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
class CameraSpec:
    """Camera intrinsics (OpenCV, pixel centres), clipping planes (metres) and mount `T_link_cam` on `link`."""

    intrinsics: Intrinsics
    link: str
    T_link_cam: F64
    near: float = 0.02
    far: float = 10.0


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
    targets, physics rate (Hz), optional illumination ramp, optional start pose, whether robot meshes are drawn."""

    urdf: str
    home: tuple[float, ...]
    camera: CameraSpec
    targets: tuple[TargetSpec, ...]
    physics_hz: float = 240.0
    illumination: IlluminationRamp | None = None
    start: StartPose | None = None
    show_robot: bool = True


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
    )


def load_scene_config(path: str | Path) -> ArmSceneConfig:
    """Read and parse a JSON scene file."""
    with open(path, encoding="utf-8") as f:
        return scene_config_from_dict(json.load(f))
