"""Configuration of the servo service (`ddvs serve --config FILE`), validated as a whole: the top of the one
configuration schema (`ddvs_service.settings`).

A configuration is a JSON object (see `configs/serve/*.json`). Every field has a default, a range and a description
(its `Field`); unknown fields are refused. The `registration` settings extend the engine's `RegistrationConfig`, the
`control` settings the law's `LawSettings`: each engine and law setting is defined once, there. The same checks run
at start (`from_file`) and at run time: `ServiceConfig.merged(patch)` applies a partial update (`set_config`) and
validates the result, including the control law's stability conditions (17), (26)–(28)/(34)/(35) for the configured
intrinsics; a rejected update raises `ValueError` and changes nothing. The settings marked `START_ONLY` are read
when the robot starts; `set_config` refuses to change them (`start_only_changes`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, ValidationError
from pydantic.json_schema import JsonDict

from ddvs_service.camera import Intrinsics
from ddvs_service.control.law import ControlConfig, ControlLaw, LawSettings
from ddvs_service.protocol.ros_settings import RosSettings
from ddvs_service.protocol.session import SessionConfig
from ddvs_service.registration.config import RegistrationConfig
from ddvs_service.registration.general_config import (
    DEFAULT_INTERPOLATION,
    GeneralConfig,
    HoldEpipoleSetting,
    InterpolationSetting,
)
from ddvs_service.settings import Settings, narrowed

MAX_IMAGE_SIDE = 16384  # pixels, the widest or tallest camera image accepted
MAX_FRAME_TIMEOUT_S = 10.0  # the longest no-frame watchdog accepted
MAX_FRAME_BYTES = 256 << 20  # the largest camera frame or reference accepted, bytes
# `json_schema_extra` of a setting read when the robot starts, never changed by `set_config` (the robot's keys, its
# network session, its state folder, its camera)
START_ONLY: JsonDict = {"start_only": True}

Side = Annotated[int, Field(ge=1, le=MAX_IMAGE_SIDE)]
Corner = Annotated[int, Field(ge=0, le=MAX_IMAGE_SIDE)]


class IntrinsicsConfig(Settings):
    """Pinhole intrinsics in pixels (0-based pixel-centre principal point); used instead of `camera/info`."""

    fx: float = Field(gt=0, le=1e6, description="Focal length along u, pixels.")
    fy: float = Field(gt=0, le=1e6, description="Focal length along v, pixels.")
    cx: float = Field(ge=-MAX_IMAGE_SIDE, le=2 * MAX_IMAGE_SIDE, description="Principal point column, pixels.")
    cy: float = Field(ge=-MAX_IMAGE_SIDE, le=2 * MAX_IMAGE_SIDE, description="Principal point row, pixels.")
    width: Side = Field(description="Image width, pixels.")
    height: Side = Field(description="Image height, pixels.")

    def to_intrinsics(self) -> Intrinsics:
        return Intrinsics(self.fx, self.fy, self.cx, self.cy, self.width, self.height)


class CameraSettings(Settings):
    """Which of the camera's image topics the service reads (docs/cameras.md). `images`: `raw` (`camera/image`,
    ROS `image_raw`: frames as the sensor took them, rectified by the service with the camera info's distortion,
    `ddvs_service.rectification`) or `rect` (`camera/image_rect`, ROS `image_rect`: frames rectified upstream, e.g.
    by image_proc; intrinsics from the camera info's P). `transport`: `raw` (`sensor_msgs/Image`) or `compressed`
    (`sensor_msgs/CompressedImage`, JPEG or PNG, on `<image topic>/compressed` as image_transport names it)."""

    images: Literal["raw", "rect"] = Field(default="raw", description=(
        "raw: camera/image (ROS image_raw), rectified by the service when the camera info has distortion; rect: "
        "camera/image_rect (ROS image_rect), already rectified, intrinsics from the camera info's P."))
    transport: Literal["raw", "compressed"] = Field(default="raw", description=(
        "raw: sensor_msgs/Image; compressed: sensor_msgs/CompressedImage (JPEG or PNG) on the image topic's "
        "/compressed."))

    @property
    def topic(self) -> str:
        """The row of `protocol.keys.TOPICS` these frames arrive on."""
        row = "camera_image" if self.images == "raw" else "camera_image_rect"
        return row if self.transport == "raw" else f"{row}_compressed"


class RegistrationSettings(RegistrationConfig):
    """The registration: every engine setting of `RegistrationConfig` (`levels` … `defocus_px`, the same
    definitions and defaults), the model (planar, `ρ* ≡ 0`, or general, eq. (2): `G`, `e`, `ρ*`, sampled as
    `GeneralConfig.interpolation`, `e` held near the goal as `GeneralConfig.hold_epipole_px`), the template, and the
    re-acquisition (`registration.reacquisition`: off, or the global initialiser with that hypothesis source)."""

    model: Literal["planar", "general"] = Field(default="planar", description=(
        "planar: the planar model (ρ* ≡ 0); general: the general model of eq. (2) (G, e, ρ*)."))
    interpolation: InterpolationSetting = DEFAULT_INTERPOLATION
    hold_epipole_px: HoldEpipoleSetting = 0.05
    roi: tuple[Corner, Corner, Side, Side] | None = Field(default=None, description=(
        "Template [x, y, w, h] in reference pixels; null: `template_size` centred on the control point."))
    template_size: tuple[Side, Side] = Field(default=(200, 150), description=(
        "Template [w, h] in pixels, centred on the control point, when `roi` is null."))
    global_init: bool = Field(default=True, description=(
        "Re-acquire with the global initialiser (Fourier-Mellin hypotheses) when the tracker loses the target."))
    feature_source: Literal["none", "orb", "sift"] = Field(default="none", description=(
        "Feature hypotheses added to the global initialiser's: none, orb or sift."))

    def engine_config(self) -> RegistrationConfig:
        """The planar engine's settings."""
        return narrowed(self, RegistrationConfig)

    def general_config(self) -> GeneralConfig:
        """The general engine's settings: `engine_config` as its base, `interpolation` and `hold_epipole_px`."""
        return GeneralConfig(base=self.engine_config(), interpolation=self.interpolation,
                             hold_epipole_px=self.hold_epipole_px)


class ControlSettings(LawSettings):
    """The servo law (`LawSettings`: `law` dvs | dvs_reduced | ddvs, gains (1/s), control pixel, `c_star`,
    saturation (m/s, rad/s), stop threshold) and the stop decided by the service's state machine: CONVERGED after
    `converge_frames` consecutive frames below the stop threshold (the law itself keeps commanding `Λ ε̄` until
    then); `resume_factor` × stop threshold is the hysteresis threshold above which a CONVERGED servo resumes (the
    frame's own norm: a disturbance is answered at once). The stop compares the norm of the mean error ē over the
    last `settle_frames` tracked frames: near the goal a small template's error norm jitters from frame to frame on
    clean frames (estimation noise), so a single frame's norm stops the servo when the noise happens to dip, not
    when the pose is there. A mean can hide a scatter as well: the stop also needs the window full
    (`settle_frames` tracked frames) and the RMS deviation of its errors from their mean,
    s = √(mean_k ‖ε̄_k − ē‖²) (units of the error), below `scatter_factor` × the stop threshold — an estimate that
    moves by several thresholds from frame to frame (a biased, noisy fit) is not declared converged wherever its
    mean happens to read zero. An unbiased but very noisy estimate stops on a longer window instead, the last
    `noise_frames` tracked frames: the norm of their mean and its standard error s/√N both below the threshold, and
    their scatter at most `noise_ratio` × the one the image noise predicts from the registration's covariance
    (`service.settling`; README, Robustness)."""

    resume_factor: float = Field(default=5.0, gt=1, le=100, description=(
        "A CONVERGED servo resumes when a frame's error norm exceeds resume_factor × stop_threshold."))
    converge_frames: int = Field(default=3, ge=1, le=1000, description=(
        "Consecutive frames below the stop threshold before CONVERGED."))
    settle_frames: int = Field(default=10, ge=1, le=1000, description=(
        "Tracked frames whose mean error is compared with the stop threshold."))
    scatter_factor: float = Field(default=2.0, gt=0, le=1000, description=(
        "The RMS scatter of those frames' errors must be below scatter_factor × stop_threshold."))
    noise_frames: int = Field(default=90, ge=2, le=10000, description=(
        "Tracked frames of the longer window on which a noisy, unbiased estimate stops."))
    noise_ratio: float = Field(default=3.0, gt=0, le=1000, description=(
        "Largest ratio of that window's scatter to the scatter the registration's covariance predicts."))

    def law_config(self) -> ControlConfig:
        """The law's settings; its own stop threshold is 0 because the state machine decides when to stop."""
        return narrowed(self, ControlConfig, stop_threshold=0.0)


class ServiceConfig(Settings):
    """Everything `ddvs serve` needs. Safety: `frame_timeout_s` without a frame → zero twist; LOST when the
    registration fails or its inlier ratio is below `registration.min_inlier_ratio` (a tracked frame: the tracker's
    lower floor while an occluder slides over the template, `registration.integrity.Integrity.inlier_floor`)."""

    prefix: str = Field(default="ddvs", min_length=1, max_length=100, json_schema_extra=START_ONLY,
                        description="First segment of every key of the robot.")
    robot: str = Field(default="robot0", min_length=1, max_length=100, json_schema_extra=START_ONLY,
                       description="The robot's name, the second segment of its keys.")
    zenoh: SessionConfig = Field(default_factory=SessionConfig, json_schema_extra=START_ONLY,
                                 description="How the service joins the Zenoh network.")
    ros: RosSettings = Field(default_factory=RosSettings, json_schema_extra=START_ONLY,
                             description="ROS 2 mode over rmw_zenoh (docs/ros2.md).")
    state_dir: Path = Field(default=Path("state"), json_schema_extra=START_ONLY,
                            description="Folder of the robot's persisted state (reference, estimate, changes).")
    camera: CameraSettings = Field(default_factory=CameraSettings, json_schema_extra=START_ONLY,
                                   description="The camera topic read: raw or rectified, compressed or not.")
    intrinsics: IntrinsicsConfig | None = Field(default=None, json_schema_extra=START_ONLY, description=(
        "The camera's intrinsics; null: those of the camera's camera/info."))
    registration: RegistrationSettings = Field(default_factory=RegistrationSettings,
                                               description="The registration (engine, model, template).")
    control: ControlSettings = Field(default_factory=ControlSettings, description="The servo law and its stop.")
    frame_timeout_s: float = Field(default=0.2, gt=0, le=MAX_FRAME_TIMEOUT_S, description=(
        "Seconds without a camera frame after which the servo commands a zero twist (the watchdog)."))
    max_frame_bytes: int = Field(default=16 * 1024 * 1024, ge=1024, le=MAX_FRAME_BYTES, description=(
        "Largest camera frame accepted, bytes, and largest decoded reference upload."))
    status_every_frame: bool = Field(default=True, description=(
        "Publish a status for every frame; false: only when the state changes or the last one is stale."))

    @classmethod
    def from_file(cls, path: str | Path) -> ServiceConfig:
        try:
            return cls.model_validate(json.loads(Path(path).read_text(encoding="utf-8")))
        except (OSError, json.JSONDecodeError, ValidationError) as exc:
            raise ValueError(f"service configuration {path}: {exc}") from exc

    def merged(self, patch: dict[str, Any], intrinsics: Intrinsics | None = None) -> ServiceConfig:
        """A new configuration with `patch` (nested dicts merge) applied and fully checked (see `check`)."""
        data = deep_merge(self.model_dump(mode="json"), patch)
        try:
            new = type(self).model_validate(data)
        except ValidationError as exc:
            raise ValueError(f"invalid configuration: {exc}") from exc
        new.check(intrinsics)
        return new

    def check(self, intrinsics: Intrinsics | None = None) -> None:
        """With intrinsics (given or configured), build the law, which checks the stability conditions (raises
        `ValueError` naming what is wrong); every other setting was checked on construction."""
        intr = intrinsics or (self.intrinsics.to_intrinsics() if self.intrinsics else None)
        if intr is not None:
            ControlLaw(self.control.law_config(), intr)

    def start_only_changes(self, new: ServiceConfig) -> list[str]:
        """The settings marked `START_ONLY` whose value differs in `new`."""
        return [name for name, info in type(self).model_fields.items()
                if info.json_schema_extra == START_ONLY and getattr(new, name) != getattr(self, name)]


def deep_merge(base: dict[str, Any], patch: dict[str, Any]) -> dict[str, Any]:
    """`base` with `patch` applied: nested dicts merge key by key, any other value replaces."""
    out = dict(base)
    for key, value in patch.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = value
    return out
