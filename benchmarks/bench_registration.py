"""Speed of the planar registration engine (issue 3), with its baselines measured in the same run.

- One Gauss-Newton iteration (8 sl(3) + 1 gain + 1 bias unknowns, Huber weights) at a 200×150 and a 640×480 ROI of
  the Oxford boat image: `PlanarRegistration.run` forced to run K iterations on one level (step tolerance 1e-12 px),
  divided by K; it includes the Python solve and update. Baselines: `cv2.findTransformECC` (MOTION_HOMOGRAPHY, the
  same ROI as template, the whole current image as input, exactly K iterations, divided by K, so its per-call setup
  is spread over the iterations) and one evaluation of the vectorised float64 numpy iteration
  (`benchmarks/numpy_iteration.py`, no solve). The three are interleaved in every repetition; the ratios are the
  medians of the per-repetition ratios, which cancels most of the load of a shared machine.
- A tracking frame: `Tracker.track` on consecutive frames of a smooth trajectory (2 px, 0.1°, 0.1 % scale apart)
  at a 200×150 ROI; median over the frames, with the worst corner error against the true homographies.
- First registration in a fresh process (`import` of the engine, Taichi start, kernels loaded or compiled, one
  registration from identity): with the Taichi offline cache warm, and cold (an empty temporary cache directory
  through `TI_OFFLINE_CACHE_FILE_PATH`).

Run: `.venv/bin/python benchmarks/bench_registration.py [--reps 30] [--write-readme]`; the machine (CPU, cores, load
average, Taichi backend) is printed with the table. `--write-readme` replaces the registration section of
`benchmarks/README.md`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ddvs_service.registration.config import RegistrationConfig  # noqa: E402
from ddvs_service.registration.planar import PlanarRegistration  # noqa: E402
from ddvs_service.registration.tracker import Tracker  # noqa: E402
from evaluation.numpy_iteration import numpy_step  # noqa: E402
from evaluation.pairs import ONE_GAIN_HUBER  # noqa: E402
from sim.textures import texture_path  # noqa: E402

IMAGE = texture_path("boat")
# The results page (docs/results/) holding each benchmark section that `--write-readme` rewrites.
RESULTS = ROOT / "docs" / "results"
RESULTS_PAGES = {
    "registration-real-pairs": RESULTS / "accuracy.md",
    "registration-cost-optimum": RESULTS / "accuracy.md",
    "registration-bench": RESULTS / "speed.md",
    "global-init": RESULTS / "robustness.md",
    "record-cost": RESULTS / "speed.md",
    "batched-fleet": RESULTS / "fleet.md",
}
ITERATIONS = 20  # K iterations per timed call (ours and ECC)


def load_reference() -> np.ndarray:
    img = cv2.imread(str(IMAGE), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise FileNotFoundError(f"benchmark image {IMAGE} could not be read as an image")
    return img.astype(np.float32)


def centred_roi(shape: tuple[int, ...], w: int, h: int) -> tuple[int, int, int, int]:
    return (shape[1] - w) // 2, (shape[0] - h) // 2, w, h


def similarity_about(centre: tuple[float, float], shift: tuple[float, float], angle_deg: float,
                     scale: float) -> np.ndarray:
    """Rotation by `angle_deg` and scaling about `centre` (pixels), then a shift (pixels)."""
    a = np.deg2rad(angle_deg)
    R = scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    H = np.eye(3)
    H[:2, :2] = R
    H[:2, 2] = np.asarray(centre) + np.asarray(shift) - R @ np.asarray(centre)
    return H


def warp(img: np.ndarray, H: np.ndarray) -> np.ndarray:
    """The current image of a planar scene: current(H p) = img(p)."""
    return cv2.warpPerspective(img, H, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR)


def machine() -> str:
    from kernels.backend import init

    model = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                  if line.startswith("model name")), platform.processor())
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    return f"{model}, {os.cpu_count()} cores, load average {load}, Python {platform.python_version()}, " \
           f"Taichi backend {init()}"


def iteration_times(ref: np.ndarray, w: int, h: int, reps: int) -> dict[str, float]:
    """Median per-iteration times (ms) of ours, ECC and numpy, and the medians of the per-repetition ratios."""
    roi = centred_roi(ref.shape, w, h)
    x, y = roi[0], roi[1]
    cur = warp(ref, similarity_about((x + w / 2, y + h / 2), (1.0, -0.7), 0.3, 1.003))
    config = RegistrationConfig(levels=1, max_iterations=ITERATIONS, step_tolerance_px=1e-12, **ONE_GAIN_HUBER)
    problem = PlanarRegistration.prepare(ref, roi=roi, config=config)
    params = _kernel_params(problem)
    template = np.ascontiguousarray(ref[y : y + h, x : x + w])
    ecc_start = np.array([[1, 0, x], [0, 1, y], [0, 0, 1]], dtype=np.float32)
    criteria = (cv2.TERM_CRITERIA_COUNT, ITERATIONS, 0.0)

    def ours() -> float:
        t = time.perf_counter()
        result = problem.run(cur, G0=np.eye(3))
        elapsed = time.perf_counter() - t
        if result.iterations != [ITERATIONS]:
            raise RuntimeError(f"expected {ITERATIONS} iterations, ran {result.iterations}: {result.reason}")
        return elapsed / ITERATIONS

    def ecc() -> float:
        t = time.perf_counter()
        cv2.findTransformECC(template, cur, ecc_start.copy(), cv2.MOTION_HOMOGRAPHY, criteria, None, 1)
        return (time.perf_counter() - t) / ITERATIONS

    def numpy_iteration() -> float:
        t = time.perf_counter()
        numpy_step(problem.reference[0], cur, params, (1, 1))
        return time.perf_counter() - t

    ours(), ecc(), numpy_iteration()  # compile, warm caches
    rows = np.array([(ours(), ecc(), numpy_iteration()) for _ in range(reps)]) * 1e3
    return {
        "ours_ms": float(np.median(rows[:, 0])),
        "ecc_ms": float(np.median(rows[:, 1])),
        "numpy_ms": float(np.median(rows[:, 2])),
        "vs_ecc": float(np.median(rows[:, 0] / rows[:, 1])),
        "vs_numpy": float(np.median(rows[:, 0] / rows[:, 2])),
    }


def _kernel_params(problem: PlanarRegistration) -> np.ndarray:
    """The kernel's parameter array at identity, level 0, Huber with σ = 4 grey levels (the numpy iteration's input)."""
    from ddvs_service.registration.planar import _State

    problem._fill_level(problem.levels[0])
    problem._fill_state(np.eye(3), _State(G=np.eye(3), gains=np.ones((1, 1)), beta=0.0, scale=4.0))
    return problem._params.copy()


def tracking(ref: np.ndarray, frames: int) -> dict[str, float]:
    """Median `Tracker.track` time (ms) over a smooth trajectory; worst corner error (px) and median iterations."""
    roi = centred_roi(ref.shape, 200, 150)
    x, y, w, h = roi
    centre = (x + w / 2, y + h / 2)
    truths = [similarity_about(centre, (1.6 * k, 1.2 * k), 0.1 * k, 1.0 + 0.001 * k) for k in range(frames + 1)]
    images = [warp(ref, H) for H in truths]
    corners = np.array([[x, x + w - 1, x + w - 1, x], [y, y, y + h - 1, y + h - 1], [1, 1, 1, 1]], dtype=float)
    tracker = Tracker.prepare(ref, roi, RegistrationConfig(**ONE_GAIN_HUBER))
    tracker.track(images[0])  # compile
    times, errors, iterations = [], [], []
    for H_true, image in zip(truths[1:], images[1:], strict=True):
        t = time.perf_counter()
        result = tracker.track(image)
        times.append(time.perf_counter() - t)
        a, b = H_true @ corners, result.G @ corners
        errors.append(float(np.max(np.linalg.norm(a[:2] / a[2] - b[:2] / b[2], axis=0))))
        iterations.append(sum(result.iterations))
    return {"frame_ms": float(np.median(times) * 1e3), "max_error_px": max(errors),
            "iterations": float(np.median(iterations))}


def first_registration(cache_dir: str | None) -> dict[str, float]:
    """A fresh interpreter runs `--first-registration`; `cache_dir`: Taichi offline cache (None: the default)."""
    env = dict(os.environ)
    if cache_dir is not None:
        env["TI_OFFLINE_CACHE_FILE_PATH"] = cache_dir
    t = time.perf_counter()
    out = subprocess.run([sys.executable, __file__, "--first-registration"], env=env, capture_output=True,
                         text=True, check=True)
    process_s = time.perf_counter() - t
    return {**json.loads(out.stdout.strip().splitlines()[-1]), "process_s": process_s}


def _first_registration_child() -> None:
    """Child of `first_registration`: time from before the engine's import to the end of the first registration."""
    t = time.perf_counter()
    from ddvs_service.registration.planar import register

    ref = load_reference()
    roi = centred_roi(ref.shape, 200, 150)
    x, y, w, h = roi
    cur = warp(ref, similarity_about((x + w / 2, y + h / 2), (5.0, -3.0), 2.0, 1.02))
    t_register = time.perf_counter()
    result = register(ref, cur, roi=roi, config=RegistrationConfig(**ONE_GAIN_HUBER))
    t_end = time.perf_counter()
    print(json.dumps({"first_s": t_end - t, "register_s": t_end - t_register, "converged": result.converged}))


def markdown(machine_line: str, iters: dict[str, dict[str, float]], track: dict[str, float],
             warm: dict[str, float], cold: dict[str, float], reps: int) -> str:
    lines = [
        f"Machine: {machine_line}. Medians over {reps} interleaved repetitions of {ITERATIONS} iterations.",
        "",
        "| measurement | ours | cv2.findTransformECC | numpy (float64) | ours / ECC (target ≤ 0.5) "
        "| ours / numpy (target ≤ 0.3) |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in iters.items():
        lines.append(f"| one iteration, {name} ROI | {r['ours_ms']:.3f} ms | {r['ecc_ms']:.3f} ms "
                     f"| {r['numpy_ms']:.3f} ms | {r['vs_ecc']:.2f} | {r['vs_numpy']:.3f} |")
    lines += [
        "",
        "| measurement | value | target |",
        "|---|---|---|",
        f"| tracking frame, 200×150 ROI, 2 px apart (median; worst corner error {track['max_error_px']:.3f} px, "
        f"median {track['iterations']:.0f} iterations) | {track['frame_ms']:.2f} ms | ≤ 3 ms |",
        f"| first registration, fresh process, warm offline cache (import → result; whole process "
        f"{warm['process_s']:.2f} s) | {warm['first_s']:.2f} s | ≤ 2 s |",
        f"| first registration, fresh process, cold offline cache (whole process {cold['process_s']:.2f} s) "
        f"| {cold['first_s']:.2f} s | reported |",
    ]
    return "\n".join(lines)


def write_readme_section(key: str, title: str, table: str, script: str) -> None:
    """Replace (or append) the section between the `<!-- key:begin/end -->` markers of its results page
    (`RESULTS_PAGES[key]`, under docs/results/), dated: results pages are where measurements carry their date."""
    page = RESULTS_PAGES[key]
    begin, end = f"<!-- {key}:begin -->", f"<!-- {key}:end -->"
    date = time.strftime("%Y-%m-%d", time.gmtime())
    section = (f"{begin}\n## {title} (`benchmarks/{script}`)\n\nMeasured {date}.\n\n{table}\n\n"
               f"Re-run: `.venv/bin/python benchmarks/{script} --write-readme`.\n{end}")
    text = page.read_text(encoding="utf-8")
    if begin in text and end in text:
        text = text[: text.index(begin)] + section + text[text.index(end) + len(end) :]
    else:
        text = text.rstrip("\n") + "\n\n" + section + "\n"
    page.write_text(text, encoding="utf-8")


def table_main(doc: str, run: Callable[[], str], key: str, title: str, script: str) -> int:
    """The `main` of a benchmark that prints one markdown table: `run()` → stdout, and with `--write-readme` into
    its `key` section of its results page (`write_readme_section`). `doc`: the script's docstring."""
    parser = argparse.ArgumentParser(description=doc.split("\n")[0])
    parser.add_argument("--write-readme", action="store_true", help="rewrite its section of its results page")
    args = parser.parse_args()
    table = run()
    print(table)
    if args.write_readme:
        write_readme_section(key, title, table, script)
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--reps", type=int, default=30, help="interleaved repetitions per ROI size")
    parser.add_argument("--frames", type=int, default=60, help="tracking frames")
    parser.add_argument("--write-readme", action="store_true", help="rewrite its section of its results page")
    parser.add_argument("--first-registration", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.first_registration:
        _first_registration_child()
        return 0
    first_registration(None)  # make sure the default offline cache is warm
    warm = first_registration(None)
    with tempfile.TemporaryDirectory(prefix="ddvs-ti-cache-") as empty:
        cold = first_registration(empty)
    ref = load_reference()
    iters = {f"{w}×{h}": iteration_times(ref, w, h, args.reps if w <= 200 else max(5, args.reps // 3))
             for w, h in ((200, 150), (640, 480))}
    track = tracking(ref, args.frames)
    table = markdown(machine(), iters, track, warm, cold, args.reps)
    print(table)
    if args.write_readme:
        write_readme_section("registration-bench", "Registration speed", table, "bench_registration.py")
    return 0


if __name__ == "__main__":
    sys.exit(main())
