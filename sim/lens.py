"""A lens with distortion in front of a simulated pinhole camera: the raw image a calibrated real camera delivers.

`DistortedLens(intrinsics, model, d)` is the camera a `sensor_msgs/CameraInfo` with `k` = `intrinsics.K`,
`distortion_model` = `model` and `d` describes ("plumb_bob", "rational_polynomial" or "equidistant", OpenCV's
models, as `ddvs_service.rectification` undoes them). `raw(render)` forms the raw image: each raw pixel looks along
the ray of its undistorted normalised point (`cv2.undistortPoints`, `cv2.fisheye.undistortPoints`), read by
bilinear interpolation from a pinhole image of the same focal length rendered over a canvas wide enough to hold
every such point (`render(canvas_intrinsics)` supplies it, e.g. `sim.freeflyer.render_view`). Pixel centres at
integer coordinates. `camera_info` is the matching calibration (P = [K | 0]: rectified to the same pinhole camera).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.protocol.ros import CameraInfo, Header

F32 = NDArray[np.float32]


@dataclass(frozen=True, eq=False)
class DistortedLens:
    """The raw images of the pinhole camera `intrinsics` seen through distortion `model` with coefficients `d`."""

    intrinsics: Intrinsics
    model: str
    d: tuple[float, ...]
    canvas: Intrinsics = field(init=False)
    _map_x: F32 = field(init=False, repr=False)
    _map_y: F32 = field(init=False, repr=False)

    def __post_init__(self) -> None:
        import cv2

        K, D = self.intrinsics.K, np.asarray(self.d, dtype=np.float64)
        u, v = np.meshgrid(np.arange(self.intrinsics.width, dtype=np.float64),
                           np.arange(self.intrinsics.height, dtype=np.float64))
        raw = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
        if self.model == "equidistant":
            ideal = cv2.fisheye.undistortPoints(raw, K, D, P=K)
        elif self.model in ("plumb_bob", "rational_polynomial"):
            ideal = cv2.undistortPoints(raw, K, D, P=K)
        else:
            raise ValueError(f"distortion model {self.model!r}: expected plumb_bob, rational_polynomial or equidistant")
        ideal = ideal.reshape(self.intrinsics.height, self.intrinsics.width, 2)
        left, top = np.floor(ideal.min(axis=(0, 1))) - 2.0
        right, bottom = np.ceil(ideal.max(axis=(0, 1))) + 2.0
        i = self.intrinsics
        canvas = Intrinsics(i.fx, i.fy, i.cx - left, i.cy - top, int(right - left) + 1, int(bottom - top) + 1, i.skew)
        object.__setattr__(self, "canvas", canvas)
        object.__setattr__(self, "_map_x", (ideal[..., 0] - left).astype(np.float32))
        object.__setattr__(self, "_map_y", (ideal[..., 1] - top).astype(np.float32))

    def raw(self, render: Callable[[Intrinsics], NDArray]) -> F32:
        """The raw (distorted) float32 image of what `render(intrinsics)` shows a pinhole camera."""
        import cv2

        image = np.ascontiguousarray(render(self.canvas), dtype=np.float32)
        return np.asarray(cv2.remap(image, self._map_x, self._map_y, cv2.INTER_LINEAR), np.float32)

    def camera_info(self, header: Header) -> CameraInfo:
        """The calibration of this camera as a driver publishes it: K, D, R = I, P = [K | 0]."""
        K = self.intrinsics.K
        return CameraInfo(header=header, height=self.intrinsics.height, width=self.intrinsics.width,
                          distortion_model=self.model, d=np.asarray(self.d, dtype=np.float64), k=K.reshape(-1),
                          p=np.hstack([K, np.zeros((3, 1))]).reshape(-1))
