"""CPU cost of one robot's frame on a `ddvs serve` loop thread, and where it goes (issue 21).

One `RobotServo` with `bench_fleet`'s settings (320×240 frames, 200×150 template, the service's defaults) serves a
closed-loop plant in lockstep: the plant (same process, a Zenoh session of its own connected over loopback TCP)
renders the "boat" poster from its pose (`bench_fleet`'s scene and random start), publishes the frame, and waits for
the twist before integrating it and rendering the next, so the frames are the same on every run once the servo moves
(`servoed`). The loop thread's work per frame is what `ServeProcess` runs for a frame: the robot's inputs,
`handle_frame` (decode, registration, control, twist and status out, residual offer). Measured per frame after a
warm-up: the loop thread's CPU time (`time.thread_time`: the Python side; it waits while a kernel runs), the
process's (`time.process_time`: Taichi's worker threads, which run the kernels' pixel loops, and the Zenoh threads
besides) and wall time, the Taichi launches (calls of `kernels.launch.Prepared`), and the stages `handle_frame`
reports in its status (`latency_ms`). `--profile OUT`: the measured frames again under cProfile (its overhead
inflates the totals; the shares are what it is for). `--estimates OUT`: every frame's `G` and twist as JSON, to
compare two revisions (`--compare A B` prints the largest differences, from the first servoed frame on: `servoed`).

    .venv/bin/python benchmarks/bench_frame_cost.py [--frames 300] [--warm-up 30] [--profile OUT] [--estimates OUT]
    .venv/bin/python benchmarks/bench_frame_cost.py --compare A.json B.json
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_fleet import CAMERA, RATE_HZ, free_port, plant_scene, start_pose  # noqa: E402 - after the path set-up
from ddvs_service.lie import se3_exp  # noqa: E402
from ddvs_service.protocol import (  # noqa: E402
    Command,
    Header,
    Keys,
    SessionConfig,
    Time,
    declare_publisher,
    decode_twist_stamped,
    dump,
    encode_image,
    image_from_array,
    open_session,
)
from ddvs_service.protocol.upload import encode_upload  # noqa: E402
from ddvs_service.service.config import ServiceConfig  # noqa: E402
from ddvs_service.service.robot import RobotServo  # noqa: E402
from kernels import launch  # noqa: E402

TWIST_WAIT_S = 5.0


class LaunchCounter:
    """Counts `kernels.launch.Prepared` launches (every per-frame kernel launch of the tracker goes through one)."""

    def __init__(self) -> None:
        self.count = 0
        self._call = launch.Prepared.__call__
        counter = self

        def counted(prepared: launch.Prepared) -> None:
            counter.count += 1
            counter._call(prepared)

        launch.Prepared.__call__ = counted  # type: ignore[method-assign]


def run(frames: int, warm_up: int, profile: Path | None) -> dict[str, Any]:
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="ddvs-frame-cost-") as tmp:
        config = ServiceConfig.model_validate({
            "robot": "r0", "state_dir": tmp, "zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]},
            "intrinsics": {"fx": CAMERA.fx, "fy": CAMERA.fy, "cx": CAMERA.cx, "cy": CAMERA.cy,
                           "width": CAMERA.width, "height": CAMERA.height},
            "registration": {"template_size": [200, 150]},
        })
        service = open_session(config.zenoh)
        plant = open_session(SessionConfig(connect=[f"tcp/127.0.0.1:{port}"]))
        robot = RobotServo(config)
        try:
            return _serve(robot, service, plant, frames, warm_up, profile)
        finally:
            robot.close("benchmark done")
            plant.close()
            service.close()


def _serve(robot: RobotServo, service: Any, plant: Any, frames: int, warm_up: int,
           profile: Path | None) -> dict[str, Any]:
    robot.open(service)
    keys = Keys("ddvs", "r0")
    scene = plant_scene()
    goal = np.clip(scene.render(), 0, 255).astype(np.uint8)
    for command in (Command(op="set_reference", source="upload", image={"format": "png", "data": encode_upload(goal)}),
                    Command(op="start")):
        reply = robot.handle_command(dump(command))
        if not reply.ok:
            raise SystemExit(f"{command.op} refused: {reply.error}")
    got = threading.Event()
    twist = np.zeros(6)

    def on_twist(sample: Any) -> None:
        nonlocal twist
        twist = decode_twist_stamped(sample.payload.to_bytes()).vector
        got.set()

    pub = declare_publisher(plant, keys, "camera_image")
    sub = plant.declare_subscriber(keys.key("servo_twist"), on_twist)
    time.sleep(0.5)  # the sessions meet
    pose = start_pose(0)
    launches = LaunchCounter()
    profiler = cProfile.Profile() if profile else None
    rows: list[dict[str, Any]] = []
    for k in range(warm_up + frames):
        image = scene.render(scene.homography(pose[:3, :3], pose[:3, 3]))
        frame = np.clip(image, 0, 255).astype(np.uint8)
        got.clear()
        pub.put(encode_image(image_from_array(frame, "mono8", Header(Time.from_ns(time.time_ns()), "camera"))))
        inbox = robot.inbox
        deadline = time.monotonic() + TWIST_WAIT_S
        while inbox.waiting_since is None:
            inbox.wait(0.05)
            if time.monotonic() > deadline:
                raise SystemExit(f"frame {k} never reached the robot's inbox")
        measured = k >= warm_up
        n0, cpu0, proc0, wall0 = launches.count, time.thread_time(), time.process_time(), time.perf_counter()
        if profiler is not None and measured:
            profiler.enable()
        robot.handle_inputs()
        arrival = inbox.take_frame()
        assert arrival is not None
        robot.handle_frame(arrival)
        if profiler is not None and measured:
            profiler.disable()
        cpu, proc, wall = time.thread_time() - cpu0, time.process_time() - proc0, time.perf_counter() - wall0
        if not got.wait(TWIST_WAIT_S):
            raise SystemExit(f"frame {k}: no twist")
        status = robot._last_status
        assert status is not None
        rows.append({"measured": measured, "cpu_ms": cpu * 1e3, "process_cpu_ms": proc * 1e3, "wall_ms": wall * 1e3,
                     "launches": launches.count - n0, "iterations": status.iterations, "state": status.state,
                     "stages_ms": status.latency_ms.model_dump(), "G": robot.pipeline.G.reshape(-1).tolist(),
                     "twist": twist.tolist()})
        pose = pose @ se3_exp(np.array(twist) / RATE_HZ)
    sub.undeclare()
    pub.undeclare()
    if profiler is not None and profile is not None:
        profiler.dump_stats(str(profile))
    return {"rows": rows, "final_offset_mm": float(np.linalg.norm(pose[:3, 3]) * 1e3)}


def summary(result: dict[str, Any]) -> dict[str, Any]:
    rows = [r for r in result["rows"] if r["measured"]]

    def stats(values: list[float]) -> dict[str, float]:
        a = np.array(values)
        return {"mean": round(float(a.mean()), 3), "median": round(float(np.median(a)), 3),
                "p90": round(float(np.percentile(a, 90)), 3)}

    stages = {name: stats([r["stages_ms"][name] for r in rows]) for name in ("decode", "registration", "control",
                                                                            "publish")}
    return {"frames": len(rows), "cpu_ms": stats([r["cpu_ms"] for r in rows]),
            "process_cpu_ms": stats([r["process_cpu_ms"] for r in rows]),
            "wall_ms": stats([r["wall_ms"] for r in rows]), "launches": stats([r["launches"] for r in rows]),
            "iterations": stats([r["iterations"] for r in rows]), "stages_ms": stages,
            "states": sorted({r["state"] for r in rows}), "final_offset_mm": round(result["final_offset_mm"], 3),
            "load_average": [round(x, 2) for x in os.getloadavg()]}


def servoed(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The frames from the first non-zero twist on: the first frame is answered untracked (zero twist, the plant
    holds still) until the background global initialiser's pose is adopted, after a number of frames that depends
    on thread timing; from there on the lockstep sequence is deterministic."""
    first = next((k for k, r in enumerate(rows) if any(r["twist"])), len(rows))
    return rows[first:]


def compare(a: Path, b: Path) -> None:
    ra, rb = (servoed(json.loads(p.read_text())["rows"]) for p in (a, b))
    n = min(len(ra), len(rb))
    G = np.abs(np.array([r["G"] for r in ra[:n]]) - np.array([r["G"] for r in rb[:n]]))
    tw = np.abs(np.array([r["twist"] for r in ra[:n]]) - np.array([r["twist"] for r in rb[:n]]))
    same = sum(r["G"] == s["G"] for r, s in zip(ra[:n], rb[:n], strict=True))
    print(json.dumps({"frames": n, "bit_identical_G": same, "max_abs_diff_G": float(G.max()),
                      "max_abs_diff_twist": float(tw.max()),
                      "iterations_differ": sum(r["iterations"] != s["iterations"]
                                               for r, s in zip(ra[:n], rb[:n], strict=True))}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--warm-up", type=int, default=30)
    parser.add_argument("--profile", type=Path, help="cProfile the measured frames into this file")
    parser.add_argument("--estimates", type=Path, help="write every measured frame's figures here (JSON)")
    parser.add_argument("--compare", type=Path, nargs=2, metavar=("A", "B"))
    args = parser.parse_args()
    if args.compare:
        compare(*args.compare)
        return
    result = run(args.frames, args.warm_up, args.profile)
    print(json.dumps(summary(result)))
    if args.estimates:
        args.estimates.write_text(json.dumps(result))
    if args.profile:
        pstats.Stats(str(args.profile)).sort_stats("tottime").print_stats(30)


if __name__ == "__main__":
    main()
