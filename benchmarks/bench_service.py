"""End-to-end latency of the servo service over Zenoh on loopback (issue 6).

Three processes: `ddvs serve` (320×240 frames, 200×150 ROI, decoupled law), a frame publisher (this script with
`--publish`) and the receiver (this script), which sets the reference, starts the servo and timestamps every twist.
Latency = twist arrival (receiver's `time.time_ns()`) − the frame's stamp (publisher's `time.time_ns()` before it
encodes and puts the frame); the service stamps each twist with its frame's stamp. Frames follow a smooth 2-px
circle around the reference (a tracking workload). At rates above the service's throughput it must keep up with the
newest frame: latency stays bounded and the surplus frames are dropped, never queued.

Warm-up: the publisher first sends frames at 30 Hz until the service has answered `WARM_UP_FRAMES` of them (global
initialisation and kernel compilation take seconds on a loaded machine), then measures; only frames stamped after
that point count. Per frame the service's status gives its own time (`latency_ms.total`: payload arrival → twist
published, with `registration` inside it), so `transport = end to end − service` is everything outside the service
loop: the publisher's encode and put, Zenoh both ways, the hand-off to the service's loop thread, the receiver's
wake-up.

State load (`--hogs N`): N busy-loop processes at normal priority run while measuring (two on a 2-core host: every
core contested); `--realtime-priority P` runs the service under SCHED_FIFO, `--realtime-chain` the camera publisher
and the receiver too (the hogs stay at normal priority).
Never stale: the service withholds a twist that would go out more than `frame_timeout_s` after its frame arrived
with two newer frames waiting (status counter `stale`); such frames have no twist and count as not answered.

Watchers (`--watchers none record foxglove`, issue 19): while measuring, `ddvs record` (a bag of every channel,
raw frames) or `ddvs monitor --foxglove` with a WebSocket client subscribed to every channel (the residual image
included, which the service then computes at 5 Hz) runs beside the service; one run each, in that order per rate.

    .venv/bin/python benchmarks/bench_service.py [--rates 30 100 200] [--seconds 10] [--hogs 0 2]
                                                 [--realtime-priority 10] [--watchers none record] [--markdown]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.rows import print_rows  # noqa: E402
from ddvs_service.protocol import (  # noqa: E402 - after the path set-up for running as a script
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
from ddvs_service.protocol.upload import encode_upload  # noqa: E402
from ddvs_service.service.config import IntrinsicsConfig, RegistrationSettings, ServiceConfig  # noqa: E402
from sim.textures import texture_path  # noqa: E402

W, H, F = 320, 240, 420.0


def bench_config(**settings: Any) -> ServiceConfig:
    """The service configuration of the benchmarks: this camera's intrinsics, a 200×150 template, and `settings`."""
    return ServiceConfig(intrinsics=IntrinsicsConfig(fx=F, fy=F, cx=(W - 1) / 2, cy=(H - 1) / 2, width=W, height=H),
                         registration=RegistrationSettings(template_size=(200, 150)), **settings)
WARM_UP_FRAMES = 30
WARM_UP_LIMIT_S = 120.0
DATASET = texture_path("boat")


def scene() -> np.ndarray:
    img = cv2.imread(str(DATASET), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise SystemExit(f"missing dataset image {DATASET}")
    return cv2.resize(img[100:580, 150:790], (W, H), interpolation=cv2.INTER_AREA)


def frame_at(img: np.ndarray, k: int) -> np.ndarray:
    a = 2 * np.pi * k / 90.0
    M = np.array([[1.0, 0.0, 2.0 * np.cos(a)], [0.0, 1.0, 2.0 * np.sin(a)]])
    return cv2.warpAffine(img, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def publish(port: int, rate: float, seconds: float) -> None:
    """Publisher process: frames at 30 Hz until the service answered `WARM_UP_FRAMES` of them, then at `rate` Hz
    for `seconds`, each stamped with the wall clock before it is encoded and put (the project's camera QoS).
    Prints the measured frames, the wall clock at which measuring began and the median stamp → put-returned time."""
    img = scene()
    frames = [frame_at(img, k) for k in range(90)]
    keys = Keys("ddvs", "bench")
    session = open_session(SessionConfig(connect=[f"tcp/127.0.0.1:{port}"]))
    pub = declare_publisher(session, keys, "camera_image")
    answered: list[None] = []  # one entry per status seen during the warm-up (appended by Zenoh's thread)
    status = session.declare_subscriber(keys.key("servo_status"), lambda _sample: answered.append(None))
    k = 0

    def put_next() -> float:
        nonlocal k
        stamp = time.time_ns()
        pub.put(encode_image(image_from_array(frames[k % 90], "mono8", Header(Time.from_ns(stamp), "camera"))))
        k += 1
        return (time.time_ns() - stamp) / 1e6

    limit = time.monotonic() + WARM_UP_LIMIT_S
    while len(answered) < WARM_UP_FRAMES:
        if time.monotonic() > limit:
            raise SystemExit(f"the service answered fewer than {WARM_UP_FRAMES} frames in {WARM_UP_LIMIT_S} s")
        put_next()
        time.sleep(1 / 30)
    status.undeclare()
    time.sleep(0.2)
    start_ns = time.time_ns()
    put_ms = []
    period = 1.0 / rate
    t0 = time.perf_counter()
    n = 0
    while time.perf_counter() - t0 < seconds:
        put_ms.append(put_next())
        n += 1
        time.sleep(max(0.0, t0 + n * period - time.perf_counter()))
    pub.undeclare()
    session.close()
    print(json.dumps({"published": n, "start_ns": start_ns, "put_median_ms": float(np.median(put_ms))}))


def hog() -> None:
    """A CPU hog at normal priority (SCHED_OTHER, also when started from a real-time chain): spins until killed."""
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    while True:
        pass


def command(session, keys: Keys, **kwargs: object) -> Reply:
    for reply in session.get(keys.key("servo_command"), payload=dump(Command(**kwargs)), timeout=30.0):
        return Reply.model_validate_json(reply.ok.payload.to_bytes())
    raise RuntimeError("the service did not answer")


def watch_foxglove(url: str, stop: threading.Event) -> None:
    """A Foxglove WebSocket client that subscribes every advertised channel and reads until `stop`."""
    import asyncio

    import websockets

    async def client() -> None:
        async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"], max_size=None) as ws:
            while not stop.is_set():
                try:
                    frame = await asyncio.wait_for(ws.recv(), timeout=0.2)
                except TimeoutError:
                    continue
                except websockets.ConnectionClosed:
                    return  # the monitor stopped first
                if isinstance(frame, str) and json.loads(frame).get("op") == "advertise":
                    ids = [c["id"] for c in json.loads(frame)["channels"]]
                    await ws.send(json.dumps({"op": "subscribe",
                                              "subscriptions": [{"id": i, "channelId": i} for i in ids]}))

    asyncio.run(client())


def start_watcher(watcher: str, port: int, workdir: str) -> tuple[subprocess.Popen, threading.Event]:
    """`ddvs record` or `ddvs monitor --foxglove` + a subscribed client, connected to the service at `port`."""
    stop = threading.Event()
    common = ["--robot", "bench", "--connect", f"tcp/127.0.0.1:{port}"]
    if watcher == "record":
        proc = subprocess.Popen([sys.executable, "-m", "ddvs.cli", "record", str(Path(workdir) / "bag"), *common],
                                cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        return proc, stop
    ws_port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "ddvs.cli", "monitor", "--foxglove", "--port", str(ws_port),
                             *common], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    assert proc.stdout is not None and "ws://" in proc.stdout.readline()
    threading.Thread(target=watch_foxglove, args=(f"ws://127.0.0.1:{ws_port}", stop), daemon=True).start()
    return proc, stop


def summarise(rate: float, hogs: int, run: dict, statuses: list[dict], arrival_ms: dict[int, float],
              counters: list[dict]) -> dict:
    """Figures of one rate from the answered frames' statuses (in stamp order), their twists' latencies and the
    counters of every measured frame's status (stale ones too)."""
    e2e = np.array([arrival_ms[s["frame_stamp_ns"]] for s in statuses])
    service = np.array([s["latency_ms"]["total"] for s in statuses])
    reg = np.array([s["latency_ms"]["registration"] for s in statuses])
    transport = e2e - service
    tail = e2e >= np.percentile(e2e, 99)
    half = len(e2e) // 2

    def ms(x: np.ndarray) -> dict[str, float]:
        return {"median": round(float(np.median(x)), 2), "p99": round(float(np.percentile(x, 99)), 2),
                "max": round(float(x.max()), 1)}

    return {
        "rate_hz": rate, "hogs": hogs, "published": run["published"], "twists": len(e2e),
        "dropped": counters[-1]["dropped"] - counters[0]["dropped"],
        "stale": counters[-1].get("stale", 0) - counters[0].get("stale", 0),
        "within_period": round(float(np.mean(e2e <= 1e3 / rate)), 4), "end_to_end_ms": ms(e2e),
        "service_ms": ms(service), "registration_ms": ms(reg), "transport_ms": ms(transport),
        "publisher_put_median_ms": round(run["put_median_ms"], 2),
        "tail_service_share": round(float(np.median(service[tail] / e2e[tail])), 2),
        "median_halves_ms": [round(float(np.median(e2e[:half])), 2), round(float(np.median(e2e[half:])), 2)],
        "states": sorted({s["state"] for s in statuses}), "load_average": round(os.getloadavg()[0], 2),
    }


def measure(rate: float, seconds: float, hogs: int, realtime_priority: int | None, watcher: str = "none") -> dict:
    port = free_port()
    state = tempfile.mkdtemp(prefix="ddvs-bench-")
    cfg = Path(state) / "serve.json"
    cfg.write_text(bench_config(robot="bench", state_dir=Path(state),
                                zenoh=SessionConfig(listen=[f"tcp/127.0.0.1:{port}"])).model_dump_json())
    env = {k: v for k, v in os.environ.items() if not k.startswith("DDVS_ZENOH_")}
    realtime = ["--realtime-priority", str(realtime_priority)] if realtime_priority else []
    service = subprocess.Popen([sys.executable, "-m", "ddvs.cli", "serve", "--config", str(cfg),
                                "--log-level", "WARNING", *realtime], env=env, cwd=ROOT)
    keys = Keys("ddvs", "bench")
    session = open_session(SessionConfig(connect=[f"tcp/127.0.0.1:{port}"]))
    latencies: list[tuple[int, float]] = []  # (frame stamp, ms)
    lock = threading.Lock()

    def on_twist(sample) -> None:
        arrival = time.time_ns()
        stamp = decode_twist_stamped(sample.payload.to_bytes()).header.stamp.to_ns()
        with lock:
            latencies.append((stamp, (arrival - stamp) / 1e6))

    statuses: list[dict] = []
    subs = [session.declare_subscriber(keys.key("servo_twist"), on_twist),
            session.declare_subscriber(keys.key("servo_status"), lambda s: statuses.append(json.loads(
                s.payload.to_bytes())))]
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                command(session, keys, op="get_state")
                break
            except Exception:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.3)
        img = scene()
        ok = command(session, keys, op="set_reference", source="upload",
                     image={"format": "png", "data": encode_upload(img)})
        assert ok.ok, ok.error
        assert command(session, keys, op="start").ok
        watching = start_watcher(watcher, port, state) if watcher != "none" else None
        time.sleep(1.0 if watching else 0.0)  # the watcher's subscriptions reach the service
        spinners = [subprocess.Popen([sys.executable, __file__, "--hog"]) for _ in range(hogs)]
        try:
            out = subprocess.run([sys.executable, __file__, "--publish", str(port), "--rate", str(rate),
                                  "--seconds", str(seconds)], check=True, capture_output=True, text=True)
        finally:
            for spinner in spinners:
                spinner.kill()
                spinner.wait()
            if watching:
                watching[1].set()
                watching[0].terminate()
                watching[0].wait(30)
        run = json.loads(out.stdout.strip().splitlines()[-1])
        time.sleep(0.5)
        with lock:  # twists answering a measured frame (the watchdog's zero twists carry no frame's stamp)
            arrival_ms = {stamp: ms for stamp, ms in latencies if stamp >= run["start_ns"]}
        run_statuses = [s for s in statuses if s["frame_stamp_ns"] in arrival_ms]
        run_statuses.sort(key=lambda s: s["frame_stamp_ns"])
        measured = sorted((s for s in statuses if s["frame_stamp_ns"] >= run["start_ns"]),
                          key=lambda s: s["frame_stamp_ns"])  # stale ones included
        return {"watcher": watcher,
                **summarise(rate, hogs, run, run_statuses, arrival_ms, [s["counters"] for s in measured])}
    finally:
        for s in subs:
            s.undeclare()
        session.close()
        service.terminate()
        service.wait(timeout=30)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--publish", type=int, metavar="PORT", help=argparse.SUPPRESS)
    parser.add_argument("--rate", type=float, default=30.0, help=argparse.SUPPRESS)
    parser.add_argument("--rates", type=float, nargs="+", default=[30.0, 100.0, 200.0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--hogs", type=int, nargs="+", default=[0], help="CPU hogs while measuring (one run each)")
    parser.add_argument("--hog", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--realtime-priority", type=int, metavar="1-99",
                        help="run the service under SCHED_FIFO (ddvs serve --realtime-priority)")
    parser.add_argument("--realtime-chain", action="store_true",
                        help="with --realtime-priority: the camera publisher and the receiver under SCHED_FIFO too")
    parser.add_argument("--watchers", nargs="+", default=["none"], choices=("none", "record", "foxglove"),
                        help="what watches the servo while measuring (one run each; default none)")
    parser.add_argument("--markdown", action="store_true", help="print a markdown table")
    args = parser.parse_args()
    if args.publish:
        publish(args.publish, args.rate, args.seconds)
        return
    if args.hog:
        hog()
    if args.realtime_chain:  # this process (the receiver) and the publisher it starts; the hogs reset themselves
        if not args.realtime_priority:
            raise SystemExit("--realtime-chain needs --realtime-priority")
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.realtime_priority))
    print(f"# machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.2f}", flush=True)
    rows = [measure(rate, args.seconds, hogs, args.realtime_priority, watcher)
            for hogs in args.hogs for rate in args.rates for watcher in args.watchers]
    print_rows(rows, args.markdown, MARKDOWN_HEADER, markdown_cells)


MARKDOWN_HEADER = ["input rate", "watcher", "hogs", "frames published / answered / dropped / stale",
                   "twists within a period", "end to end median / p99 / max", "service median / p99",
                   "registration median / p99", "transport median / p99", "p99 frames: service share",
                   "median 1st / 2nd half", "load"]


def markdown_cells(r: dict) -> list[str]:
    def ms(x: dict, with_max: bool = False) -> str:
        return f"{x['median']:.2f} / {x['p99']:.2f}" + (f" / {x['max']:.1f}" if with_max else "") + " ms"

    return [f"{r['rate_hz']:.0f} Hz", r["watcher"], str(r["hogs"]),
            f"{r['published']} / {r['twists']} / {r['dropped']} / {r['stale']}", f"{r['within_period']:.1%}",
            ms(r["end_to_end_ms"], True), ms(r["service_ms"]), ms(r["registration_ms"]), ms(r["transport_ms"]),
            f"{r['tail_service_share']:.0%}",
            f"{r['median_halves_ms'][0]:.2f} / {r['median_halves_ms'][1]:.2f} ms", f"{r['load_average']:.2f}"]


if __name__ == "__main__":
    main()
