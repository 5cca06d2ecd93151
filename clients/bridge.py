"""Camera twist → joint velocities for a camera-mounted arm (Pinocchio), with singularity, velocity and position care.

Frames and conventions (ARCHITECTURE.md): the camera frame has OpenCV axes (x right, y down, z forward), metres,
radians. A twist `xi = [v; ω]` is expressed in the *current camera frame* (body twist), so the camera pose in the
robot base frame advances as `T ← T · exp(xi dt)`. Poses `T_a_b` are 4×4 matrices mapping frame-b coordinates to
frame a. The robot base frame is the URDF root link.

`ArmKinematics` is the robot description: a Pinocchio model of any URDF reduced to the controlled joints, with an
`OP_FRAME` "camera" rigidly attached to a link at the configured mount pose `T_link_cam`.
`pin.computeFrameJacobian(..., pin.LOCAL)` of that frame is the matrix `J(q)` with `xi = J(q) q̇`.

`TwistBridge` inverts it: damped least squares `q̇ = Jᵀ (J Jᵀ + λ² I)⁻¹ xi` with λ = 0 away from singularities (exact
pseudo-inverse, so the twist is reproduced exactly) and λ growing as the smallest singular value of J falls below a
threshold; then one common factor s ∈ [0, 1] scales the whole vector so that every joint respects its velocity limit
and brakes before its position limit (the camera keeps the commanded direction, only slower); and a deadman returns
zero velocities when the last twist is older than a timeout.
"""

from __future__ import annotations

import json
import math
import site
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike, NDArray

from ddvs_service.lie import pose, so3_exp

F64 = NDArray[np.float64]

PACKAGE_SCHEME = "package://"
_CMEEL_SHARE = Path("cmeel.prefix") / "share"


def resolve_urdf(path: str) -> Path:
    """File path of a URDF given as a plain path or a ROS-style `package://NAME/rest` URL.

    `package://` URLs are looked up under `<site-packages>/cmeel.prefix/share/NAME` (where the `example-robot-data`
    wheel installs its robots), e.g. `package://example-robot-data/robots/ur_description/urdf/ur5_robot.urdf`.
    """
    if not path.startswith(PACKAGE_SCHEME):
        candidate = Path(path).expanduser()
        if not candidate.is_file():
            raise FileNotFoundError(f"URDF file {candidate} does not exist")
        return candidate
    relative = path[len(PACKAGE_SCHEME) :]
    roots = [*site.getsitepackages(), site.getusersitepackages(), *sys.path]
    for root in roots:
        candidate = Path(root) / _CMEEL_SHARE / relative
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(f"{path}: no {_CMEEL_SHARE / relative} under any site-packages folder of {sys.executable}")


def pose_from_dict(spec: dict) -> F64:
    """4×4 pose from `{"t": [x, y, z] metres, "r_deg": [rx, ry, rz] rotation vector θu in degrees}` (both optional)."""
    unknown = set(spec) - {"t", "r_deg"}
    if unknown:
        raise ValueError(f"pose keys {sorted(unknown)} not understood; expected 't' (metres) and 'r_deg' (θu, degrees)")
    t = np.asarray(spec.get("t", [0.0, 0.0, 0.0]), dtype=np.float64)
    r = np.deg2rad(np.asarray(spec.get("r_deg", [0.0, 0.0, 0.0]), dtype=np.float64))
    if t.shape != (3,) or r.shape != (3,):
        raise ValueError(f"pose 't' and 'r_deg' must have 3 numbers each, got {spec}")
    return pose(so3_exp(r), t)


class ArmKinematics:
    """Pinocchio model of an arm (URDF, reduced to `joints`) with an OP_FRAME "camera" at `T_link_cam` on `camera_link`.

    Joints not listed in `joints` are locked at their neutral position (e.g. a gripper's fingers). `joints=None`
    controls every joint of the URDF, in the model's order. Only 1-DoF joints (revolute, prismatic) are supported.
    """

    CAMERA_FRAME = "camera"

    def __init__(
        self, urdf: str, camera_link: str, T_link_cam: ArrayLike, joints: list[str] | tuple[str, ...] | None = None
    ) -> None:
        full = pin.buildModelFromUrdf(str(resolve_urdf(urdf)))
        names = list(full.names)[1:]
        wanted = names if joints is None else list(joints)
        missing = [j for j in wanted if j not in names]
        if missing:
            raise ValueError(f"joints {missing} are not in {urdf}; its joints are {names}")
        locked = [full.getJointId(n) for n in names if n not in wanted]
        model = pin.buildReducedModel(full, locked, pin.neutral(full)) if locked else full
        if model.nq != model.nv:
            raise ValueError(f"{urdf}: only 1-DoF joints are supported (nq={model.nq} ≠ nv={model.nv})")
        if not model.existFrame(camera_link):
            raise ValueError(f"camera link {camera_link!r} is not a frame of {urdf}")
        link = model.frames[model.getFrameId(camera_link)]
        T = np.asarray(T_link_cam, dtype=np.float64)
        mount = pin.SE3(T[:3, :3], T[:3, 3])
        frame = pin.Frame(
            self.CAMERA_FRAME, link.parentJoint, model.getFrameId(camera_link), link.placement * mount,
            pin.FrameType.OP_FRAME,
        )
        self.camera_frame = model.addFrame(frame)
        self.model = model
        self.data = model.createData()
        # Model joint order → the order callers use (`joints` as given).
        order = [model.getJointId(n) for n in wanted]
        self._index = np.array([model.idx_vs[j] for j in order], dtype=np.int64)
        self.joint_names: tuple[str, ...] = tuple(wanted)
        self.lower: F64 = model.lowerPositionLimit[self._index].copy()
        self.upper: F64 = model.upperPositionLimit[self._index].copy()
        self.velocity_limit: F64 = model.velocityLimit[self._index].copy()

    @property
    def dof(self) -> int:
        return len(self.joint_names)

    def _model_q(self, q: ArrayLike) -> F64:
        q = np.asarray(q, dtype=np.float64).reshape(-1)
        if q.shape != (self.dof,):
            raise ValueError(f"expected {self.dof} joint positions {self.joint_names}, got {q.shape[0]}")
        qm = np.zeros(self.model.nq)
        qm[self._index] = q
        return qm

    def camera_pose(self, q: ArrayLike) -> F64:
        """`T_base_cam(q)`: camera pose (OpenCV axes) in the robot base frame."""
        pin.framesForwardKinematics(self.model, self.data, self._model_q(q))
        return self.data.oMf[self.camera_frame].homogeneous.copy()

    def jacobian(self, q: ArrayLike) -> F64:
        """6×dof `J(q)` with `[v; ω]_cam = J(q) q̇` (camera frame, `pin.LOCAL`), columns in `joint_names` order."""
        J = pin.computeFrameJacobian(self.model, self.data, self._model_q(q), self.camera_frame, pin.LOCAL)
        return J[:, self._index]

    def inverse_kinematics(
        self, T_base_cam: ArrayLike, q0: ArrayLike, tol: float = 1e-10, max_iterations: int = 200
    ) -> F64:
        """Joint positions placing the camera at `T_base_cam`, by Gauss-Newton on SE(3) from `q0`, within limits.

        Each step solves `J Δq = log6(T(q)⁻¹ T_base_cam)` (local camera-frame error) in least squares, caps the step
        at 0.5 rad and clips to the position limits. Raises when the residual (metres + radians) stays above `tol`.
        """
        target = pin.SE3(np.asarray(T_base_cam, dtype=np.float64))
        q = np.clip(np.asarray(q0, dtype=np.float64).copy(), self.lower, self.upper)
        err = np.inf
        for _ in range(max_iterations):
            current = pin.SE3(self.camera_pose(q))
            residual = pin.log6(current.actInv(target)).vector
            err = float(np.linalg.norm(residual))
            if err < tol:
                return q
            step = np.linalg.lstsq(self.jacobian(q), residual, rcond=1e-8)[0]
            largest = float(np.max(np.abs(step)))
            if largest > 0.5:
                step *= 0.5 / largest
            q = np.clip(q + step, self.lower, self.upper)
        raise RuntimeError(
            f"inverse kinematics did not reach the camera pose (residual {err:.2e} > {tol:.0e} after {max_iterations}"
            f" iterations from q0={np.round(q0, 3).tolist()}): pose out of reach or joint limits in the way"
        )


@dataclass(frozen=True)
class BridgeLimits:
    """Tuning of `TwistBridge`.

    - `velocity_scale`: fraction of each URDF joint velocity limit that may be used (1 = the URDF limit).
    - `position_margin`: radians (metres for prismatic joints) kept clear of each URDF position limit.
    - `braking_time`: seconds; a joint moving towards a limit may go at most `distance_left / braking_time`.
    - `singular_threshold`: smallest singular value of J below which damping starts (m/rad or rad/rad per unit).
    - `max_damping`: λ reached at a singular value of 0 (λ² = (1 − (σ/threshold)²) max_damping²).
    - `deadman`: seconds after the last twist at which the bridge outputs zero velocities.
    """

    velocity_scale: float = 1.0
    position_margin: float = 0.05
    braking_time: float = 0.2
    singular_threshold: float = 0.02
    max_damping: float = 0.05
    deadman: float = 0.1

    def __post_init__(self) -> None:
        if not 0.0 < self.velocity_scale <= 1.0:
            raise ValueError(f"velocity_scale must be in (0, 1], got {self.velocity_scale}")
        for name in ("position_margin", "singular_threshold", "max_damping"):
            if getattr(self, name) < 0.0:
                raise ValueError(f"{name} must be ≥ 0, got {getattr(self, name)}")
        for name in ("braking_time", "deadman"):
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
