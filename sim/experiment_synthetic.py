"""The paper's synthetic experiment (section IV-A): a camera servoed to its reference pose in front of the horse
saddle, by the DVS (reduced error (13), `v = λ ε'`) or the decoupled DVS ((16), `c*' = m*'`, `v = Λ ε̄`).

The loop: observe a frame (plant), get `(G, e, ρ*)` from a pluggable geometry source, compute the twist, apply it for
one sampling period. `GEOMETRY_SOURCES` maps a name to a source; "exact" feeds the ground truth (no images). A source
that estimates from images declares `needs_image = True` and receives rendered frames.

Measures (all from the plant's ground truth, never used by the control):
- `images`: number of images processed up to and including the first whose error norm is below the threshold.
- final translation / rotation errors: `‖t‖` (m) and the angle of `R` (deg) of the relative pose at that image.
- `retreat_m`: largest increase of the distance from the camera centre to the saddle centre over its initial value
  (0 when it never exceeds it).
- coupling: split each commanded linear velocity `v_k` into `v_rot,k`, what the same law commands for the
  rotation alone (same `R`, `t = 0`: `G = K R K⁻¹`, `e = 0`), and the rest `v_k − v_rot,k`;
  `coupling = Σ‖v_rot,k‖ / (Σ‖v_rot,k‖ + Σ‖v_k − v_rot,k‖)` ∈ [0, 1] is the share of the translational command
  driven by the rotational error (0 for a perfectly decoupled law). `coupling_near_equilibrium` is the same over
  the images where the remaining rotation is below 5°.
- `path_excess`: length of the camera centre's path over the straight-line distance to the goal, minus 1 (0 for
  a straight path, which a purely translation-driven `v ∝ t` produces).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.control.law import ControlConfig, ControlLaw
from ddvs_service.lie import pose, pose_inv, so3_exp, so3_log
from sim.freeflyer import Frame, FreeFlyer
from sim.surfaces import paper_saddle

F64 = NDArray[np.float64]

PAPER_T = (0.17, -0.11, 0.01)
PAPER_R = (-0.1, -0.31, 1.04)
PAPER_IMAGES = {"dvs": 905, "ddvs": 762}
LAW_NAMES = {"dvs": "dvs_reduced", "ddvs": "ddvs"}


class GeometrySource(Protocol):
    """Turns a frame into the projective parameters `(G, e, ρ*)` of the control point."""

    needs_image: bool

    def __call__(self, frame: Frame) -> tuple[F64, F64, float]: ...


class ExactGeometry:
    """The ground truth `G`, `e`, `ρ*` of the frame (no image needed)."""

    needs_image = False

    def __call__(self, frame: Frame) -> tuple[F64, F64, float]:
        return frame.truth.G, frame.truth.e, frame.truth.rho


GEOMETRY_SOURCES: dict[str, Callable[[], GeometrySource]] = {"exact": ExactGeometry}


@dataclass(frozen=True)
class SyntheticSetup:
    """The experiment's parameters (paper values by default): initial pose of the camera in the reference frame
    (`t` metres, rotation vector `r` radians), focal length `f` (px), image size, saddle centre depth and
    parameter `a` (m), sampling period `dt` (s), gain, stop threshold on the error norm, an image budget, and the
    scale gauge of `G` ("sl3": det G = 1 like an estimator; "euclidean")."""

    t: tuple[float, float, float] = PAPER_T
    r: tuple[float, float, float] = PAPER_R
    f: float = 500.0
    width: int = 550
    height: int = 418
    depth: float = 1.0
    a: float = 1.0
    dt: float = 0.03
    gain: float = 0.4
    threshold: float = 1e-3
    max_images: int = 20000
    scaling: str = "sl3"


@dataclass
class ExperimentResult:
    """Outcome and traces of one run (traces have one row per processed image)."""

    law: str
    converged: bool
    images: int
    paper_images: int
    translation_error_m: float
    rotation_error_deg: float
    retreat_m: float
    coupling: float
    coupling_near_equilibrium: float
    path_excess: float
    time: F64 = field(repr=False)
    twists: F64 = field(repr=False)
    error_norms: F64 = field(repr=False)
    positions: F64 = field(repr=False)
    rotations: F64 = field(repr=False)

    def summary(self) -> dict[str, float | int | bool | str]:
        """The scalar results (JSON-ready)."""
        return {k: v for k, v in asdict(self).items() if not isinstance(v, np.ndarray)}


def run_synthetic(
    law: str, setup: SyntheticSetup = SyntheticSetup(), source: GeometrySource | None = None
) -> ExperimentResult:
    """Run the closed loop for `law` ("dvs" or "ddvs") until the error norm is below `setup.threshold` or
    `setup.max_images` images were processed."""
    if law not in LAW_NAMES:
        raise ValueError(f"unknown law {law!r}; expected one of {sorted(LAW_NAMES)}")
    source = source or ExactGeometry()
    intr = Intrinsics.centred(setup.f, setup.width, setup.height)
    saddle = paper_saddle(setup.depth, setup.a)
    control = ControlLaw(ControlConfig(LAW_NAMES[law], gains=setup.gain, stop_threshold=setup.threshold), intr)
    plant = FreeFlyer(saddle, intr, np.eye(4), pose(so3_exp(setup.r), setup.t), setup.dt, scaling=setup.scaling)
    target = saddle.T_world_surface[:3, 3]
    twists, norms, positions, rotations, rot_driven, angles = [], [], [], [], [], []
    out = None
    for _ in range(setup.max_images):
        frame = plant.observe(render=source.needs_image)
        G, e, rho = source(frame)
        out = control.compute(G, e, rho)
        R_cur_ref = frame.truth.T_cur_ref[:3, :3]
        G_rot = intr.K @ R_cur_ref @ intr.K_inv
        rot_driven.append(control.gains[:3] * control.error(G_rot, np.zeros(3), rho)[:3])
        angles.append(np.degrees(np.linalg.norm(so3_log(R_cur_ref))))
        twists.append(out.twist if not out.converged else control.gains * out.error)
        norms.append(out.error_norm)
        positions.append(frame.T_world_cam[:3, 3])
        rotations.append(frame.T_world_cam[:3, :3])
        if out.converged:
            break
        plant.move(out.twist)
    assert out is not None
    T_cur_ref = pose_inv(plant.T_world_cam)
    pos = np.array(positions)
    tw = np.array(twists)
    dist = np.linalg.norm(pos - target, axis=1)
    path = float(np.sum(np.linalg.norm(np.diff(pos, axis=0), axis=1)))
    return ExperimentResult(
        law=law,
        converged=bool(out.converged),
        images=len(norms),
        paper_images=PAPER_IMAGES[law],
        translation_error_m=float(np.linalg.norm(T_cur_ref[:3, 3])),
        rotation_error_deg=float(np.degrees(np.linalg.norm(so3_log(T_cur_ref[:3, :3])))),
        retreat_m=float(max(0.0, dist.max() - dist[0])),
        coupling=_coupling(tw[:, :3], np.array(rot_driven), np.ones(len(tw), dtype=bool)),
        coupling_near_equilibrium=_coupling(tw[:, :3], np.array(rot_driven), np.array(angles) < 5.0),
        path_excess=path / float(np.linalg.norm(pos[0])) - 1.0,
        time=np.arange(len(norms)) * setup.dt,
        twists=tw,
        error_norms=np.array(norms),
        positions=pos,
        rotations=np.array(rotations),
    )


def _coupling(v: F64, v_rot: F64, mask: NDArray[np.bool_]) -> float:
    """`Σ‖v_rot‖ / (Σ‖v_rot‖ + Σ‖v − v_rot‖)` over the rows selected by `mask` (nan when none)."""
    rot = float(np.sum(np.linalg.norm(v_rot[mask], axis=1)))
    rest = float(np.sum(np.linalg.norm(v[mask] - v_rot[mask], axis=1)))
    return rot / (rot + rest) if rot + rest > 0.0 else float("nan")


def save_plots(result: ExperimentResult, out_dir: Path, setup: SyntheticSetup = SyntheticSetup()) -> list[Path]:
    """Save the velocities v(t), ω(t) and the 3-D camera trajectory (like the paper's Fig. 3/4) as PNG files."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / f"{result.law}_velocities.png", out_dir / f"{result.law}_trajectory.png"]

    fig, (ax_v, ax_w) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    for i, name in enumerate(("x", "y", "z")):
        ax_v.plot(result.time, result.twists[:, i], label=f"v_{name}")
        ax_w.plot(result.time, result.twists[:, 3 + i], label=f"ω_{name}")
    ax_v.set_ylabel("m/s")
    ax_w.set_ylabel("rad/s")
    ax_w.set_xlabel("time (s)")
    ax_v.legend(loc="upper right")
    ax_w.legend(loc="upper right")
    ax_v.set_title(f"{result.law}: camera velocities, converged after {result.images} images")
    fig.tight_layout()
    fig.savefig(paths[0], dpi=120)
    plt.close(fig)

    fig = plt.figure(figsize=(6, 6))
    ax = fig.add_subplot(projection="3d")
    X, Y = np.meshgrid(np.linspace(-0.2, 0.2, 9), np.linspace(-0.15, 0.15, 7))
    ax.plot_wireframe(X, Y, setup.depth + (X**2 - Y**2) / setup.a, color="0.6", linewidth=0.6)
    p = result.positions
    ax.plot(p[:, 0], p[:, 1], p[:, 2], color="tab:blue", label="camera centre")
    step = max(1, len(p) // 8)
    for k in [*range(0, len(p), step), len(p) - 1]:
        for axis, color in zip(range(3), ("r", "g", "b")):
            d = 0.05 * result.rotations[k][:, axis]
            ax.plot(*zip(p[k], p[k] + d), color=color, linewidth=0.8)
    ax.set_xlabel("X (m)")
    ax.set_ylabel("Y (m)")
    ax.set_zlabel("Z (m)")
    ax.set_title(f"{result.law}: camera motion (reference frame)")
    ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(paths[1], dpi=120)
    plt.close(fig)
    return paths
