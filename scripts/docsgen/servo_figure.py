"""The README's figure: one servo converging — the camera's first view beside the reference, the control error
and the camera's 3-D trajectory — from the bag of a `ddvs demo` run.

Run: `ddvs demo --out reports/demo && python -m scripts.docsgen.servo_figure reports/demo`;
writes `docs/images/servo-converging.png`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from clients.analysis import pose_series, status_series
from clients.bag import bag_messages
from clients.recording import load_recording
from ddvs_service.protocol.keys import Keys
from ddvs_service.protocol.ros import decode_image
from scripts.docsgen.markdown import ROOT

OUT = ROOT / "docs" / "images" / "servo-converging.png"


def first_frame(bag: Path, keys: Keys) -> NDArray[np.uint8]:
    """The first camera image of the bag, as a grey or RGB array."""
    for message in bag_messages(bag):
        if message.topic.endswith("/" + keys.camera_image.split("/", 2)[-1]):
            image = decode_image(message.data)
            return np.array(image.array)
    raise ValueError(f"{bag}: no camera image recorded")


def compose(run_dir: Path, out: Path = OUT) -> Path:
    """Draw the three panels of a demo run (`run_dir`: `reference.png`, `recording/`) into `out`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recording = load_recording(run_dir / "recording")
    keys = Keys(recording.meta.get("prefix", "ddvs"), recording.meta.get("robot", "robot0"))
    reference = plt.imread(run_dir / "reference.png")
    start = first_frame(run_dir / "recording", keys)
    series = status_series(recording)
    poses = pose_series(recording)
    if poses is None:
        raise ValueError(f"{run_dir}: the recording has no ground truth or reference pose")

    fig = plt.figure(figsize=(12, 3.6))
    grid = fig.add_gridspec(2, 3, width_ratios=[0.8, 1.3, 1.1])
    for row, (image, title) in enumerate(((start, "camera at the start"), (reference, "reference image"))):
        ax = fig.add_subplot(grid[row, 0])
        ax.imshow(image, cmap="gray")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    ax = fig.add_subplot(grid[:, 1])
    ax.semilogy(np.arange(len(series.error_norm)), np.maximum(series.error_norm, 1e-12))
    ax.axhline(1e-3, color="k", ls="--", lw=0.8, label="stop threshold")
    ax.set_xlabel("image (30 Hz)")
    ax.set_ylabel("control error ‖ε̄‖")
    ax.set_title("decoupled DVS error (16)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    ax3 = fig.add_subplot(grid[:, 2], projection="3d")
    p = poses.position
    ax3.plot(p[:, 0], p[:, 1], p[:, 2], lw=1.5)
    ax3.scatter(*p[0], color="tab:red", label="start")
    ax3.scatter(0, 0, 0, color="k", marker="x", s=50, label="reference")
    ax3.set_xlabel("x (m)")
    ax3.set_ylabel("y (m)")
    ax3.set_zlabel("z (m)")
    ax3.set_title("camera path, reference camera frame", fontsize=9)
    ax3.legend(fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m scripts.docsgen.servo_figure", description=__doc__)
    parser.add_argument("run_dir", type=Path, help="a `ddvs demo` run's folder (the demo's default: reports/demo)")
    parser.add_argument("--out", type=Path, default=OUT, help=f"PNG to write (default {OUT.relative_to(ROOT)})")
    args = parser.parse_args(argv)
    print(f"wrote {compose(args.run_dir, args.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
