"""The servo laws: DVS (12) on the full error (7), DVS on the reduced error (13) (the paper's DVS runs) and the
decoupled DVS (25) on `ε̄` (14)/(16), with per-axis gains, twist saturation and a stop criterion.

Output twist: `[v; ω]` of the current camera in its own frame (body twist, OpenCV axes), m/s and rad/s, to be
applied as `T ← T · exp(twist · dt)`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.control.errors import (
    check_inputs,
    decoupling_matrix,
    dvs_error_normalised,
    reduced_error_normalised,
)
from ddvs_service.control.stability import LAWS, check_configuration

F64 = NDArray[np.float64]


def _optional_vector(x: ArrayLike | None, size: int, name: str) -> tuple[float, ...] | None:
    if x is None:
        return None
    a = np.asarray(x, dtype=np.float64).reshape(-1)
    if a.size != size or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be {size} finite numbers, got {x!r}")
    return tuple(float(v) for v in a)


@dataclass(frozen=True)
class ControlConfig:
    """Configuration of a control law, validated at construction (law name, gains, limits) and again, with the
    intrinsics, when a `ControlLaw` is built (stability conditions, see `stability.check_configuration`).

    - `law`: "dvs" (full error (7) with `θμ`, `v = Λ ε`), "dvs_reduced" ((13), `v = Λ ε'`, the paper's DVS runs)
      or "ddvs" ((16), `v = Λ ε̄`).
    - `gains`: one gain or 6 per-axis gains `λ1..λ6` (1/s), applied as `diag(gains)`.
    - `p_star`: control pixel (u, v) in the reference image (default: principal point, `m*' = [0, 0, 1]`).
    - `c_star`: the normalised 3-vector `c*'` of (15) (default `m*'`); used by "ddvs" only.
    - `max_linear` (m/s), `max_angular` (rad/s): the whole twist is scaled down so that `‖v‖` and `‖ω‖` respect
      both limits (its direction is kept).
    - `stop_threshold`: the law reports `converged` and commands zero twist when the norm of its error is below it.
    - `q_star` (1/m) and `z_star` (m): optional metric knowledge (simulation only) enabling conditions (18), (34).
    """

    law: str = "ddvs"
    gains: float | tuple[float, ...] = 0.4
    p_star: tuple[float, float] | None = None
    c_star: tuple[float, float, float] | None = None
    max_linear: float = math.inf
    max_angular: float = math.inf
    stop_threshold: float = 1e-3
    q_star: tuple[float, float, float] | None = None
    z_star: float | None = None
    gain_vector: tuple[float, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.law not in LAWS:
            raise ValueError(f"unknown control law {self.law!r}; expected one of {LAWS}")
        g = np.asarray(self.gains, dtype=np.float64).reshape(-1)
        if g.size not in (1, 6) or not np.all(np.isfinite(g)):
            raise ValueError(f"gains must be one or 6 finite numbers (1/s), got {self.gains!r}")
        object.__setattr__(self, "gain_vector", tuple(float(v) for v in np.broadcast_to(g, (6,))))
        object.__setattr__(self, "p_star", _optional_vector(self.p_star, 2, "p_star"))
        object.__setattr__(self, "c_star", _optional_vector(self.c_star, 3, "c_star"))
        object.__setattr__(self, "q_star", _optional_vector(self.q_star, 3, "q_star"))
        if not (self.max_linear > 0.0 and self.max_angular > 0.0):
            raise ValueError(f"velocity limits must be positive, got {self.max_linear} m/s, {self.max_angular} rad/s")
        if not (math.isfinite(self.stop_threshold) and self.stop_threshold >= 0.0):
            raise ValueError(f"stop_threshold must be a finite non-negative error norm, got {self.stop_threshold}")
        if self.z_star is not None and not (math.isfinite(self.z_star) and self.z_star > 0.0):
            raise ValueError(f"z_star must be a positive depth in metres, got {self.z_star}")


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
