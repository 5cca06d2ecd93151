"""The servo laws: DVS (12) on the full error (7), DVS on the reduced error (13) (the paper's DVS runs) and the
decoupled DVS (25) on `ε̄` (14)/(16), with per-axis gains, twist saturation and a stop criterion.

Output twist: `[v; ω]` of the current camera in its own frame (body twist, OpenCV axes), m/s and rad/s, to be
applied as `T ← T · exp(twist · dt)`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from ddvs_service.camera import Intrinsics
from ddvs_service.control.errors import (
    check_inputs,
    decoupling_matrix,
    dvs_error_normalised,
    reduced_error_normalised,
)
from ddvs_service.control.stability import check_configuration
from ddvs_service.settings import Settings

F64 = NDArray[np.float64]


MAX_GAIN = 10.0  # 1/s, largest |λ| accepted
MAX_LINEAR_SPEED = 10.0  # m/s, largest `max_linear` accepted
MAX_ANGULAR_SPEED = 10.0  # rad/s, largest `max_angular` accepted
MAX_PIXEL = 65536.0  # largest |coordinate| of a control pixel accepted

LawName = Literal["dvs", "dvs_reduced", "ddvs"]
Gain = Annotated[float, Field(ge=-MAX_GAIN, le=MAX_GAIN)]
Pixel = Annotated[float, Field(ge=-MAX_PIXEL, le=MAX_PIXEL)]
Direction = Annotated[float, Field(ge=-100.0, le=100.0)]


class LawSettings(Settings):
    """The settings of a servo law that a user chooses (the service's `control` settings extend them): law, gains,
    control point, saturation and stop threshold. Ranges and descriptions in each `Field`.

    - `law`: "dvs" (full error (7) with `θμ`, `v = Λ ε`), "dvs_reduced" ((13), `v = Λ ε'`, the paper's DVS runs)
      or "ddvs" ((16), `v = Λ ε̄`).
    - `max_linear` (m/s), `max_angular` (rad/s): the whole twist is scaled down so that `‖v‖` and `‖ω‖` respect
      both limits (its direction is kept).
    """

    law: LawName = Field(default="ddvs", description=(
        "dvs: the full error (7), v = Λ ε; dvs_reduced: the reduced error (13), v = Λ ε' (the paper's DVS runs); "
        "ddvs: the decoupled error (16), v = Λ ε̄ (25)."))
    gains: Gain | tuple[Gain, Gain, Gain, Gain, Gain, Gain] = Field(default=0.4, description=(
        f"One gain or 6 per-axis gains λ1..λ6 (1/s), each within ±{MAX_GAIN}, applied as diag(gains); their signs "
        "are checked against the stability conditions (26)-(28), (34)."))
    p_star: tuple[Pixel, Pixel] | None = Field(default=None, description=(
        "Control pixel (u, v) in the reference image; null: the principal point (m*' = [0, 0, 1])."))
    c_star: tuple[Direction, Direction, Direction] | None = Field(default=None, description=(
        "The normalised 3-vector c*' of (15), each entry within ±100; null: m*'. Used by ddvs only."))
    max_linear: float = Field(default=0.25, gt=0.0, le=MAX_LINEAR_SPEED, description=(
        "Saturation of the linear velocity ‖v‖, m/s (the twist is scaled, its direction kept)."))
    max_angular: float = Field(default=0.8, gt=0.0, le=MAX_ANGULAR_SPEED, description=(
        "Saturation of the angular velocity ‖ω‖, rad/s (the twist is scaled, its direction kept)."))
    stop_threshold: float = Field(default=1e-3, ge=0.0, le=1.0, description=(
        "Norm of the control error below which the servo stops (zero twist); 0: never."))

    @property
    def gain_vector(self) -> tuple[float, ...]:
        """The 6 gains λ1..λ6 (1/s)."""
        return (self.gains,) * 6 if isinstance(self.gains, float) else self.gains


class ControlConfig(LawSettings):
    """Configuration of a control law: `LawSettings`, checked again with the intrinsics when a `ControlLaw` is built
    (stability conditions, see `stability.check_configuration`), and optional metric knowledge (simulation and
    analysis only) enabling conditions (18), (34): `q_star` (1/m) and `z_star` (m)."""

    q_star: tuple[float, float, float] | None = Field(default=None, description="q*' = n*/d* of the plane, 1/m.")
    z_star: float | None = Field(default=None, gt=0.0, description="Depth of the control point, m.")


@dataclass(frozen=True)
class ControlOutput:
    """One control step: `twist` (6, `[v; ω]` body frame, m/s and rad/s), the law's `error` (6) and its norm,
    `converged` (norm below the stop threshold; the twist is then zero) and `saturated` (the twist was scaled)."""

    twist: F64
    error: F64
    error_norm: float
    converged: bool
    saturated: bool


class ControlLaw:
    """A configured servo law; `compute(G, e, rho)` turns one estimate of the projective parameters into a twist."""

    def __init__(self, config: ControlConfig, intrinsics: Intrinsics) -> None:
        self.config = config
        self.K = intrinsics.K
        p = config.p_star if config.p_star is not None else (intrinsics.cx, intrinsics.cy)
        self.m_star = intrinsics.normalize(p)
        self.c_star = np.asarray(config.c_star if config.c_star is not None else self.m_star, dtype=np.float64)
        self.gains = np.asarray(config.gain_vector, dtype=np.float64)
        check_configuration(config.law, self.gains, self.m_star, self.c_star, config.q_star, config.z_star)
        self._M = decoupling_matrix(self.m_star, self.c_star)  # (15), constant
        self._K_inv = np.asarray(np.linalg.inv(self.K), dtype=np.float64)  # (8), constant

    def error(self, G: ArrayLike, e: ArrayLike, rho: float) -> F64:
        """The configured law's error: (7), (13) or (16), 6-vector. Raises `ValueError` on non-finite inputs, naming
        them (the inputs are checked only when the error came out non-finite: this runs on every frame)."""
        H = self._K_inv @ np.asarray(G, dtype=np.float64) @ self.K  # (8)
        e_n = self._K_inv @ np.asarray(e, dtype=np.float64)
        if self.config.law == "dvs":
            err = dvs_error_normalised(H, e_n, rho, self.m_star)
        else:
            err = reduced_error_normalised(H, e_n, rho, self.m_star)
            if self.config.law == "ddvs":
                err = self._M @ err  # (14)/(16): decoupled_error, M kept
        if not np.isfinite(err).all():
            check_inputs(G, e, rho)
            raise ValueError(f"control error is not finite ({err}); check G={G!r}, e={e!r}")
        return err

    def compute(self, G: ArrayLike, e: ArrayLike, rho_at_control_point: float) -> ControlOutput:
        """Twist for the estimate `G` (SL(3), pixels), epipole `e` (pixels, homogeneous) and parallax `ρ*` of the
        control point. Raises `ValueError` on non-finite inputs; never returns a non-finite twist."""
        err = self.error(G, e, rho_at_control_point)
        norm = math.sqrt(err.dot(err))  # np.linalg.norm's arithmetic without its wrapper (every frame)
        if not math.isfinite(norm):  # finite entries whose squares overflow
            raise ValueError(f"control error is not finite ({err}); check G={G!r}, e={e!r}")
        if norm < self.config.stop_threshold:
            return ControlOutput(np.zeros(6), err, norm, True, False)
        twist = self.gains * err
        scale = min(
            1.0,
            self.config.max_linear / max(math.sqrt(twist[:3].dot(twist[:3])), 1e-300),
            self.config.max_angular / max(math.sqrt(twist[3:].dot(twist[3:])), 1e-300),
        )
        return ControlOutput(twist * scale, err, norm, False, scale < 1.0)
