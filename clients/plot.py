"""`ddvs plot`: the paper's figure types from a recording — a bag of `ddvs record` or an older JSON Lines
directory (`clients.recording.load_recording`) — with matplotlib (Agg backend, PNG files).

- `velocities.png`: camera velocities v (m/s) and ω (deg/s) in the camera frame against the image index (the top
  halves of the paper's Figs. 3, 4, 6, 7).
- `error_norm.png`: ‖ε̄‖ of the control error (16) (or (13) for DVS) against the image index, log scale, with the
  stop threshold 1e-3 when known.
- `trajectory.png`: 3-D camera positions towards convergence (bottom halves of Figs. 3, 4, 6, 7), in the reference
  camera frame (OpenCV axes, metres) when the recording has a reference pose, else in the world frame.
- `pose_error.png`: translation (mm) and rotation (deg) error to the reference pose, log scale (with ground truth).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from clients.recording import Recording


def plot_recording(recording: Recording, out_dir: str | Path, title: str = "") -> list[Path]:
    """Write the figures of `recording` into `out_dir`; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from clients.analysis import pose_series, status_series

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    series = status_series(recording)
    index = np.arange(len(series.state))
    written: list[Path] = []

    def save(fig, name: str) -> None:
        if title:
            fig.suptitle(title)
        fig.tight_layout()
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        written.append(out / name)

    fig, (ax_v, ax_w) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    for i, name in enumerate(("v_x", "v_y", "v_z")):
        ax_v.plot(index, series.twist[:, i], label=f"${name}$")
        ax_w.plot(index, np.rad2deg(series.twist[:, 3 + i]), label=f"$\\omega_{name[-1]}$")
    ax_v.set_ylabel("linear velocity (m/s)")
    ax_w.set_ylabel("angular velocity (deg/s)")
    ax_w.set_xlabel("image")
    for ax in (ax_v, ax_w):
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper right")
    save(fig, "velocities.png")

    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.semilogy(index, np.maximum(series.error_norm, 1e-12))
    threshold = recording.meta.get("stop_threshold")
    if threshold is not None:
        ax.axhline(threshold, color="k", ls="--", lw=0.8, label=f"stop threshold {threshold:g}")
        ax.legend()
    ax.set_xlabel("image")
    ax.set_ylabel("control error norm")
    ax.grid(True, which="both", alpha=0.3)
    save(fig, "error_norm.png")

    poses = pose_series(recording)
    if poses is not None:
        p = poses.position
        frame = "reference camera frame"
    else:
        truth = [r["msg"] for r in recording["ground_truth"]]
        p = np.array([np.asarray(m["camera_pose"]).reshape(4, 4)[:3, 3] for m in truth]).reshape(-1, 3)
        frame = "world frame"
    if len(p):
        fig = plt.figure(figsize=(6, 5.5))
        ax = fig.add_subplot(projection="3d")
        ax.plot(p[:, 0], p[:, 1], p[:, 2], lw=1.5)
        ax.scatter(*p[0], color="tab:red", label="start")
        ax.scatter(*p[-1], color="tab:green", label="end")
        if poses is not None:
            ax.scatter(0, 0, 0, color="k", marker="x", s=60, label="reference")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_zlabel("z (m)")
        ax.set_title(f"camera trajectory ({frame})")
        ax.legend()
        save(fig, "trajectory.png")

    if poses is not None:
        fig, (ax_t, ax_r) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
        images = np.arange(len(poses.stamp_ns))
        ax_t.semilogy(images, np.maximum(poses.translation_error_m * 1e3, 1e-6))
        ax_r.semilogy(images, np.maximum(poses.rotation_error_deg, 1e-6))
        ax_t.set_ylabel("translation error (mm)")
        ax_r.set_ylabel("rotation error (deg)")
        ax_r.set_xlabel("frame")
        for ax in (ax_t, ax_r):
            ax.grid(True, which="both", alpha=0.3)
        save(fig, "pose_error.png")
    return written


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", help="bag directory of `ddvs record`, or an older JSON Lines recording")
    parser.add_argument("--out", default=None, help="folder for the PNG files (default: <recording>/plots)")
    parser.add_argument("--title", default="", help="title written on every figure")


def run(args: argparse.Namespace) -> int:
    import json

    from clients.analysis import summarize
    from clients.recording import load_recording

    recording = load_recording(args.recording)
    out = Path(args.out) if args.out else Path(args.recording) / "plots"
    for path in plot_recording(recording, out, args.title):
        print(path)
    print(json.dumps(summarize(recording).as_dict(), indent=2))
    return 0
