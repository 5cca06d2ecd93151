"""Camera twist → joint velocities for a camera-mounted arm, with singularity, velocity and position care.

Frames and conventions as in `ddvs_service/kinematics.py`: the twist `xi = [v; ω]` is in the current camera frame
(OpenCV axes, m/s and rad/s) and `J(q)` (`ArmKinematics.jacobian`) maps joint velocities to it.

`TwistBridge` inverts it: damped least squares `q̇ = Jᵀ (J Jᵀ + λ² I)⁻¹ xi` with λ = 0 away from singularities (exact
pseudo-inverse, so the twist is reproduced exactly) and λ growing as the smallest singular value of J falls below a
threshold; then one common factor s ∈ [0, 1] scales the whole vector so that every joint respects its velocity limit
and brakes before its position limit (the camera keeps the commanded direction, only slower); and a deadman returns
zero velocities when the last twist is older than a timeout.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.kinematics import ArmKinematics, pose_from_dict

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class BridgeLimits:
    """Tuning of `TwistBridge`.

    - `velocity_scale`: fraction of each URDF joint velocity limit that may be used (1 = the URDF limit).
    - `position_margin`: radians (metres for prismatic joints) kept clear of each URDF position limit.
    - `braking_time`: seconds; a joint moving towards a limit may go at most `distance_left / braking_time`.
    - `singular_threshold`: smallest singular value of J below which damping starts (m/rad or rad/rad per unit).
    - `max_damping`: λ reached at a singular value of 0 (λ² = (1 − (σ/threshold)²) max_damping²).
    - `deadman`: seconds after the last twist at which the bridge outputs zero velocities; also the oldest twist
      (by stamp, on the plant's clock) the bridge node acts on.
    - `max_linear` (m/s), `max_angular` (rad/s): a twist beyond these norms is rejected, not executed.
    """

    velocity_scale: float = 1.0
    position_margin: float = 0.05
    braking_time: float = 0.2
    singular_threshold: float = 0.02
    max_damping: float = 0.05
    deadman: float = 0.1
    max_linear: float = 1.0
    max_angular: float = 3.0

    def __post_init__(self) -> None:
        if not 0.0 < self.velocity_scale <= 1.0:
            raise ValueError(f"velocity_scale must be in (0, 1], got {self.velocity_scale}")
        for name in ("position_margin", "singular_threshold", "max_damping"):
            if getattr(self, name) < 0.0:
                raise ValueError(f"{name} must be ≥ 0, got {getattr(self, name)}")
        for name in ("braking_time", "deadman", "max_linear", "max_angular"):
            if getattr(self, name) <= 0.0:
                raise ValueError(f"{name} must be > 0 seconds, got {getattr(self, name)}")


class TwistBridge:
    """Camera twist (camera frame) + joint positions → joint velocities, for any URDF and camera mount.

    Stateless mapping: `joint_velocities(xi, q)`. Deadman use: `set_twist(xi, t)` when a twist arrives, then
    `command(q, t)` at the control rate (all times in seconds on one clock).
    """

    def __init__(self, kinematics: ArmKinematics, limits: BridgeLimits | None = None) -> None:
        self.kinematics = kinematics
        self.limits = limits or BridgeLimits()
        self.max_velocity: F64 = kinematics.velocity_limit * self.limits.velocity_scale
        self._twist = np.zeros(6)
        self._twist_time = -math.inf

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.kinematics.joint_names

    def damped_inverse(self, J: ArrayLike) -> F64:
        """`Jᵀ (J Jᵀ + λ² I)⁻¹` (dof×6) with the singular-value-dependent damping of `BridgeLimits`."""
        J = np.asarray(J, dtype=np.float64)
        U, sigma, Vt = np.linalg.svd(J, full_matrices=False)
        sigma_min = float(sigma[-1]) if sigma.size == 6 else 0.0  # fewer than 6 joints: always rank-deficient
        threshold = self.limits.singular_threshold
        lam2 = 0.0
        if sigma_min < threshold:
            lam2 = (1.0 - (sigma_min / threshold) ** 2) * self.limits.max_damping**2
        with np.errstate(divide="ignore"):
            inv = np.where(sigma > 1e-12, sigma / (sigma**2 + lam2), 0.0)
        return (Vt.T * inv) @ U.T

    def limit_scale(self, qd: ArrayLike, q: ArrayLike) -> float:
        """Largest s ∈ [0, 1] such that `s q̇` respects the velocity limits and the braking bounds of the positions.

        Per joint the admissible interval is `[max(−v̄, (q_lo + m − q)/τ), min(v̄, (q_hi − m − q)/τ)]` widened to
        contain 0 (a joint already inside the margin may always stop or move back).
        """
        qd = np.asarray(qd, dtype=np.float64)
        q = np.asarray(q, dtype=np.float64)
        lim, kin = self.limits, self.kinematics
        hi = np.maximum(np.minimum(self.max_velocity, (kin.upper - lim.position_margin - q) / lim.braking_time), 0.0)
        lo = np.minimum(np.maximum(-self.max_velocity, (kin.lower + lim.position_margin - q) / lim.braking_time), 0.0)
        scale = 1.0
        for v, a, b in zip(qd, lo, hi):
            if v > b:
                scale = min(scale, b / v)
            elif v < a:
                scale = min(scale, a / v)
        return max(scale, 0.0)

    def joint_velocities(self, twist: ArrayLike, q: ArrayLike) -> F64:
        """Joint velocities (rad/s or m/s, `joint_names` order) realising the camera twist `[v; ω]` (m/s, rad/s)."""
        twist = np.asarray(twist, dtype=np.float64).reshape(-1)
        if twist.shape != (6,) or not np.all(np.isfinite(twist)):
            raise ValueError(f"twist must be 6 finite numbers [vx, vy, vz, wx, wy, wz], got {twist}")
        qd = self.damped_inverse(self.kinematics.jacobian(q)) @ twist
        return qd * self.limit_scale(qd, q)

    def set_twist(self, twist: ArrayLike, t: float) -> None:
        """Record the latest commanded twist and its arrival time `t` (seconds)."""
        self._twist = np.asarray(twist, dtype=np.float64).reshape(6).copy()
        self._twist_time = float(t)

    def command(self, q: ArrayLike, t: float) -> F64:
        """Joint velocities for the latest twist at time `t`; zeros when it is older than `limits.deadman`."""
        if t - self._twist_time > self.limits.deadman:
            return np.zeros(self.kinematics.dof)
        return self.joint_velocities(self._twist, q)


def bridge_from_config(config: dict) -> TwistBridge:
    """Build a bridge from a configuration mapping (a `configs/arm/*bridge*.json` file):

    `{"urdf": str, "camera_link": str, "mount": pose dict (T_link_cam), "joints": [names] | null,
      "limits": {BridgeLimits fields}}`.
    """
    unknown = set(config) - {"urdf", "camera_link", "mount", "joints", "limits"}
    if unknown:
        raise ValueError(f"bridge configuration keys {sorted(unknown)} not understood")
    kinematics = ArmKinematics(
        config["urdf"], config["camera_link"], pose_from_dict(config.get("mount", {})), config.get("joints")
    )
    return TwistBridge(kinematics, BridgeLimits(**config.get("limits", {})))


def load_bridge(path: str | Path) -> TwistBridge:
    """Read a JSON bridge configuration file and build the bridge (`bridge_from_config`)."""
    with open(path, encoding="utf-8") as f:
        return bridge_from_config(json.load(f))
