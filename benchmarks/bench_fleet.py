"""Many robots at 30 Hz on one host: one `ddvs serve` process serving N robots against N processes (issue 21).

Each robot has a plant of its own in a separate process (this script with `--publish`): a camera in front of a
textured plane (`sim.planar_scene.PlanarScene`, the shipped "boat" poster 0.7 m ahead, 320×240, f = 420 px) whose
pose integrates the servo's twists (`T_ref_cur ← T_ref_cur · exp(ξ dt)`, the twist last received, dt = 1/30 s per
period),
rendered by `cv2.warpPerspective` and published at 30 Hz in real time (an absolute schedule; each frame stamped with
the wall clock before it is encoded and put; a plant the host ran too late for a frame skips it, as a camera drops
frames, and the row counts them: `skipped`). It uploads the goal image as the reference, starts the servo from a
random pose (±20 mm, ±1.7° per axis, seeded per robot) and closes the loop, so every frame is a new view the
registration must track. Latency = twist arrival (the plant's wall clock) − its frame's stamp; a frame is
answered when its twist arrived (a twist withheld as stale, or a frame dropped because a newer one came, is not).

Modes: `shared` — one `ddvs serve --robots r0 … rN-1`; `separate` — N `ddvs serve --robot ri` processes (today's
deployment). Every plant warms up (its robot answered 30 frames) before a common measuring window of `--seconds`
starts; over that window the parent reads each service process's CPU time (`/proc/<pid>/stat`, user + system,
as % of one core) and, at its end, its resident memory (VmRSS), and asks each for its robots' counters at both
ends (`list_robots`; `service_counters`: frames received, taken by the loop, registered, superseded in the inbox —
`dropped` —, stale, rejected). The load average is printed with every row, and
how many robots publish within 5 ms of one another (`crowd`: each plant keeps its own 30 Hz schedule, so the phases
its start gave it hold for the whole run, and the frames that meet there wait for each other once every period).
`--trace`: the plants also read their robots' status and the row says what became of each frame not answered
(`missed`, `missed_kinds`: superseded in the inbox, twist withheld as stale, lost before the service, twist lost)
and where the answered frames' time went (`parts_ms_mean`: outside the service, queued in its inbox, its work, and
the service's CPU time over that work).

    .venv/bin/python benchmarks/bench_fleet.py [--robots 1 2 4 8 16] [--modes shared separate] [--seconds 30]
                                               [--service-shm on|off] [--realtime-priority P] [--trace]
                                               [--markdown] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_service import bench_config  # noqa: E402
from benchmarks.rows import print_rows  # noqa: E402
from ddvs_service.camera import Intrinsics  # noqa: E402 - after the path set-up for running as a script
from ddvs_service.lie import se3_exp, so3_exp  # noqa: E402
from ddvs_service.protocol import (  # noqa: E402
    Command,
    Header,
    Keys,
    Reply,
    SessionConfig,
    Time,
    declare_publisher,
    decode_twist_stamped,
    dump,
    encode_image,
    image_from_array,
    open_session,
)
from ddvs_service.protocol.control import process_command_key  # noqa: E402
from ddvs_service.protocol.upload import encode_upload  # noqa: E402
from sim.planar_scene import POSTER_BLUR_SIGMA, PlanarScene  # noqa: E402
from sim.textures import load_texture  # noqa: E402

W, H, F = 320, 240, 420.0
CAMERA = Intrinsics(F, F, (W - 1) / 2, (H - 1) / 2, W, H)
RATE_HZ = 30.0
WARM_UP_FRAMES = 30
SLOW_MS = 10.0  # `trace`: answered frames slower than this are decomposed
CROWD_WINDOW_MS = 5.0  # `crowd`: about two frames' service on the loop thread
READY_LIMIT_S = 600.0  # 16 separate services start one Taichi each on 2 shared cores


# --- the plant process ------------------------------------------------------------------------------------------
def command(session: Any, keys: Keys, timeout: float = 30.0, **kwargs: object) -> Reply:
    for reply in session.get(keys.key("servo_command"), payload=dump(Command(**kwargs)), timeout=timeout):
        if reply.ok is None:
            raise RuntimeError(f"{keys.robot}: the service answered with a Zenoh error")
        return Reply.model_validate_json(reply.ok.payload.to_bytes())
    raise RuntimeError(f"{keys.robot}: the service did not answer")


def plant_scene() -> PlanarScene:
    """The plants' scene: the shipped "boat" poster 0.7 m ahead of the camera."""
    return PlanarScene(CAMERA, load_texture("boat", POSTER_BLUR_SIGMA), depth=0.7)


def start_pose(seed: int) -> np.ndarray:
    """A plant's random start (4×4, camera in the reference frame): ±1.7° about each axis, ±20 mm along each."""
    rng = np.random.default_rng(seed)
    pose = np.eye(4)
    pose[:3, :3] = so3_exp(rng.uniform(-0.03, 0.03, 3))
    pose[:3, 3] = rng.uniform(-0.02, 0.02, 3)
    return pose


def publish(robot: str, port: int, seed: int, trace: bool) -> None:
    """Plant process of `robot`: uploads the reference, starts the servo, closes the loop at 30 Hz; prints `ready`
    after the warm-up, reads `T0 SECONDS` (wall clock, s) from stdin, prints its figures as JSON after the window.
    `trace`: also subscribe to the robot's status and say what became of each frame (`frame_trace`)."""
    scene = plant_scene()
    keys = Keys("ddvs", robot)
    session = open_session(SessionConfig(connect=[f"tcp/127.0.0.1:{port}"]))
    lock = threading.Lock()
    arrivals: dict[int, int] = {}  # frame stamp (ns) -> twist arrival (ns)
    statuses: dict[int, dict[str, Any]] = {}  # frame stamp (ns) -> what the service's status said of it
    twist = np.zeros(6)

    def on_twist(sample: Any) -> None:
        nonlocal twist
        arrival = time.time_ns()
        msg = decode_twist_stamped(sample.payload.to_bytes())
        with lock:
            arrivals[msg.header.stamp.to_ns()] = arrival
            twist = msg.vector

    def on_status(sample: Any) -> None:
        status = json.loads(sample.payload.to_bytes())
        with lock:
            statuses[status["frame_stamp_ns"]] = {"message": status["message"], "counters": status["counters"],
                                                  "latency_ms": status["latency_ms"]}

    pub = declare_publisher(session, keys, "camera_image")
    sub = session.declare_subscriber(keys.key("servo_twist"), on_twist)
    status_sub = session.declare_subscriber(keys.key("servo_status"), on_status) if trace else None
    try:
        deadline = time.monotonic() + READY_LIMIT_S
        while True:
            try:
                command(session, keys, timeout=2.0, op="get_state")
                break
            except RuntimeError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        goal = np.clip(scene.render(), 0, 255).astype(np.uint8)
        reply = command(session, keys, op="set_reference", source="upload",
                        image={"format": "png", "data": encode_upload(goal)})
        if not reply.ok:
            raise SystemExit(f"{robot}: reference refused: {reply.error}")
        if not command(session, keys, op="start").ok:
            raise SystemExit(f"{robot}: start refused")
        pose = start_pose(seed)
        window: list[float] = []  # [T0, T1] once told
        threading.Thread(target=lambda: window.extend(map(float, sys.stdin.readline().split())), daemon=True).start()
        stamps: list[int] = []
        ready = False
        skipped_stamps: list[int] = []  # when the plant skipped a frame it was too late for (wall clock, ns)
        t0, k, periods = time.perf_counter(), 0, 1
        while not window or time.time() < window[0] + window[1] + 0.5:
            with lock:
                applied = twist.copy()
            pose = pose @ se3_exp(applied * periods / RATE_HZ)
            image = scene.render(scene.homography(pose[:3, :3], pose[:3, 3]))
            frame = np.clip(image, 0, 255).astype(np.uint8)
            stamp = time.time_ns()
            pub.put(encode_image(image_from_array(frame, "mono8", Header(Time.from_ns(stamp), "camera"))))
            stamps.append(stamp)
            if not ready:
                with lock:
                    answered = len(arrivals)
                if answered >= WARM_UP_FRAMES:
                    ready = True
                    print("ready", flush=True)
                elif time.perf_counter() - t0 > READY_LIMIT_S:
                    raise SystemExit(f"{robot}: fewer than {WARM_UP_FRAMES} frames answered in {READY_LIMIT_S} s")
            periods = next_slot(t0, k, time.perf_counter()) - k
            skipped_stamps.extend([time.time_ns()] * (periods - 1))
            k += periods
            time.sleep(max(0.0, t0 + k / RATE_HZ - time.perf_counter()))
        time.sleep(0.3)  # the last twists
        start_ns, end_ns = int(window[0] * 1e9), int((window[0] + window[1]) * 1e9)
        measured = [s for s in stamps if start_ns <= s < end_ns]
        with lock:
            latencies = [(arrivals[s] - s) / 1e6 for s in measured if s in arrivals]
            traced = frame_trace(stamps, measured, arrivals, statuses) if trace else {}
        angles = 2.0 * np.pi * RATE_HZ * (np.array(measured, dtype=np.int64) % 10**9) / 1e9
        phase_ms = float(np.angle(np.exp(1j * angles).mean()) % (2.0 * np.pi) / (2.0 * np.pi) * 1e3 / RATE_HZ)
        print(json.dumps({"robot": robot, "published": len(measured), "answered": len(latencies),
                          "skipped": sum(start_ns <= s < end_ns for s in skipped_stamps),
                          "latency_ms": latencies, "final_offset_mm": float(np.linalg.norm(pose[:3, 3]) * 1e3),
                          "phase_ms": phase_ms, **traced}), flush=True)
    finally:
        if status_sub is not None:
            status_sub.undeclare()
        sub.undeclare()
        pub.undeclare()
        session.close()


def next_slot(t0: float, k: int, now: float) -> int:
    """The plant's next frame after frame `k` on its 30 Hz grid from `t0` (`time.perf_counter()` s): `k + 1`, unless
    the plant is so late (the host did not run it) that frame `k + 1` would follow frame `k` by less than half a
    period: such frames are skipped, as a camera drops the frames its driver was late for, instead of catching up
    with frames a few ms apart (each of which would supersede the one before it in the service's inbox)."""
    slot = k + 1
    while t0 + slot / RATE_HZ < now + 0.5 / RATE_HZ:
        slot += 1
    return slot


def frame_trace(stamps: list[int], measured: list[int], arrivals: dict[int, int],
                statuses: dict[int, dict[str, Any]]) -> dict[str, Any]:
    """What became of each measured frame whose twist did not arrive, from the service's own status of every frame
    it processed (`frame_stamp_ns`, `message`, `counters`): `stale` (processed, twist withheld: its message says
    so), `twist_lost` (processed, not stale, yet no twist arrived), `superseded` (never processed, and the service's
    `dropped` counter grew between the processed frames around it: a newer frame replaced it in the inbox), `lost`
    (never processed and not counted dropped: it did not reach the service's inbox — or the statuses around it
    were lost, which the status key's congestion control allows). And `parts_ms`, where the time of every answered
    frame went (`split_latency`)."""
    index = {s: k for k, s in enumerate(stamps)}
    missed = []
    for s in measured:
        if s in arrivals:
            continue
        k = index[s]
        before = next((statuses[t] for t in reversed(stamps[:k]) if t in statuses), None)
        after = next((statuses[t] for t in stamps[k + 1:] if t in statuses), None)
        if s in statuses:
            kind = "stale" if statuses[s]["message"].startswith("stale") else "twist_lost"
        elif before is not None and after is not None and (after["counters"]["dropped"]
                                                            > before["counters"]["dropped"]):
            kind = "superseded"
        else:
            kind = "lost"
        neighbours = [round((arrivals[t] - t) / 1e6, 1) if t in arrivals else None
                      for t in stamps[max(k - 2, 0):k + 3]]
        following = stamps[k + 1] if k + 1 < len(stamps) else s
        missed.append({"frame": k, "kind": kind, "t_s": round((s - measured[0]) / 1e9, 3),
                       "next_frame_after_ms": round((following - s) / 1e6, 1),
                       "latency_ms_around": neighbours,
                       "service_total_ms": statuses[s]["latency_ms"]["total"] if s in statuses else None})
    parts = [split_latency((arrivals[s] - s) / 1e6, statuses[s]["latency_ms"]) for s in measured
             if s in arrivals and s in statuses]
    return {"missed": missed, "parts_ms": parts, "statuses": sum(s in statuses for s in measured)}


def split_latency(latency_ms: float, service: dict[str, float]) -> list[float]:
    """A frame's latency in four parts (ms): `outside` (its stamp → the service's callback, and twist out → the
    plant's callback: transport and the two processes' wake-ups), `queued` (in the service's inbox: behind other
    robots' frames, and the loop's hand-off), `work` (decode, registration, control, twist out) and the latency;
    then `work_cpu`, the service process's CPU time over that work (`Latency.cpu`: a `work` much longer is time the
    host ran other processes instead of the service)."""
    work = service["decode"] + service["registration"] + service["control"] + service["publish"]
    return [round(latency_ms - service["total"], 3), round(service["total"] - work, 3), round(work, 3),
            round(latency_ms, 3), round(service.get("cpu", float("nan")), 3)]


# --- the measuring parent ---------------------------------------------------------------------------------------
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def cpu_seconds(pid: int) -> float:
    fields_after_name = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields_after_name[11]) + int(fields_after_name[12])) / os.sysconf("SC_CLK_TCK")


def memory_mb(pid: int) -> dict[str, float]:
    """Memory of a process (MB): `rss` resident in all; `shmem`, the part in shared memory (Zenoh's shared-memory
    pools of the publishers, mapped for zero-copy frames, also resident in the publishers); `pss`, the proportional
    share (each shared page divided among the processes mapping it)."""
    values = {}
    for path in (f"/proc/{pid}/status", f"/proc/{pid}/smaps_rollup"):
        for line in Path(path).read_text().splitlines():
            name, _, rest = line.partition(":")
            if name in ("VmRSS", "RssShmem", "Pss"):
                values[name] = int(rest.split()[0]) / 1024
    return {"rss": values["VmRSS"], "shmem": values["RssShmem"], "pss": values["Pss"]}


def start_services(mode: str, robots: list[str], workdir: Path,
                   shm: bool) -> tuple[list[subprocess.Popen], dict[str, int]]:
    """The service process(es) and each robot's port; `shm`: the services' Zenoh shared memory (the default)."""
    config = workdir / "serve.json"
    config.write_text(bench_config(zenoh=SessionConfig(shm=shm)).model_dump_json())
    env = {k: v for k, v in os.environ.items() if not k.startswith("DDVS_ZENOH_")}
    common = [sys.executable, "-m", "ddvs.cli", "serve", "--config", str(config), "--log-level", "ERROR"]
    if mode == "shared":
        port = free_port()
        proc = subprocess.Popen([*common, "--robots", *robots, "--state-dir", str(workdir / "state"),
                                 "--listen", f"tcp/127.0.0.1:{port}"], cwd=ROOT, env=env, stdout=subprocess.DEVNULL)
        return [proc], {r: port for r in robots}
    procs, ports = [], {}
    for r in robots:
        ports[r] = free_port()
        procs.append(subprocess.Popen([*common, "--robot", r, "--state-dir", str(workdir / r),
                                       "--listen", f"tcp/127.0.0.1:{ports[r]}"], cwd=ROOT, env=env,
                                      stdout=subprocess.DEVNULL))
    return procs, ports


def measure(mode: str, n: int, seconds: float, shm: bool, trace: bool) -> dict[str, Any]:
    robots = [f"r{i}" for i in range(n)]
    with tempfile.TemporaryDirectory(prefix="ddvs-fleet-") as tmp:
        services, ports = start_services(mode, robots, Path(tmp), shm)
        flags = ["--trace"] if trace else []
        plants = [subprocess.Popen([sys.executable, __file__, "--publish", r, "--port", str(ports[r]),
                                    "--seed", str(i), *flags], cwd=ROOT, stdin=subprocess.PIPE,
                                   stdout=subprocess.PIPE, text=True) for i, r in enumerate(robots)]
        try:
            t_start = time.monotonic()
            for plant in plants:
                assert plant.stdout is not None
                line = plant.stdout.readline()
                if line.strip() != "ready":
                    raise SystemExit(f"a plant failed before its warm-up ended ({mode}, N={n})")
            ready_s = time.monotonic() - t_start
            t0 = time.time() + 1.0
            for plant in plants:
                assert plant.stdin is not None
                plant.stdin.write(f"{t0} {seconds}\n")
                plant.stdin.flush()
            listing = open_session(SessionConfig(connect=[f"tcp/127.0.0.1:{p}" for p in sorted(set(ports.values()))]))
            processes = robots[:1] if mode == "shared" else robots  # a process is named after its first robot
            try:
                time.sleep(max(0.0, t0 - time.time()))
                cpu0, load0 = [cpu_seconds(p.pid) for p in services], os.getloadavg()
                counted0 = service_counters(listing, processes)
                time.sleep(seconds)
                cpu1, load1 = [cpu_seconds(p.pid) for p in services], os.getloadavg()
                counted1 = service_counters(listing, processes)
            finally:
                listing.close()
            memory = [memory_mb(p.pid) for p in services]
            results = []
            for plant in plants:
                out, _ = plant.communicate(timeout=120)
                results.append(json.loads(out.strip().splitlines()[-1]))
        finally:
            for proc in [*plants, *services]:
                if proc.poll() is None:
                    proc.send_signal(signal.SIGTERM)
            for proc in [*plants, *services]:
                try:
                    proc.wait(timeout=60)
                except subprocess.TimeoutExpired:
                    proc.kill()
    counted = {name: sum(counted1[r][name] - counted0[r][name] for r in robots) for name in counted0[robots[0]]}
    return {**summarise(mode, n, seconds, results, cpu1, cpu0, memory, load0, load1, ready_s), "shm": shm,
            "service_counters": counted, "realtime_priority": os.sched_getparam(0).sched_priority}


def service_counters(session: Any, processes: list[str]) -> dict[str, dict[str, int]]:
    """Each robot's counters as its service process reports them (`list_robots`): `received` (frames that reached
    the process), `taken` (by the loop), and the `Status` counters (`frames` registered, `dropped`: superseded in the
    inbox, `stale`, `rejected`, `idle`)."""
    counted = {}
    for process in processes:
        for reply in session.get(process_command_key("ddvs", process), payload=dump(Command(op="list_robots")),
                                 timeout=10.0):
            if reply.ok is None:
                raise RuntimeError(f"process {process}: list_robots answered with a Zenoh error")
            listed = Reply.model_validate_json(reply.ok.payload.to_bytes())
            assert listed.data is not None, listed.error
            for r in listed.data["robots"]:
                counted[r["robot"]] = {"received": r["received"], "taken": r["fairness"]["frames"], **r["counters"]}
    return counted


def summarise(mode: str, n: int, seconds: float, results: list[dict[str, Any]], cpu1: list[float],
              cpu0: list[float], memory: list[dict[str, float]], load0: tuple[float, ...], load1: tuple[float, ...],
              ready_s: float) -> dict[str, Any]:
    per_robot = []
    for r in results:
        lat = np.array(r["latency_ms"]) if r["latency_ms"] else np.array([np.nan])
        per_robot.append({"robot": r["robot"], "published": r["published"], "answered": r["answered"],
                          "median_ms": round(float(np.median(lat)), 2),
                          "p99_ms": round(float(np.percentile(lat, 99)), 2),
                          "final_offset_mm": round(r["final_offset_mm"], 2)})
    phases = [r["phase_ms"] for r in results]
    pooled = np.concatenate([np.array(r["latency_ms"]) for r in results if r["latency_ms"]] or [np.array([np.nan])])
    published = sum(r["published"] for r in results)
    answered = sum(r["answered"] for r in results)
    return {
        "mode": mode, "robots": n, "seconds": seconds, "published": published, "answered": answered,
        "skipped": sum(r["skipped"] for r in results),
        "answered_fraction": round(answered / max(published, 1), 4),
        "worst_robot_answered_fraction": round(min(p["answered"] / max(p["published"], 1) for p in per_robot), 4),
        "median_ms": round(float(np.median(pooled)), 2), "p99_ms": round(float(np.percentile(pooled, 99)), 2),
        "worst_robot_p99_ms": max(p["p99_ms"] for p in per_robot),
        **{f"{kind}_mb": round(sum(m[kind] for m in memory), 1) for kind in ("rss", "shmem", "pss")},
        "cpu_percent": round(100.0 * (sum(cpu1) - sum(cpu0)) / seconds, 1),
        "load_average": [round(load0[0], 2), round(load1[0], 2)], "ready_s": round(ready_s, 1),
        "crowd_5ms": crowd(phases, CROWD_WINDOW_MS), "phases_ms": sorted(round(p, 1) for p in phases),
        "per_robot": per_robot, **traced_summary(results),
    }


def traced_summary(results: list[dict[str, Any]]) -> dict[str, Any]:
    """The plants' traces (`--trace`) pooled: every frame not answered with its robot, the count of each kind (and of
    the superseded, those replaced by a frame its plant published less than half a period later), and the mean parts
    of the latency (`split_latency`) of every answered frame and of those slower than `SLOW_MS`."""
    if not all("missed" in r for r in results):
        return {}
    missed = [{"robot": r["robot"], **m} for r in results for m in r["missed"]]
    parts = np.array([p for r in results for p in r["parts_ms"]] or [[np.nan] * 5])
    slow = parts[parts[:, 3] > SLOW_MS]

    def mean_parts(rows: np.ndarray) -> dict[str, float | None]:
        return {name: round(float(rows[:, i].mean()), 2) if len(rows) else None
                for i, name in enumerate(("outside", "queued", "work", "latency", "work_cpu"))}

    return {"missed": missed, "missed_kinds": {kind: sum(m["kind"] == kind for m in missed)
                                               for kind in ("superseded", "stale", "lost", "twist_lost")},
            "superseded_by_a_frame_within_half_a_period": sum(
                m["kind"] == "superseded" and m["next_frame_after_ms"] < 500.0 / RATE_HZ for m in missed),
            "parts_ms_mean": mean_parts(parts), "slow": len(slow), "slow_parts_ms_mean": mean_parts(slow),
            "statuses": sum(r["statuses"] for r in results)}


def crowd(phases_ms: list[float], window_ms: float) -> int:
    """The most robots whose frames are published within `window_ms` of one another in each period (phases: each
    plant's publishing time modulo the frame period, fixed for a run by when its plant started): the frames the
    loop thread finds waiting together once a period, which sets the tail latency of the run."""
    period = 1e3 / RATE_HZ
    ordered = sorted(p % period for p in phases_ms)
    wrapped = ordered + [p + period for p in ordered]
    return max((sum(1 for q in wrapped[i:i + len(ordered)] if q - p <= window_ms) for i, p in enumerate(ordered)),
               default=0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    parser.add_argument("--modes", nargs="+", choices=["shared", "separate"], default=["shared", "separate"])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--service-shm", choices=["on", "off"], default="on",
                        help="the services' Zenoh shared memory (on: the default of every node; off: frames are "
                             "copied over loopback TCP and the plants' shared-memory pools are not mapped)")
    parser.add_argument("--realtime-priority", type=int, metavar="1-99",
                        help="the whole chain (this process, the services and the plants it starts, which inherit "
                             "it) under SCHED_FIFO at this priority: what the process does when it gets the cores "
                             "of a host busy with other work (root or CAP_SYS_NICE)")
    parser.add_argument("--trace", action="store_true",
                        help="the plants also subscribe to their robots' status and report what became of each "
                             "frame not answered (stale, superseded, lost, twist lost) and where the slow frames' "
                             "time went (the row's `missed`, `slow`; the status traffic is the run's too)")
    parser.add_argument("--markdown", action="store_true")
    parser.add_argument("--json", type=Path, help="also write every row (per-robot figures included) here")
    parser.add_argument("--publish", metavar="ROBOT", help=argparse.SUPPRESS)  # the plant process
    parser.add_argument("--port", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.publish:
        publish(args.publish, args.port, args.seed, args.trace)
        return
    if args.realtime_priority:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.realtime_priority))
    rows = []
    for n in args.robots:
        for mode in args.modes:
            row = measure(mode, n, args.seconds, args.service_shm == "on", args.trace)
            print(json.dumps({k: v for k, v in row.items() if k != "per_robot"}), file=sys.stderr, flush=True)
            rows.append(row)
            if args.json:
                args.json.write_text(json.dumps(rows, indent=1))
    print_rows(rows, args.markdown,
               ["mode", "robots", "answered", "worst robot answered", "median ms", "p99 ms", "worst robot p99 ms",
                "RSS MB (of it shared memory)", "PSS MB", "CPU % of a core", "load avg (start→end)",
                "robots within 5 ms"],
               lambda r: [r["mode"], str(r["robots"]), f"{r['answered']}/{r['published']}",
                          f"{100 * r['worst_robot_answered_fraction']:.1f} %", str(r["median_ms"]), str(r["p99_ms"]),
                          str(r["worst_robot_p99_ms"]), f"{r['rss_mb']} ({r['shmem_mb']})", str(r["pss_mb"]),
                          str(r["cpu_percent"]), f"{r['load_average'][0]}→{r['load_average'][1]}",
                          str(r["crowd_5ms"])])


if __name__ == "__main__":
    main()
