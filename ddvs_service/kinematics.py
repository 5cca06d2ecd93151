"""Pure arm kinematics with Pinocchio: URDF lookup, pose dictionaries, the camera frame and its Jacobian.

Frames and conventions (ARCHITECTURE.md): the camera frame has OpenCV axes (x right, y down, z forward), metres,
radians. A twist `xi = [v; ω]` is expressed in the *current camera frame* (body twist), so the camera pose in the
robot base frame advances as `T ← T · exp(xi dt)`. Poses `T_a_b` are 4×4 matrices mapping frame-b coordinates to
frame a. The robot base frame is the URDF root link.

`ArmKinematics` is the robot description: a Pinocchio model of any URDF reduced to the controlled joints, with an
`OP_FRAME` "camera" rigidly attached to a link at the configured mount pose `T_link_cam`.
`pin.computeFrameJacobian(..., pin.LOCAL)` of that frame is the matrix `J(q)` with `xi = J(q) q̇`.
Used by the arm plant (`sim/`) and the twist bridge (`clients/bridge.py`).
"""

from __future__ import annotations

import site
import sys
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
        start = np.asarray(q0, dtype=np.float64)
        q = np.clip(start, self.lower, self.upper)
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
            f" iterations from q0={np.round(start, 3).tolist()}): pose out of reach or joint limits in the way"
        )
