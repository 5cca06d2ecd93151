"""Figures of merit of a recorded servo run: images to convergence, camera pose error, latencies.

Conventions: the "image index" counts processed frames (one `Status` each) from the first SERVOING status, as the
paper counts "images to convergence" (Sec. 4: 417 for DVS and 309 for the decoupled DVS on the real planar scene).
Pose errors compare the ground-truth camera pose `T_world_cam` (OpenCV axes, metres) with the reference camera pose
`T_world_ref` stored as `reference_pose` (row-major 4×4) in the recording's meta: translation ‖t(T_ref_cam)‖ in
metres and rotation angle ‖θu(R_ref_cam)‖ in degrees, with `T_ref_cam = T_world_ref⁻¹ T_world_cam`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from clients.recording import Recording
from ddvs_service.lie import pose_inv, so3_log

F64 = NDArray[np.float64]
LATENCY_FIELDS = ("decode", "registration", "control", "publish", "total")


@dataclass
class StatusSeries:
    """Per processed frame from the first SERVOING status on: frame stamps (ns), states, error norms, twists (N×6,
    m/s and rad/s, camera frame) and latencies (N×5 ms in `LATENCY_FIELDS` order)."""

    stamp_ns: NDArray[np.int64]
    state: list[str]
    error_norm: F64
    twist: F64
    latency_ms: F64


def status_series(recording: Recording) -> StatusSeries:
    """The status stream from the first SERVOING status (everything when the servo never started)."""
    msgs = [r["msg"] for r in recording["status"]]
    first = next((i for i, m in enumerate(msgs) if m["state"] == "SERVOING"), 0)
    msgs = msgs[first:]
    return StatusSeries(
        stamp_ns=np.array([m["frame_stamp_ns"] for m in msgs], dtype=np.int64),
        state=[m["state"] for m in msgs],
        error_norm=np.array([m["error_norm"] for m in msgs], dtype=np.float64),
        twist=np.array([m["twist"] for m in msgs], dtype=np.float64).reshape(-1, 6),
        latency_ms=np.array([[m["latency_ms"][k] for k in LATENCY_FIELDS] for m in msgs],
                            dtype=np.float64).reshape(-1, len(LATENCY_FIELDS)),
    )


def images_to_convergence(states: list[str]) -> int | None:
    """Number of images processed while SERVOING before the first CONVERGED one (None: never converged)."""
    try:
        return states.index("CONVERGED")
    except ValueError:
        return None


@dataclass
class PoseSeries:
    """Ground-truth camera positions `p_ref_cam` (N×3, metres, reference camera frame) and pose errors."""

    stamp_ns: NDArray[np.int64]
    position: F64
    translation_error_m: F64
    rotation_error_deg: F64


def reference_pose(recording: Recording) -> F64 | None:
    """`T_world_ref` from the meta (`reference_pose`, 16 row-major numbers), or None when not recorded."""
    values = recording.meta.get("reference_pose")
    if values is None:
        return None
    T = np.asarray(values, dtype=np.float64)
    if T.size != 16:
        raise ValueError(f"meta reference_pose has {T.size} numbers; expected 16 (row-major 4×4)")
    return T.reshape(4, 4)


def pose_series(recording: Recording) -> PoseSeries | None:
    """Camera poses relative to the reference pose, from the ground-truth stream (None without both)."""
    T_world_ref = reference_pose(recording)
    truth = [r["msg"] for r in recording["ground_truth"]]
    if T_world_ref is None or not truth:
        return None
    T_ref_world = pose_inv(T_world_ref)
    rel = np.array([T_ref_world @ np.asarray(m["camera_pose"], dtype=np.float64).reshape(4, 4) for m in truth])
    return PoseSeries(
        stamp_ns=np.array([m["stamp_ns"] for m in truth], dtype=np.int64),
        position=rel[:, :3, 3],
        translation_error_m=np.linalg.norm(rel[:, :3, 3], axis=1),
        rotation_error_deg=np.rad2deg([np.linalg.norm(so3_log(T[:3, :3])) for T in rel]),
    )


@dataclass
class RunSummary:
    """What `summarize` reports (JSON-ready through `as_dict`). Latencies are the service's own per-frame times
    (median and 95th percentile, ms); `stamp_to_twist_ms` is the median delay from a frame's stamp to the arrival
    of the twist computed from it, only for a real-time clock (a lockstep plant's stamps are simulated time; meta
    `clock` "lockstep" leaves it None)."""

    frames: int
    images_to_convergence: int | None
    final_state: str | None
    final_error_norm: float | None
    final_translation_error_mm: float | None = None
    final_rotation_error_deg: float | None = None
    initial_translation_error_mm: float | None = None
    initial_rotation_error_deg: float | None = None
    latency_median_ms: dict[str, float] = field(default_factory=dict)
    latency_p95_ms: dict[str, float] = field(default_factory=dict)
    stamp_to_twist_ms: float | None = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def summarize(recording: Recording) -> RunSummary:
    series = status_series(recording)
    summary = RunSummary(
        frames=len(series.state),
        images_to_convergence=images_to_convergence(series.state),
        final_state=series.state[-1] if series.state else None,
        final_error_norm=float(series.error_norm[-1]) if series.state else None,
    )
    if series.state:
        summary.latency_median_ms = dict(zip(LATENCY_FIELDS, np.median(series.latency_ms, axis=0).round(3).tolist()))
        summary.latency_p95_ms = dict(zip(LATENCY_FIELDS,
                                          np.percentile(series.latency_ms, 95, axis=0).round(3).tolist()))
    poses = pose_series(recording)
    if poses is not None:
        summary.initial_translation_error_mm = float(poses.translation_error_m[0] * 1e3)
        summary.initial_rotation_error_deg = float(poses.rotation_error_deg[0])
        summary.final_translation_error_mm = float(poses.translation_error_m[-1] * 1e3)
        summary.final_rotation_error_deg = float(poses.rotation_error_deg[-1])
    twists = recording["twist"]
    if twists and recording.meta.get("clock") != "lockstep":
        summary.stamp_to_twist_ms = float(np.median([(t["recv_ns"] - t["stamp_ns"]) * 1e-6 for t in twists]))
    return summary
