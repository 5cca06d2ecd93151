"""Batched fleet path: launches per frame and cost per frame against the number of robots, per robot and in lock-step
(`registration.lockstep`), on each Taichi backend; and the constants of the robots-per-device model
(docs/performance.md, "Robots per device").

For each backend (a subprocess with `DDVS_TAICHI_ARCH` set) and each robot count B, B robots
(`evaluation.fleet_frames`: 320×240 frames, 200×150 template, the service's registration defaults) track their
frames, one frame per robot per fleet cycle, through two fleets of trackers started alike, the cycles alternated:
- per robot: `tracker.track` of each robot's frame in turn (what the `ddvs serve` loop does, one frame a turn);
- lock-step: `Lockstep.run` of the B `tracker.track` calls: one `planar_step` launch per iteration for all.
Per cycle: wall time, Taichi launches (calls of `kernels.launch.Prepared`) and the time inside them; the two
fleets' estimates are compared (largest corner difference). Reported: medians per frame (cycle / B), launches per
frame, the lock-step/per-robot ratio of the same run.

Model constants: one `planar_step` launch on a stack of B robots' level-0 steps (all robots active) is timed for
each B, and `t_launch(B) = t_0 + B · P · c_pixel` fitted (least squares; P = 30,000 template pixels): `t_0` the
fixed cost of a launch (on Vulkan it includes copying the arrays to the device and back, which grows with B and so
partly lands in the slope), `c_pixel` the cost per pixel evaluated; `t_host`, the Python per robot frame, is the
per-robot path's time outside launches per frame.

Figures from lavapipe (Vulkan on the CPU) check the path and the launch counts; they are not GPU speeds.

    .venv/bin/python benchmarks/bench_batched.py [--arch cpu vulkan] [--robots 1 2 4 8 16] [--cycles 20]
                                                 [--write-readme]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_registration import machine, write_readme_section  # noqa: E402 - after the path set-up
from evaluation.fleet_frames import TEMPLATE, robot_frames  # noqa: E402

WARM_UP_CYCLES = 3
FIT_REPEATS = 30


class LaunchClock:
    """Counts `kernels.launch.Prepared` launches and the wall time spent inside them."""

    def __init__(self) -> None:
        from kernels import launch

        self.count = 0
        self.seconds = 0.0
        call = launch.Prepared.__call__
        clock = self

        def timed(prepared: launch.Prepared) -> None:
            t = time.perf_counter()
            call(prepared)
            clock.seconds += time.perf_counter() - t
            clock.count += 1

        launch.Prepared.__call__ = timed  # type: ignore[method-assign]


def corners_apart(a: np.ndarray, b: np.ndarray, roi: tuple[int, int, int, int]) -> float:
    from evaluation.pairs import corner_error

    return corner_error(a, b, roi)


def measure_fleet(n_robots: int, cycles: int, clock: LaunchClock) -> dict[str, Any]:
    """Both paths over `cycles` fleet cycles of `n_robots` robots (module docstring)."""
    from ddvs_service.registration.lockstep import Lockstep
    from ddvs_service.registration.tracker import Tracker

    robots = [robot_frames(k, WARM_UP_CYCLES + cycles) for k in range(n_robots)]
    fleets = []
    for _ in range(2):
        fleet = []
        for robot in robots:
            tracker = Tracker.prepare(robot.reference, roi=robot.roi)
            tracker.reset(robot.start)
            fleet.append(tracker)
        fleets.append(fleet)
    alone, together = fleets
    lockstep = Lockstep()
    rows: dict[str, list[tuple[float, int, float]]] = {"per_robot": [], "lockstep": []}
    apart = 0.0
    converged = 0
    try:
        for c in range(WARM_UP_CYCLES + cycles):
            frames = [robot.frames[c] for robot in robots]
            order = ("per_robot", "lockstep") if c % 2 == 0 else ("lockstep", "per_robot")
            results: dict[str, list[Any]] = {}
            for path in order:
                n0, s0, t0 = clock.count, clock.seconds, time.perf_counter()
                if path == "per_robot":
                    results[path] = [tracker.track(frame) for tracker, frame in zip(alone, frames, strict=True)]
                else:
                    results[path] = lockstep.run([lambda t=t, f=f: t.track(f)
                                                  for t, f in zip(together, frames, strict=True)])
                if c >= WARM_UP_CYCLES:
                    rows[path].append((time.perf_counter() - t0, clock.count - n0, clock.seconds - s0))
            for robot, a, b in zip(robots, results["per_robot"], results["lockstep"], strict=True):
                apart = max(apart, corners_apart(a.G, b.G, robot.roi))
                converged += int(a.converged and b.converged)
    finally:
        lockstep.close()

    def per_frame(path: str) -> dict[str, float]:
        wall = np.array([r[0] for r in rows[path]]) / n_robots
        launches = np.array([r[1] for r in rows[path]]) / n_robots
        inside = np.array([r[2] for r in rows[path]]) / n_robots
        return {"ms": float(np.median(wall) * 1e3), "launches": float(launches.mean()),
                "launch_ms": float(np.median(inside) * 1e3), "host_ms": float(np.median(wall - inside) * 1e3)}

    per_robot, lock = per_frame("per_robot"), per_frame("lockstep")
    ratios = [b[0] / a[0] for a, b in zip(rows["per_robot"], rows["lockstep"], strict=True)]
    return {"robots": n_robots, "per_robot": per_robot, "lockstep": lock, "ratio": float(np.median(ratios)),
            "corners_apart_px": apart, "converged": converged, "frames": n_robots * (WARM_UP_CYCLES + cycles)}


def fit_launch(robot_counts: list[int]) -> dict[str, Any]:
    """Median time of one `planar_step` launch on a stack of B robots' level-0 steps, for each B, and the fit
    `t_0 + B · P · c_pixel` (module docstring)."""
    from ddvs_service.registration.planar import PlanarRegistration
    from kernels.backend import compile_settings
    from kernels.launch import Prepared
    from kernels.planar_step import planar_step

    times = {}
    for n in robot_counts:
        robots = [robot_frames(k, 1) for k in range(n)]
        engines = [PlanarRegistration.prepare(r.reference, roi=r.roi) for r in robots]
        for engine, robot in zip(engines, robots, strict=True):
            engine.run(robot.frames[0], G0=robot.start, first_level=0)  # fills each engine's level-0 parameters
        inputs = [engine.step_inputs(0) for engine in engines]
        ref = np.stack([i.reference for i in inputs])
        cur = np.stack([i.current.buffers[0] for i in inputs])
        params = np.stack([i.params for i in inputs])
        work = np.zeros((n, inputs[0].work.size), dtype=np.float32)
        with compile_settings():
            launch = Prepared(planar_step, ref, cur, params, work, *inputs[0].grid)
        launch()
        samples = []
        for _ in range(FIT_REPEATS):
            t = time.perf_counter()
            launch()
            samples.append(time.perf_counter() - t)
        times[n] = float(np.median(samples))
    pixels = TEMPLATE[0] * TEMPLATE[1]
    B = np.array(robot_counts, dtype=float)
    slope, intercept = np.polyfit(B, np.array([times[n] for n in robot_counts]), 1)
    return {"launch_ms": {str(n): t * 1e3 for n, t in times.items()}, "t0_ms": float(intercept * 1e3),
            "c_pixel_ns": float(slope / pixels * 1e9), "pixels": pixels}


def measure(robot_counts: list[int], cycles: int) -> dict[str, Any]:
    """This process's backend: every fleet size and the launch fit."""
    from kernels.backend import init

    arch = init()
    clock = LaunchClock()
    fleets = [measure_fleet(n, cycles, clock) for n in robot_counts]
    return {"arch": arch, "machine": machine(), "fleets": fleets, "fit": fit_launch(robot_counts),
            "load_after": [round(x, 2) for x in os.getloadavg()]}


def markdown(results: list[dict[str, Any]], cycles: int) -> str:
    lines = []
    for result in results:
        fit = result["fit"]
        lines += [
            f"**{result['arch']}** — {result['machine']}; load average after: "
            f"{', '.join(str(x) for x in result['load_after'])}. {cycles} fleet cycles per row after "
            f"{WARM_UP_CYCLES} of warm-up, medians per frame (cycle / robots).",
            "",
            "| robots | per robot: ms / frame | launches / frame | in launches ms | lock-step: ms / frame | "
            "launches / frame | in launches ms | lock-step / per robot | estimates apart (px) | converged |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for row in result["fleets"]:
            a, b = row["per_robot"], row["lockstep"]
            lines.append(f"| {row['robots']} | {a['ms']:.2f} | {a['launches']:.2f} | {a['launch_ms']:.2f} | "
                         f"{b['ms']:.2f} | {b['launches']:.2f} | {b['launch_ms']:.2f} | {row['ratio']:.2f} | "
                         f"{row['corners_apart_px']:.1e} | {row['converged']} of {row['frames']} |")
        times = ", ".join(f"B = {n}: {t:.2f} ms" for n, t in fit["launch_ms"].items())
        host = result["fleets"][0]["per_robot"]["host_ms"]
        lines += ["", f"One `planar_step` launch on a stack of B robots' level-0 steps: {times}; fitted "
                      f"t_launch(B) = t_0 + B · P · c_pixel with **t_0 = {fit['t0_ms']:.3f} ms**, "
                      f"**c_pixel = {fit['c_pixel_ns']:.2f} ns** (P = {fit['pixels']:,} pixels); "
                      f"**t_host = {host:.2f} ms** per frame outside launches (per robot, 1 robot).", ""]
    return "\n".join(lines).rstrip("\n")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--arch", nargs="+", default=["cpu", "vulkan"], help="Taichi backends, one process each")
    parser.add_argument("--robots", nargs="+", type=int, default=[1, 2, 4, 8, 16])
    parser.add_argument("--cycles", type=int, default=20, help="measured fleet cycles per robot count")
    parser.add_argument("--write-readme", action="store_true", help="rewrite its section of docs/results/fleet.md")
    parser.add_argument("--measure", action="store_true", help=argparse.SUPPRESS)  # the child: this backend only
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure(args.robots, args.cycles)))
        return 0
    results = []
    for arch in args.arch:
        done = subprocess.run([sys.executable, __file__, "--measure", "--robots", *map(str, args.robots),
                               "--cycles", str(args.cycles)], cwd=ROOT, capture_output=True, text=True,
                              env={**os.environ, "DDVS_TAICHI_ARCH": arch, "PYTHONPATH": str(ROOT)})
        if done.returncode != 0:
            raise SystemExit(f"{arch}: {done.stderr[-3000:]}")
        result = json.loads(done.stdout.strip().splitlines()[-1])
        if result["arch"] != arch:
            raise SystemExit(f"asked for {arch!r}, Taichi started {result['arch']!r}")
        results.append(result)
    table = markdown(results, args.cycles)
    print(table)
    if args.write_readme:
        write_readme_section("batched-fleet", "Batched fleet path: launches and cost per frame against robots",
                             table, "bench_batched.py")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
