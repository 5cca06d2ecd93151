"""Start-up of the servo service after a restart: process start → alive → first twist (issue 21).

A service that was servoing is restarted while a camera publishes at 30 Hz (this process, stamps = wall clock):
`alive` is the first reply to `get_state`, `first answer` the first twist answering a frame (a zero one while the
service is still re-acquiring counts), `first twist` the first non-zero one (the servo moving again), all measured
from the moment the process was spawned, with the Taichi offline cache warm (one run beforehand fills it). This process
listens and the service connects to it as it opens its session, so no reconnection period of Zenoh's is measured.
The warm-up (the default) compiles the configuration's kernels before the service declares itself alive;
`--no-warmup` leaves them to the first frame. The warm-up's own time is read from the service's log. Besides wall
time each row gives the service process's CPU time (all threads, `/proc/PID/stat`) when it answered alive and right
after its first twist: on a shared host the wall time grows with the load, the CPU time much less.

`--phases N` adds N in-process breakdowns of the same restart up to the end of the warm-up
(`benchmarks/startup_phases.py`: imports, `ti.init`, robots, the warm-up's Taichi front end and the rest), each a
fresh process on the same warm cache: median and range of wall and CPU time per phase.

    .venv/bin/python benchmarks/bench_startup.py [--runs 3] [--phases 0] [--gain-grid 1 1] [--model planar]
        [--markdown]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_service import F, H, W, command, frame_at, free_port, scene  # noqa: E402
from benchmarks.rows import print_rows  # noqa: E402
from ddvs_service.protocol import (  # noqa: E402
    Header,
    Keys,
    SessionConfig,
    Time,
    declare_publisher,
    decode_twist_stamped,
    encode_image,
    image_from_array,
    open_session,
)
from ddvs_service.protocol.upload import encode_upload  # noqa: E402

KEYS = Keys("ddvs", "boot")


def spawn(config: Path, *args: str) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if not k.startswith("DDVS_ZENOH_")}
    return subprocess.Popen([sys.executable, "-m", "ddvs.cli", "serve", "--config", str(config), *args],
                            env=env, cwd=ROOT, stderr=subprocess.PIPE, text=True)


def stop(service: subprocess.Popen) -> str:
    service.send_signal(signal.SIGTERM)
    _, stderr = service.communicate(timeout=60)
    return stderr


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process `pid` so far (all its threads)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def warm_up_seconds(log: str) -> float | None:
    for line in log.splitlines():
        if line.startswith("{") and json.loads(line).get("msg") == "kernels warmed up":
            return float(json.loads(line)["seconds"])
    return None


def prepare(config: Path, port: int) -> None:
    """A first run: upload the reference and start the servo, so that the state directory resumes SERVOING (this
    run also fills Taichi's offline cache)."""
    service = spawn(config)
    with open_session(SessionConfig(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        wait_alive(session, time.monotonic() + 300)
        assert command(session, KEYS, op="set_reference", source="upload",
                       image={"format": "png", "data": encode_upload(scene())}).ok
        assert command(session, KEYS, op="start").ok
        time.sleep(1.0)
    stop(service)


def wait_alive(session, deadline: float) -> float:
    while True:
        try:
            command(session, KEYS, op="get_state")
            return time.monotonic()
        except Exception:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.02)


def restart(config: Path, port: int, warmup: bool) -> dict:
    frames = [frame_at(scene(), k) for k in range(90)]
    first_answer: list[float] = []
    first_twist: list[float] = []
    with open_session(SessionConfig(listen=[f"tcp/127.0.0.1:{port}"])) as session:

        def on_twist(sample) -> None:  # a twist answering a frame carries its wall-clock stamp (a watchdog's zero: 0)
            twist = decode_twist_stamped(sample.payload.to_bytes())
            if twist.header.stamp.to_ns() < t_frames:
                return
            if not first_answer:
                first_answer.append(time.monotonic())
            if not first_twist and (np.any(twist.linear != 0.0) or np.any(twist.angular != 0.0)):
                first_twist.append(time.monotonic())

        t_frames = time.time_ns()
        sub = session.declare_subscriber(KEYS.key("servo_twist"), on_twist)
        pub = declare_publisher(session, KEYS, "camera_image")
        done = threading.Event()

        def camera() -> None:
            k = 0
            while not done.is_set():
                stamp = Header(Time.from_ns(time.time_ns()), "camera")
                pub.put(encode_image(image_from_array(frames[k % 90], "mono8", stamp)))
                k += 1
                time.sleep(1 / 30)

        thread = threading.Thread(target=camera)
        thread.start()
        t0 = time.monotonic()
        service = spawn(config, *(() if warmup else ("--no-warmup",)))
        try:
            alive = wait_alive(session, t0 + 300) - t0
            cpu_alive = cpu_seconds(service.pid)
            deadline = time.monotonic() + 300
            while not first_twist and time.monotonic() < deadline:
                time.sleep(0.005)
            cpu_twist = cpu_seconds(service.pid)
        finally:
            done.set()
            thread.join()
            log = stop(service)
            sub.undeclare()
            pub.undeclare()
    return {"warmup": warmup, "alive_s": round(alive, 3), "first_answer_s": round(first_answer[0] - t0, 3),
            "first_twist_s": round(first_twist[0] - t0, 3),
            "cpu_alive_s": round(cpu_alive, 2), "cpu_first_twist_s": round(cpu_twist, 2),
            "warm_up_s": warm_up_seconds(log), "load_average": round(os.getloadavg()[0], 2)}


def phases(config: Path, runs: int) -> list[dict]:
    """`runs` breakdowns (`startup_phases`), one row per phase: wall and CPU seconds of each run."""
    per_run = []
    for _ in range(runs):
        spawned_at = time.monotonic()
        done = subprocess.run([sys.executable, "-m", "benchmarks.startup_phases", str(spawned_at), str(config)],
                              cwd=ROOT, capture_output=True, text=True, check=True)
        per_run.append(json.loads(done.stdout.strip().splitlines()[-1])["phases"])
    rows = [{"phase": p["phase"], "wall_s": [run[i]["wall_s"] for run in per_run],
             "cpu_s": [run[i]["cpu_s"] for run in per_run]} for i, p in enumerate(per_run[0])]
    rows.append({"phase": "total", "wall_s": [sum(p["wall_s"] for p in run) for run in per_run],
                 "cpu_s": [sum(p["cpu_s"] for p in run) for run in per_run]})
    return rows


def spread(values: list[float]) -> str:
    return f"{np.median(values):.2f} s ({min(values):.2f}–{max(values):.2f})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--gain-grid", type=int, nargs=2, default=[1, 1], metavar=("ROWS", "COLS"))
    parser.add_argument("--model", choices=["planar", "general"], default="planar")
    parser.add_argument("--phases", type=int, default=0, metavar="N", help="N in-process breakdowns as well")
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    port = free_port()
    state = tempfile.mkdtemp(prefix="ddvs-boot-")
    config = Path(state) / "serve.json"
    config.write_text(json.dumps({
        "robot": "boot", "state_dir": state, "zenoh": {"connect": [f"tcp/127.0.0.1:{port}"]},
        "intrinsics": {"fx": F, "fy": F, "cx": (W - 1) / 2, "cy": (H - 1) / 2, "width": W, "height": H},
        "registration": {"template_size": [200, 150], "gain_grid": args.gain_grid, "model": args.model},
    }))
    prepare(config, port)
    if args.phases:
        load = os.getloadavg()[0]
        print_rows(phases(config, args.phases), args.markdown,
                   ["phase", "wall: median (range)", "CPU: median (range)"],
                   lambda r: [r["phase"], spread(r["wall_s"]), spread(r["cpu_s"])])
        print(f"\n{args.phases} runs, load {load:.2f} before, {os.getloadavg()[0]:.2f} after\n")
    rows = [restart(config, port, warmup) for _ in range(args.runs) for warmup in (True, False)]
    print_rows(rows, args.markdown,
               ["warm-up", "process start → alive: wall / CPU", "→ first answer", "→ first non-zero twist: wall / CPU",
                "warm-up itself", "load"],
               lambda r: ["yes" if r["warmup"] else "no", f"{r['alive_s']:.2f} s / {r['cpu_alive_s']:.2f} s",
                          f"{r['first_answer_s']:.2f} s",
                          f"{r['first_twist_s']:.2f} s / {r['cpu_first_twist_s']:.2f} s",
                          f"{r['warm_up_s'] or 0:.2f} s", f"{r['load_average']:.2f}"])


if __name__ == "__main__":
    main()
