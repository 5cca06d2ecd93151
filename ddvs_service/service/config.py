"""Configuration of the servo service (`ddvs serve --config FILE`), validated as a whole.

A configuration is a JSON object (see `configs/serve/*.json`). Every field has a default; unknown fields are refused.
`ServiceConfig.merged(patch)` applies a partial update (run-time `set_config`) and validates the result, including
the control law's stability conditions (17), (26)–(28)/(34)/(35) for the configured intrinsics; a rejected update
raises `ValueError` and changes nothing.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ddvs_service.camera import Intrinsics
from ddvs_service.control.law import ControlConfig, ControlLaw
from ddvs_service.protocol.ros_settings import RosSettings
from ddvs_service.protocol.session import SessionConfig
from ddvs_service.registration.config import RegistrationConfig, RobustLoss
from ddvs_service.registration.general_config import GeneralConfig, Interpolation


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class IntrinsicsConfig(_Strict):
    """Pinhole intrinsics in pixels (0-based pixel-centre principal point); used instead of `camera/info`."""

    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    width: int = Field(gt=0)
    height: int = Field(gt=0)

    def to_intrinsics(self) -> Intrinsics:
        return Intrinsics(self.fx, self.fy, self.cx, self.cy, self.width, self.height)


_ENGINE = RegistrationConfig()  # the engine's defaults: the one definition of each engine setting
_GENERAL = GeneralConfig()


class RegistrationSettings(_Strict):
    """The registration: `model` planar (`ρ* ≡ 0`) or general (eq. (2): `G`, `e`, `ρ*`), the engine's settings,
    and the template: `roi = [x, y, w, h]` in reference pixels, or `template_size = [w, h]` centred on the control
    point when `roi` is null. Each engine setting (`levels` … `defocus_px`) is the `RegistrationConfig` field of that
    name, with its default and its checks (`engine_config`), except two defaults chosen from the robustness matrix
    (issue 20, README "Robustness"): `gain_grid` 3×3 (a single gain cannot represent a light ramp: CONVERGED 53 mm
    from the goal under a static 0.6→1.4 ramp, and it leaves 3.4 mm at the stop on clean anti-aliased frames
    against 1.1 mm with 3×3) and `robust` Tukey (its zero weight beyond 4.685 σ keeps a 30 % occluder out of the
    fit; Huber's bounded weight let it drag the fit until the service went LOST); `interpolation` (general model
    only) is `GeneralConfig.interpolation`. `global_init` and `feature_source`: the re-acquisition
    (`registration.reacquisition`; off, or the global initialiser with that hypothesis source)."""

    model: Literal["planar", "general"] = "planar"
    interpolation: Interpolation = _GENERAL.interpolation
    roi: tuple[int, int, int, int] | None = None
    template_size: tuple[int, int] = (200, 150)
    levels: int = _ENGINE.levels
    max_iterations: int = _ENGINE.max_iterations
    gain_grid: tuple[int, int] = (3, 3)
    robust: RobustLoss = "tukey"
    min_inlier_ratio: float = _ENGINE.min_inlier_ratio
    tracking_step_tolerance_px: float = Field(default=_ENGINE.tracking_step_tolerance_px, gt=0)
    gamma: float = _ENGINE.gamma
    defocus_px: float = _ENGINE.defocus_px
    global_init: bool = True
    feature_source: Literal["none", "orb", "sift"] = "none"

    def engine_config(self) -> RegistrationConfig:
        """The planar engine's settings (raises ValueError naming a bad value)."""
        return RegistrationConfig(**{name: getattr(self, name) for name in _ENGINE_FIELDS})

    def general_config(self) -> GeneralConfig:
        """The general engine's settings: `engine_config` as its base, and `interpolation`."""
        return GeneralConfig(base=self.engine_config(), interpolation=self.interpolation)


_ENGINE_FIELDS = tuple(f.name for f in dataclasses.fields(RegistrationConfig)
                       if f.name in RegistrationSettings.model_fields)


class ControlSettings(_Strict):
    """The servo law (`ControlConfig`): `law` dvs | dvs_reduced | ddvs, gains (1/s), control pixel, `c_star`,
    saturation (m/s, rad/s) and the stop threshold on the error norm, applied by the service's state machine: CONVERGED
    after `converge_frames` consecutive frames below it (the law itself keeps commanding `Λ ε̄` until then);
    `resume_factor` × stop threshold is the hysteresis threshold above which a CONVERGED servo resumes (the frame's
    own norm: a disturbance is answered at once). The stop compares the norm of the mean error ē over the last
    `settle_frames` tracked frames: near the goal a 70×70 template's error
    norm jitters at 1.5–2.3e-3 from frame to frame on clean frames (estimation noise; the camera is 0.5 mm away), so
    a single frame's norm stops the servo when the noise happens to dip, not when the pose is there. A mean can hide
    a scatter as well: the stop also needs the window full (`settle_frames` tracked frames) and the RMS deviation of
    its errors from their mean, s = √(mean_k ‖ε̄_k − ē‖²) (units of the error), below `scatter_factor` × the stop
    threshold — an estimate that moves by several thresholds from frame to frame (a biased, noisy fit: a plate over
    a third of a 70×70 template) is not declared converged wherever its mean happens to read zero. An unbiased but
    very noisy estimate stops on a longer window instead, the last `noise_frames` tracked frames: the norm of their
    mean and its standard error s/√N both below the threshold, and their scatter at most `noise_ratio` × the one
    the image noise predicts from the registration's covariance (`service.settling`; README, Robustness)."""

    law: Literal["dvs", "dvs_reduced", "ddvs"] = "ddvs"
    gains: float | tuple[float, float, float, float, float, float] = 0.4
    p_star: tuple[float, float] | None = None
    c_star: tuple[float, float, float] | None = None
    max_linear: float = Field(default=0.25, gt=0)
    max_angular: float = Field(default=0.8, gt=0)
    stop_threshold: float = Field(default=1e-3, gt=0)
    resume_factor: float = Field(default=5.0, gt=1)
    converge_frames: int = Field(default=3, ge=1)
    settle_frames: int = Field(default=10, ge=1)
    scatter_factor: float = Field(default=2.0, gt=0)
    noise_frames: int = Field(default=90, ge=2)
    noise_ratio: float = Field(default=3.0, gt=0)

    def law_config(self) -> ControlConfig:
        """The law's settings; its own stop threshold is 0 because the state machine decides when to stop."""
        return ControlConfig(
            law=self.law,
            gains=self.gains,
            p_star=self.p_star,
            c_star=self.c_star,
            max_linear=self.max_linear,
            max_angular=self.max_angular,
            stop_threshold=0.0,
        )


class ServiceConfig(_Strict):
    """Everything `ddvs serve` needs. Safety: `frame_timeout_s` without a frame → zero twist; LOST when the
    registration fails or its inlier ratio is below `registration.min_inlier_ratio` (a tracked frame: the tracker's
    lower floor while an occluder slides over the template, `registration.integrity.Integrity.inlier_floor`)."""

    prefix: str = "ddvs"
    robot: str = "robot0"
    zenoh: SessionConfig = Field(default_factory=SessionConfig)
    ros: RosSettings = Field(default_factory=RosSettings)  # ROS 2 mode over rmw_zenoh (docs/ros2.md); read at start
    state_dir: Path = Path("state")
    intrinsics: IntrinsicsConfig | None = None
    registration: RegistrationSettings = Field(default_factory=RegistrationSettings)
    control: ControlSettings = Field(default_factory=ControlSettings)
    frame_timeout_s: float = Field(default=0.2, gt=0)
    max_frame_bytes: int = Field(default=16 * 1024 * 1024, gt=0)
    status_every_frame: bool = True

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
        """Build the engine and law settings (raises `ValueError` naming what is wrong); with intrinsics, also the
        law itself, which checks the stability conditions."""
        self.registration.engine_config()
        law = self.control.law_config()
        intr = intrinsics or (self.intrinsics.to_intrinsics() if self.intrinsics else None)
        if intr is not None:
            ControlLaw(law, intr)


def deep_merge(base: dict[str, Any], patch: dict[str, Any]) -> dict[str, Any]:
    """`base` with `patch` applied: nested dicts merge key by key, any other value replaces."""
    out = dict(base)
    for key, value in patch.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = value
    return out
