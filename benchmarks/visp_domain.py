"""ViSP's photometric visual servoing on the domain sweep's finite plane: success rate per displacement size, beside
the sweep's own rates (issue 23).

ViSP side (`benchmarks/visp/photometric_domain.cpp`, compiled here with g++ and `pkg-config visp` into a temporary
directory; Debian's `libvisp-dev` 3.5): `vpFeatureLuminance` (every pixel but ViSP's 10 px border, constant depth Z
= 1 m, the true depth at the goal) and vpServo's eye-in-hand law with the interaction matrix at the goal
(`vpServo::DESIRED`: v = −λ L*⁺ (I − I*), written out with L*⁺ computed once — the same law, without vpServo's
pseudo-inverse of the same 210 000 × 6 matrix at every image) on `vpImageSimulator` renders (bilinear) of the same
scene as `ddvs experiment domain` on the "planar" target: the texture `TEXTURE` on 1 m × 0.75 m at 1 m, uniform grey
(128) around it, f = 500 px, 550×418, the same starts (`orchestration.experiment_domain.trial_start`, start rule
included), dt = 0.1 s, the service's velocity limits, image budget 400, gain λ = `VISP_GAIN` = 5 /s (λ·dt = 0.5;
ViSP's example uses 30 /s at 0.04 s, 1.2): with the sweep's λ = 0.4 /s this law barely moves — its L*⁺ (I − I*) is a
small fraction of the displacement on this texture, so from 5 mm / 1.5° the squared error fell by 10 % in 100 images
— and at λ·dt = 1 it chatters about the goal. A trial stops converged when ‖v‖ and ‖ω‖ are below 1e-4 (m/s, rad/s),
diverged when the camera leaves 0.2–3 m of the target centre; success = a true final error ≤ 10 mm and ≤ 1° (the
sweep's bounds) when it stops or at the end of the budget. No illumination change or noise (ViSP's luminance feature
assumes constant brightness).

With `--domain DIR` the table also shows the sweep's planar rates from `DIR/trials.jsonl` (same seed required);
`--reuse` rebuilds the table from the ViSP trials saved in `--out` (after each round of sizes) without running ViSP.
Run: `.venv/bin/python benchmarks/visp_domain.py --trials 8 --domain reports/domain_finite` (default sizes).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ddvs_service.lie import pose_inv, so3_log
from ddvs_service.service.config import ControlSettings
from orchestration.experiment_domain import (
    CAMERA,
    TARGET_EXTENT_M,
    UNIT_R_DEG,
    UNIT_T_M,
    DomainSettings,
    make_surface,
    trial_start,
)
from orchestration.experiment_synthetic import TEXTURE
from sim.textures import load_texture

SOURCE = Path(__file__).with_name("visp") / "photometric_domain.cpp"
BACKGROUND = 128
STOP_VELOCITY = 1e-4
VISP_GAIN = 5.0


@dataclass
class VispTrial:
    size: float
    trial: int
    outcome: str  # success (true final error within the bounds), or why not: diverged, budget, wrong_pose
    images: int
    translation_error_m: float
    rotation_error_deg: float


def build(work: Path) -> Path:
    """Compile the harness; a clear error when g++ or ViSP's pkg-config file is missing."""
    for tool in ("g++", "pkg-config"):
        if shutil.which(tool) is None:
            raise RuntimeError(f"{tool} not found: install it (Debian: apt-get install g++ pkg-config libvisp-dev)")
    flags = subprocess.run(["pkg-config", "--cflags", "--libs", "visp"], capture_output=True, text=True)
    if flags.returncode != 0:
        raise RuntimeError(f"pkg-config finds no ViSP ({flags.stderr.strip()}); Debian: apt-get install libvisp-dev")
    binary = work / "photometric_domain"
    subprocess.run(["g++", "-O2", "-o", str(binary), str(SOURCE), *flags.stdout.split()], check=True)
    return binary


def run_visp(binary: Path, texture_path: Path, starts: list[np.ndarray], max_images: int) -> list[tuple[int, str,
                                                                                                        np.ndarray]]:
    """`(images, reason, final T_world_cam)` of each start (`T_ref_start`, world = reference camera frame)."""
    T_world_target = make_surface("planar").T_world_surface
    limits = ControlSettings()
    header = [str(texture_path), CAMERA.width, CAMERA.height, CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy,
              *TARGET_EXTENT_M, float(T_world_target[2, 3]), VISP_GAIN, 0.1, max_images, limits.max_linear,
              limits.max_angular, STOP_VELOCITY, BACKGROUND]
    poses = [T_world_target] + [pose_inv(T) @ T_world_target for T in starts]
    text = " ".join(map(str, header)) + "\n" + " ".join(repr(float(v)) for v in poses[0].ravel())
    text += f"\n{len(starts)}\n" + "\n".join(" ".join(repr(float(v)) for v in cMo.ravel()) for cMo in poses[1:]) + "\n"
    # One thread: under a shared machine's load, OpenMP threads of the ViSP build wait on each other.
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = subprocess.run([str(binary)], input=text, capture_output=True, text=True, env=env)
    if run.returncode != 0:
        raise RuntimeError(f"the ViSP harness failed (exit {run.returncode}): {run.stderr.strip()}")
    out = run.stdout.splitlines()
    results = []
    for line in out:
        fields = line.split()
        cMo = np.array([float(v) for v in fields[2:18]]).reshape(4, 4)
        results.append((int(fields[0]), fields[1], T_world_target @ pose_inv(cMo)))
    return results


def visp_trials(sizes: list[float], trials: int, seed: int, max_images: int, saved: Path) -> list[VispTrial]:
    """Every (size, trial), trial-major (an interrupted run has covered every size about equally); the trials so far
    are written to `saved` (JSON) after each round of sizes."""
    settings = DomainSettings(seed=seed)
    out: list[VispTrial] = []
    with tempfile.TemporaryDirectory(prefix="ddvs-visp-") as tmp:
        work = Path(tmp)
        binary = build(work)
        texture_path = work / "texture.pgm"
        cv2.imwrite(str(texture_path), np.clip(np.round(load_texture(TEXTURE)), 0, 255).astype(np.uint8))
        for k in range(trials):
            starts = [trial_start(settings, size, k)[0] for size in sizes]
            results = run_visp(binary, texture_path, starts, max_images)
            for size, (images, reason, T) in zip(sizes, results, strict=True):
                t_err = float(np.linalg.norm(T[:3, 3]))
                r_err = float(np.degrees(np.linalg.norm(so3_log(T[:3, :3]))))
                small = t_err <= settings.max_translation_m and r_err <= settings.max_rotation_deg
                outcome = "success" if small else "wrong_pose" if reason == "converged" else reason
                out.append(VispTrial(size, k, outcome, images, t_err, r_err))
            saved.write_text(json.dumps([t.__dict__ for t in out], indent=1))
    return out


def sweep_rates(domain: Path, seed: int) -> dict[tuple[str, float], tuple[int, int]]:
    """`(law, size) → (successes, trials)` of the planar target in a domain sweep's journal."""
    settings = json.loads((domain / "settings.json").read_text())
    if settings["seed"] != seed or settings["illumination"] or settings["scene"] != "finite":
        raise ValueError(f"{domain} is not a finite-scene sweep without illumination change with seed {seed}")
    rates: dict[tuple[str, float], tuple[int, int]] = {}
    for line in (domain / "trials.jsonl").read_text().splitlines():
        t = json.loads(line)
        if t["target"] == "planar":
            wins, n = rates.get((t["law"], t["size"]), (0, 0))
            rates[(t["law"], t["size"])] = (wins + (t["outcome"] == "success"), n + 1)
    return rates


def table(trials: list[VispTrial], rates: dict[tuple[str, float], tuple[int, int]]) -> str:
    lines = ["| size | ‖t‖ (m) | angle (°) | ViSP photometric | diverged | budget | wrong pose | mean images "
             "(successes) | ddvs decoupled DVS | ddvs DVS |", "|---|---|---|---|---|---|---|---|---|---|"]
    for size in sorted({t.size for t in trials}):
        group = [t for t in trials if t.size == size]
        wins = [t.images for t in group if t.outcome == "success"]
        count = {o: sum(t.outcome == o for t in group) for o in ("diverged", "budget", "wrong_pose")}
        ours = []
        for law in ("ddvs", "dvs"):
            w, n = rates.get((law, size), (0, 0))
            ours.append(f"{w}/{n} ({w / n:.0%})" if n else "—")
        lines.append(f"| {size:g} | {size * UNIT_T_M:.3f} | {size * UNIT_R_DEG:g} | {len(wins)}/{len(group)} "
                     f"({len(wins) / len(group):.0%}) | {count['diverged']} | {count['budget']} "
                     f"| {count['wrong_pose']} | {np.mean(wins) if wins else float('nan'):.0f} | {ours[0]} "
                     f"| {ours[1]} |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=float, nargs="+", default=[0.1, 0.25, 0.5, 0.75, 1.0, 2.0])
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-images", type=int, default=400)
    parser.add_argument("--domain", type=Path, help="a finite-scene domain sweep to show beside (its --out)")
    parser.add_argument("--out", type=Path, default=Path("reports/visp_domain"))
    parser.add_argument("--reuse", action="store_true", help="table from the trials saved in --out, no ViSP run")
    args = parser.parse_args()
    saved = args.out / "trials.json"
    args.out.mkdir(parents=True, exist_ok=True)
    if args.reuse:
        trials = [VispTrial(**t) for t in json.loads(saved.read_text())]
    else:
        trials = visp_trials(args.sizes, args.trials, args.seed, args.max_images, saved)
    rates = sweep_rates(args.domain, args.seed) if args.domain else {}
    text = table(trials, rates)
    (args.out / "visp_domain.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
