"""Re-acquisition under a large occluder, in the closed loop (issue 20): the robustness matrix's hard combination
with the target hidden for a while after the occluder came in.

The matrix's cells no longer go LOST under the occluder, so this forces it: from plant frame `--hide-from` the camera
sees a uniform grey image (the target hidden, the servo LOST) for `--hide-frames` frames, then the occluded view
again, the camera held still meanwhile. The run is `orchestration.experiment_robustness.run_one` (free-flying
camera, the service's per-frame code, lockstep at 30 Hz, re-acquisition within the step) under the condition
"hard_combination_hidden"; its verdict checks the servo against the ground truth ("frames servoed on a wrong fit":
twists from an estimate whose control error is far from the true one). Before issue 20's re-acquisition from the
last good estimate, such a run stayed LOST for good: the global initialiser cannot see through the occluder.

    .venv/bin/python benchmarks/reacquire_under_occluder.py [--targets planar saddle] [--laws ddvs dvs]
                                                            [--hide-from 150] [--hide-frames 10 30]
                                                            [--template 70]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from orchestration import experiment_robustness as robustness  # noqa: E402 - after the path set-up
from sim.conditions import FrameContext  # noqa: E402

F32 = NDArray[np.float32]


@dataclass(frozen=True)
class Hidden:
    """The target hidden: a uniform grey image (`level`) from plant frame `start` for `frames` frames."""

    start: int
    frames: int
    level: float = 90.0

    def __call__(self, image: F32, ctx: FrameContext) -> F32:
        if self.start <= ctx.index < self.start + self.frames:
            return np.full_like(image, self.level)
        return image


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--targets", nargs="+", default=["planar"], choices=robustness.TARGETS)
    parser.add_argument("--laws", nargs="+", default=["ddvs"], choices=["ddvs", "dvs"])
    parser.add_argument("--hide-from", type=int, default=150)
    parser.add_argument("--hide-frames", type=int, nargs="+", default=[10, 30])
    parser.add_argument("--template", type=int, default=None, help="planar template side (default: the shipped one)")
    args = parser.parse_args()
    base = robustness.CONDITIONS["hard_combination"]
    print(f"load average before: {os.getloadavg()}", flush=True)
    for frames in args.hide_frames:
        robustness.CONDITIONS["hard_combination_hidden"] = replace(
            base, images=(*base.images, Hidden(args.hide_from, frames)))
        for target in args.targets:
            for law in args.laws:
                template = {"registration": {"template_size": [args.template] * 2}} if args.template else {}
                settings = robustness.RobustnessSettings(targets=(target,), laws=(law,),
                                                         conditions=("hard_combination_hidden",),
                                                         overrides=template if target == "planar" else {})
                run = robustness.run_one(target, law, "paper", "hard_combination_hidden", settings)
                fields = {k: v for k, v in asdict(run).items() if not isinstance(v, list)}
                row = {"hidden_frames": frames, "template": args.template, **fields}
                print(json.dumps(row), flush=True)
    print(f"load average after: {os.getloadavg()}", flush=True)


if __name__ == "__main__":
    main()
