"""End-to-end latency of the servo service over Zenoh on loopback (issue 6).

Three processes: `ddvs serve` (320×240 frames, 200×150 ROI, decoupled law), a frame publisher (this script with
`--publish`) and the receiver (this script), which sets the reference, starts the servo and timestamps every twist.
Latency = twist arrival (receiver's `time.time_ns()`) − the frame's stamp (publisher's `time.time_ns()` just before
`put`); the service stamps each twist with its frame's stamp. Frames follow a smooth 2-px circle around the
reference (a tracking workload). At rates above the service's throughput it must keep up with the newest frame:
latency stays bounded and the surplus frames are dropped, never queued.

    .venv/bin/python benchmarks/bench_service.py [--rates 30 100 200] [--seconds 10] [--markdown]
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

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ddvs_service.datasets import dataset_image  # noqa: E402
from ddvs_service.protocol import (  # noqa: E402 - after the path set-up for running as a script
    Command,
    Header,
    Keys,
    Reply,
    SessionConfig,
    Time,
    decode_twist_stamped,
    dump,
    encode_image,
    image_from_array,
    open_session,
)
from ddvs_service.protocol.upload import encode_upload  # noqa: E402

W, H, F = 320, 240, 420.0
DATASET = dataset_image("oxford/boat/img1.png")


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
    """Publisher process: frames at `rate` Hz for `seconds`, stamped with the wall clock just before `put`."""
    img = scene()
    frames = [frame_at(img, k) for k in range(90)]
    keys = Keys("ddvs", "bench")
    session = open_session(SessionConfig(connect=[f"tcp/127.0.0.1:{port}"]))
    pub = session.declare_publisher(keys.key("camera_image"))
    period = 1.0 / rate
    t0 = time.perf_counter()
    k = 0
    while time.perf_counter() - t0 < seconds:
        header = Header(Time.from_ns(time.time_ns()), "camera")
        pub.put(encode_image(image_from_array(frames[k % 90], "mono8", header)))
        k += 1
        time.sleep(max(0.0, t0 + k * period - time.perf_counter()))
    pub.undeclare()
    session.close()
    print(json.dumps({"published": k}))


def command(session, keys: Keys, **kwargs: object) -> Reply:
    for reply in session.get(keys.key("servo_command"), payload=dump(Command(**kwargs)), timeout=30.0):
        return Reply.model_validate_json(reply.ok.payload.to_bytes())
    raise RuntimeError("the service did not answer")


def measure(rate: float, seconds: float) -> dict[str, float]:
    port = free_port()
    state = tempfile.mkdtemp(prefix="ddvs-bench-")
    config = {
        "robot": "bench", "state_dir": state, "zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]},
        "intrinsics": {"fx": F, "fy": F, "cx": (W - 1) / 2, "cy": (H - 1) / 2, "width": W, "height": H},
        "registration": {"template_size": [200, 150]},
    }
    cfg = Path(state) / "serve.json"
    cfg.write_text(json.dumps(config))
    env = {k: v for k, v in os.environ.items() if not k.startswith("DDVS_ZENOH_")}
    service = subprocess.Popen([sys.executable, "-m", "ddvs_service.cli", "serve", "--config", str(cfg),
                                "--log-level", "WARNING"], env=env, cwd=ROOT)
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
        # warm-up: one second of frames at 30 Hz (global initialisation, kernel compilation), then measure
        subprocess.run([sys.executable, __file__, "--publish", str(port), "--rate", "30", "--seconds", "1.5"],
                       check=True, capture_output=True)
        time.sleep(0.5)
        with lock:
            latencies.clear()
        n_status = len(statuses)
        out = subprocess.run([sys.executable, __file__, "--publish", str(port), "--rate", str(rate),
                              "--seconds", str(seconds)], check=True, capture_output=True, text=True)
        published = json.loads(out.stdout.strip().splitlines()[-1])["published"]
        time.sleep(0.5)
        run_statuses = statuses[n_status:]
        frame_stamps = {s["frame_stamp_ns"] for s in run_statuses}
        with lock:  # twists answering a frame (the watchdog's zero twists carry no frame's stamp)
            lat = np.array([ms for stamp, ms in latencies if stamp in frame_stamps])
        reg = [s["latency_ms"]["registration"] for s in run_statuses]
        half = len(lat) // 2
        return {
            "rate_hz": rate, "published": published, "twists": len(lat),
            "median_ms": float(np.median(lat)), "p99_ms": float(np.percentile(lat, 99)),
            "max_ms": float(lat.max()),
            "first_half_median_ms": float(np.median(lat[:half])), "second_half_median_ms": float(np.median(lat[half:])),
            "registration_median_ms": float(np.median(reg)) if reg else float("nan"),
            "states": sorted({s["state"] for s in run_statuses}),
        }
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
    parser.add_argument("--markdown", action="store_true", help="print a markdown table")
    args = parser.parse_args()
    if args.publish:
        publish(args.publish, args.rate, args.seconds)
        return
    print(f"# machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.2f}", flush=True)
    rows = [measure(rate, args.seconds) for rate in args.rates]
    if args.markdown:
        print("| input rate | frames published | twists | median | p99 | max | median 1st/2nd half | registration |")
        print("|---|---|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['rate_hz']:.0f} Hz | {r['published']} | {r['twists']} | {r['median_ms']:.2f} ms | "
                  f"{r['p99_ms']:.2f} ms | {r['max_ms']:.1f} ms | {r['first_half_median_ms']:.2f} / "
                  f"{r['second_half_median_ms']:.2f} ms | {r['registration_median_ms']:.2f} ms |")
    else:
        for r in rows:
            print(json.dumps(r))


if __name__ == "__main__":
    main()
