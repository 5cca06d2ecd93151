"""Start-up of the servo service after a restart: process start → alive → first twist (issue 21).

A service that was servoing is restarted while a camera publishes at 30 Hz (this process, stamps = wall clock):
`alive` is the first reply to `get_state`, `first answer` the first twist answering a frame (a zero one while the
service is still re-acquiring counts), `first twist` the first non-zero one (the servo moving again), all measured
from the moment the process was spawned, with the Taichi offline cache warm (one run beforehand fills it). That
first run tracks the camera until the servo moves, so each restart resumes from a persisted last good estimate, and
the camera's view goes on where the last run stopped (the arm stays still while the service is down). This process
listens and the service connects to it as it opens its session, so no reconnection period of Zenoh's is measured.
The warm-up (the default) compiles the configuration's kernels before the service declares itself alive;
`--no-warmup` leaves them to the first frame. The warm-up's own time is read from the service's log. Besides wall
time each row gives the service process's CPU time (all threads, `/proc/PID/stat`) when it answered alive and right
after its first twist: on a shared host the wall time grows with the load, the CPU time much less.

`--phases N` adds N in-process breakdowns of the same restart up to the end of the warm-up
(`benchmarks/startup_phases.py`: imports, `ti.init`, robots, the warm-up's Taichi front end and the rest), each a
fresh process on the same warm cache: median and range of wall and CPU time per phase.

`--jump N` adds N restarts whose camera, once the servo moves, jumps twice to a view only the global initialiser
finds (the scene turned by `JUMP_DEG`, then back): the loop's longest pause between two answers until the servo
moves again, and how long that took. A servo resumed from its estimate compiles the initialiser's kernels at the
first of those searches (`service.startup.needs_initialiser`).

    .venv/bin/python benchmarks/bench_startup.py [--runs 3] [--phases 0] [--jump 0] [--gain-grid 1 1]
        [--model planar] [--markdown]
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

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_service import H, W, bench_config, command, frame_at, free_port, scene  # noqa: E402
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
JUMP_DEG = 25.0  # the view after a jump: the scene turned by this much (degrees)


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


class Camera:
    """A 30 Hz camera on `session` (stamps = wall clock) whose view moves in a small circle (`frame_at`), on its
    own thread between `start` and `stop`. The view goes on from where the last `stop` left it: the arm does not move
    while the service is down (its bridge's watchdog stops it), so a restarted service sees what it last saw."""

    def __init__(self) -> None:
        self.views = [[frame_at(view, k) for k in range(90)] for view in (scene(), turned(scene(), JUMP_DEG))]
        self.frames = self.views[0]
        self.k = 0
        self._done = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, session) -> None:
        pub = declare_publisher(session, KEYS, "camera_image")
        self._done.clear()

        def run() -> None:
            while not self._done.is_set():
                stamp = Header(Time.from_ns(time.time_ns()), "camera")
                pub.put(encode_image(image_from_array(self.frames[self.k % 90], "mono8", stamp)))
                self.k += 1
                time.sleep(1 / 30)
            pub.undeclare()

        self._thread = threading.Thread(target=run)
        self._thread.start()

    def jump(self) -> None:
        """Show the other view (the scene turned by `JUMP_DEG` from this one): more than tracking follows."""
        self.frames = self.views[1] if self.frames is self.views[0] else self.views[0]

    def stop(self) -> None:
        self._done.set()
        if self._thread is not None:
            self._thread.join()


def turned(image: np.ndarray, degrees: float) -> np.ndarray:
    A = cv2.getRotationMatrix2D(((W - 1) / 2, (H - 1) / 2), degrees, 1.0)
    return cv2.warpAffine(image, A, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def prepare(config: Path, port: int, camera: Camera) -> None:
    """A first run: upload the reference, start the servo and serve the camera until it moves, so that the state
    directory resumes SERVOING from a last good estimate, as a servo stopped while it works does (this run also
    fills Taichi's offline cache)."""
    service = spawn(config)
    with open_session(SessionConfig(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        wait_alive(session, time.monotonic() + 300)
        assert command(session, KEYS, op="set_reference", source="upload",
                       image={"format": "png", "data": encode_upload(scene())}).ok
        assert command(session, KEYS, op="start").ok
        moving = threading.Event()

        def on_twist(sample) -> None:
            twist = decode_twist_stamped(sample.payload.to_bytes())
            if np.any(twist.linear != 0.0) or np.any(twist.angular != 0.0):
                moving.set()

        sub = session.declare_subscriber(KEYS.key("servo_twist"), on_twist)
        camera.start(session)
        try:
            assert moving.wait(300), "the prepared servo never moved"
            time.sleep(0.5)
        finally:
            camera.stop()
            sub.undeclare()
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


def restart(config: Path, port: int, warmup: bool, camera: Camera) -> dict:
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
        camera.start(session)
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
            log = stop(service)  # the camera runs until the service stopped: what it last saw is where it resumes
            camera.stop()
            sub.undeclare()
    return {"warmup": warmup, "alive_s": round(alive, 3), "first_answer_s": round(first_answer[0] - t0, 3),
            "first_twist_s": round(first_twist[0] - t0, 3),
            "cpu_alive_s": round(cpu_alive, 2), "cpu_first_twist_s": round(cpu_twist, 2),
            "warm_up_s": warm_up_seconds(log), "load_average": round(os.getloadavg()[0], 2)}


def jump(config: Path, port: int, camera: Camera) -> dict:
    """A restart with the warm-up; once the servo moves, the camera jumps to the other view, which only the global
    initialiser finds: how long the loop's longest pause between two answers was from the jump until the servo
    moved again (a resumed servo compiles the initialiser's kernels there, holding the GIL), and how long that
    re-acquisition took."""
    answers: list[tuple[float, bool]] = []  # arrival, non-zero
    messages: list[str] = []
    with open_session(SessionConfig(listen=[f"tcp/127.0.0.1:{port}"])) as session:

        def on_twist(sample) -> None:
            twist = decode_twist_stamped(sample.payload.to_bytes())
            if twist.header.stamp.to_ns() >= t_frames:
                answers.append((time.monotonic(), bool(np.any(twist.linear != 0.0) or np.any(twist.angular != 0.0))))

        def on_status(sample) -> None:
            messages.append(json.loads(sample.payload.to_bytes()).get("message", ""))

        t_frames = time.time_ns()
        subs = [session.declare_subscriber(KEYS.key("servo_twist"), on_twist),
                session.declare_subscriber(KEYS.key("servo_status"), on_status)]
        camera.start(session)
        service = spawn(config)
        try:
            deadline = time.monotonic() + 300
            while not any(moving for _, moving in answers) and time.monotonic() < deadline:
                time.sleep(0.005)
            searches = [search_after_jump(camera, answers, messages, deadline) for _ in range(2)]
        finally:
            log = stop(service)
            camera.stop()
            for sub in subs:
                sub.undeclare()
    return {"searches": searches, "initialiser_warmed_up": '"initialiser": true' in log,
            "load_average": round(os.getloadavg()[0], 2)}


def search_after_jump(camera: Camera, answers: list[tuple[float, bool]], messages: list[str],
                      deadline: float) -> dict:
    """Jump the camera to the other view and wait until the servo moves again (its first 0.2 s of answers are
    still the old view's); the longest pause between answers meanwhile, the time it took, whether the initialiser
    found the view."""
    camera.jump()
    t_jump, n_messages = time.monotonic(), len(messages)
    while time.monotonic() < deadline and not any(moving for t, moving in answers if t > t_jump + 0.2):
        time.sleep(0.005)
    moved = next(t for t, moving in answers if moving and t > t_jump + 0.2)
    gaps = np.diff([t_jump, *[t for t, _ in answers if t_jump < t <= moved]])
    return {"longest_pause_s": round(float(gaps.max()), 3), "reacquired_s": round(moved - t_jump, 3),
            "initialiser": any("global initialisation: ok" in m for m in messages[n_messages:])}


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
    parser.add_argument("--jump", type=int, default=0, metavar="N",
                        help="N restarts whose camera then jumps to a view only the initialiser finds")
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    port = free_port()
    state = tempfile.mkdtemp(prefix="ddvs-boot-")
    config = Path(state) / "serve.json"
    base = bench_config(robot="boot", state_dir=Path(state), zenoh=SessionConfig(connect=[f"tcp/127.0.0.1:{port}"]))
    config.write_text(base.merged({"registration": {"gain_grid": args.gain_grid, "model": args.model}})
                      .model_dump_json())
    camera = Camera()
    prepare(config, port, camera)
    if args.phases:
        load = os.getloadavg()[0]
        print_rows(phases(config, args.phases), args.markdown,
                   ["phase", "wall: median (range)", "CPU: median (range)"],
                   lambda r: [r["phase"], spread(r["wall_s"]), spread(r["cpu_s"])])
        print(f"\n{args.phases} runs, load {load:.2f} before, {os.getloadavg()[0]:.2f} after\n")
    rows = [restart(config, port, warmup, camera) for _ in range(args.runs) for warmup in (True, False)]
    print_rows(rows, args.markdown,
               ["warm-up", "process start → alive: wall / CPU", "→ first answer", "→ first non-zero twist: wall / CPU",
                "warm-up itself", "load"],
               lambda r: ["yes" if r["warmup"] else "no", f"{r['alive_s']:.2f} s / {r['cpu_alive_s']:.2f} s",
                          f"{r['first_answer_s']:.2f} s",
                          f"{r['first_twist_s']:.2f} s / {r['cpu_first_twist_s']:.2f} s",
                          f"{r['warm_up_s'] or 0:.2f} s", f"{r['load_average']:.2f}"])
    if args.jump:
        print()
        print_rows([jump(config, port, camera) for _ in range(args.jump)], args.markdown,
                   ["initialiser warmed up at start", "found by the initialiser: 1st / 2nd jump",
                    "longest pause between answers: 1st / 2nd", "jump → moving again: 1st / 2nd", "load"],
                   lambda r: ["yes" if r["initialiser_warmed_up"] else "no",
                              " / ".join("yes" if s["initialiser"] else "no" for s in r["searches"]),
                              " / ".join(f"{s['longest_pause_s']:.2f} s" for s in r["searches"]),
                              " / ".join(f"{s['reacquired_s']:.2f} s" for s in r["searches"]),
                              f"{r['load_average']:.2f}"])


if __name__ == "__main__":
    main()
