"""Rectification of raw camera frames: from the distorted image a `sensor_msgs/CameraInfo` describes to the pinhole
image the engine models, as ROS's `image_proc` does it.

A camera info describes the raw image by `k` and `d` (distortion model "plumb_bob", "rational_polynomial" or
"equidistant", the fisheye model) and the rectified image by `r` and the first 3×3 of `p` (the pinhole intrinsics
of `image_rect`). `camera_geometry` tells, for the images the service reads, which intrinsics the engine uses and
whether each frame must be rectified first:

- `image_raw` (rectified = False): a frame with distortion (or R ≠ I) is remapped to the image of `p` (`k` when `p`
  is all zeros) with maps computed once per camera info (`cv2.initUndistortRectifyMap`,
  `cv2.fisheye.initUndistortRectifyMap`; bilinear, black outside the raw image); without distortion the raw image
  is already the pinhole image of `k` and is used as it is;
- `image_rect` (rectified = True): the frame is already rectified; its intrinsics are `p`'s, whatever `d` says.

Pixel centres at integer coordinates (OpenCV's convention, the project's). The maps are float32: the interpolation
position keeps its full precision (the 16-bit fixed-point maps round it to 1/32 px).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.protocol.errors import InconsistentMessage, UnsupportedEncoding
from ddvs_service.protocol.ros import CameraInfo

DISTORTION_MODELS: dict[str, tuple[int, ...]] = {
    "plumb_bob": (4, 5),  # k1 k2 t1 t2 [k3]
    "rational_polynomial": (8,),  # k1 k2 t1 t2 k3 k4 k5 k6
    "equidistant": (4,),  # fisheye k1 k2 k3 k4
}
"""Supported `CameraInfo.distortion_model` names and their numbers of coefficients."""


@dataclass(frozen=True, eq=False)
class Rectifier:
    """Remaps raw frames (grey, the camera info's size) to the rectified pinhole image of `intrinsics`."""

    intrinsics: Intrinsics
    map_x: NDArray[np.float32]
    map_y: NDArray[np.float32]

    def __call__(self, frame: NDArray) -> NDArray:
        """The rectified frame (same dtype as `frame`); `ValueError` when `frame` is not the raw image's size."""
        import cv2

        if frame.shape[:2] != self.map_x.shape:
            raise ValueError(f"frame is {frame.shape[1]}×{frame.shape[0]}; the camera info is for "
                             f"{self.map_x.shape[1]}×{self.map_x.shape[0]} images")
        return np.asarray(cv2.remap(frame, self.map_x, self.map_y, cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=0))


@dataclass(frozen=True, eq=False)
class CameraGeometry:
    """What the engine needs of a camera info: the pinhole `intrinsics` of the frames it registers, and the
    `rectifier` each raw frame goes through first (None: the frames are used as they arrive)."""

    intrinsics: Intrinsics
    rectifier: Rectifier | None

    def frame(self, pixels: NDArray) -> NDArray:
        """`pixels` as the engine registers them (rectified when needed)."""
        return pixels if self.rectifier is None else self.rectifier(pixels)


def camera_geometry(info: CameraInfo, rectified: bool) -> CameraGeometry:
    """The geometry of frames described by `info`: `rectified` for `image_rect`, False for `image_raw` (module
    docstring). Raises `InconsistentMessage` / `UnsupportedEncoding` naming what the camera info gets wrong."""
    if rectified:
        return CameraGeometry(info.rectified_intrinsics(), None)
    R = info.r.reshape(3, 3)
    if not info.distorted and (np.array_equal(R, np.eye(3)) or not np.any(R)):
        return CameraGeometry(info.to_intrinsics(), None)
    return CameraGeometry(*_rectifier(info))


def _rectifier(info: CameraInfo) -> tuple[Intrinsics, Rectifier]:
    import cv2

    model = info.distortion_model
    if model not in DISTORTION_MODELS:
        raise UnsupportedEncoding(f"CameraInfo.distortion_model {model!r} is not supported; expected one of "
                                  f"{', '.join(DISTORTION_MODELS)}")
    if info.d.size not in DISTORTION_MODELS[model]:
        raise InconsistentMessage(f"CameraInfo.d has {info.d.size} coefficients; {model} has "
                                  f"{' or '.join(map(str, DISTORTION_MODELS[model]))}")
    if not np.all(np.isfinite(info.d)):
        raise InconsistentMessage(f"CameraInfo.d = {info.d.tolist()}: expected finite coefficients")
    K = info.to_intrinsics().K
    target = info.rectified_intrinsics()
    R = info.r.reshape(3, 3) if np.any(info.r) else np.eye(3)
    size = (info.width, info.height)
    if model == "equidistant":
        map_x, map_y = cv2.fisheye.initUndistortRectifyMap(K, info.d, R, target.K, size, cv2.CV_32FC1)
    else:
        map_x, map_y = cv2.initUndistortRectifyMap(K, info.d, R, target.K, size, cv2.CV_32FC1)
    return target, Rectifier(target, np.asarray(map_x, np.float32), np.asarray(map_y, np.float32))
