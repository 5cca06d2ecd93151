"""Cost of `ddvs record` (issue 19): frames kept, the recorder's CPU share and the bag's size per minute, at 30 and
100 Hz of 320×240 mono8 frames, for raw frames (zstd or lz4 chunks) and CompressedImage PNG / JPEG.

Per configuration: `ddvs record` runs as its own process (real Zenoh on loopback); this script publishes, at the
rate, a camera frame (a 320×240 crop of the boat image moving 1 px per frame, with Gaussian sensor noise σ = 2 grey
levels, so that compression sees camera-like data), its camera info, a twist and a JSON status, for `--seconds`;
then stops the recorder (SIGINT) and reads the bag back. Reported: frames recorded / published, the recorder's CPU
time over the publishing interval as a share of one core (psutil, user + system), and the bag's size per minute of
recording (MB = 10⁶ bytes). The load average of the machine is printed with the table.

    .venv/bin/python benchmarks/bench_record.py [--seconds 10] [--write-readme]
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_registration import write_readme_section  # noqa: E402
from benchmarks.bench_tls import free_port  # noqa: E402
from clients.bag import bag_messages, storage_files  # noqa: E402
from clients.channels import run_channels  # noqa: E402
from ddvs_service.protocol import (  # noqa: E402
    CameraInfo,
    Counters,
    Header,
    Keys,
    Latency,
    SessionConfig,
    Status,
    Time,
    TwistStamped,
    declare_publisher,
    dump,
    encode_camera_info,
    encode_image,
    encode_twist_stamped,
    image_from_array,
    open_session,
)
from evaluation.pairs import load  # noqa: E402

W, H = 320, 240
KEYS = Keys("ddvs", "benchrec")
CONFIGS = (("raw", "zstd"), ("raw", "lz4"), ("png", "zstd"), ("jpeg", "zstd"))


def camera_frames(n: int, seed: int = 0) -> list[np.ndarray]:
    """`n` 320×240 frames: a crop of the boat image moving 1 px per frame, plus sensor noise (σ = 2)."""
    boat = load("boat", 1)
    rng = np.random.default_rng(seed)
    frames = []
    for k in range(n):
        x, y = 100 + k % 300, 100 + (k // 3) % 200
        crop = boat[y:y + H, x:x + W] + rng.normal(0.0, 2.0, (H, W))
        frames.append(np.clip(crop, 0, 255).astype(np.uint8))
    return frames


def record_once(frames_mode: str, compression: str, rate: float, seconds: float, images: list[np.ndarray],
                out: Path) -> dict[str, float]:
    port = free_port()
    cmd = [sys.executable, "-m", "ddvs.cli", "record", str(out), "--robot", KEYS.robot, "--frames", frames_mode,
           "--compression", compression, "--listen", f"tcp/127.0.0.1:{port}"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while not storage_files(out)[0].exists():
        if proc.poll() is not None:
            raise RuntimeError(f"ddvs record exited with {proc.returncode}")
        time.sleep(0.05)
    recorder = psutil.Process(proc.pid)
    published = 0
    with open_session(SessionConfig(connect=[f"tcp/127.0.0.1:{port}"])) as session:
        pubs = {name: declare_publisher(session, KEYS, name)
                for name in ("camera_image", "camera_info", "servo_twist", "servo_status")}
        time.sleep(1.0)  # the recorder's subscriptions reach this session
        cpu0, t0 = sum(recorder.cpu_times()[:2]), time.monotonic()
        period, next_t, k = 1.0 / rate, time.monotonic(), 0
        while time.monotonic() - t0 < seconds:
            header = Header(Time.now(), "camera")
            pubs["camera_image"].put(encode_image(image_from_array(images[k % len(images)], "mono8", header)))
            pubs["camera_info"].put(encode_camera_info(CameraInfo(header, H, W, k=[420, 0, 159.5, 0, 420, 119.5,
                                                                                     0, 0, 1])))
            pubs["servo_twist"].put(encode_twist_stamped(TwistStamped(header, [0.01, 0, 0], [0, 0, 0.02])))
            pubs["servo_status"].put(dump(Status(
                robot=KEYS.robot, state="SERVOING", frame_stamp_ns=header.stamp.to_ns(), seq=k, error=[1e-2] * 6,
                error_norm=0.0245, iterations=2, residual_rms=3.0, inlier_ratio=0.95, twist=[0.01] * 6,
                latency_ms=Latency(decode=0.1, registration=1.0, control=0.1, publish=0.1, total=1.3),
                counters=Counters(frames=k, dropped=0, rejected=0))))
            published += 1
            k += 1
            next_t += period
            time.sleep(max(0.0, next_t - time.monotonic()))
        time.sleep(0.5)  # the recorder drains its queue
        cpu1, t1 = sum(recorder.cpu_times()[:2]), time.monotonic()
        for pub in pubs.values():
            pub.undeclare()
    proc.send_signal(signal.SIGINT)
    proc.wait(60)
    image_topic = next(s.topic for s in run_channels(KEYS, frames_mode) if s.key_name == "camera_image")
    recorded = sum(1 for m in bag_messages(out) if m.topic == image_topic)
    size = sum(p.stat().st_size for p in out.iterdir())
    return {"recorded": recorded, "published": published, "cpu": (cpu1 - cpu0) / (t1 - t0),
            "mb_per_min": size / 1e6 / (published / rate) * 60.0}


def run(seconds: float) -> str:
    images = camera_frames(600)
    rows = ["| rate | frames | chunks | frames recorded / published | recorder CPU (one core) | bag size |",
            "|---|---|---|---|---|---|"]
    with tempfile.TemporaryDirectory(prefix="ddvs-bench-record-") as tmp:
        for rate in (30.0, 100.0):
            for frames_mode, compression in CONFIGS:
                out = Path(tmp) / f"{frames_mode}-{compression}-{rate:g}"
                r = record_once(frames_mode, compression, rate, seconds, images, out)
                label = "raw Image" if frames_mode == "raw" else f"CompressedImage {frames_mode.upper()}"
                rows.append(f"| {rate:g} Hz | {label} | {compression} | {r['recorded']} / {r['published']} | "
                            f"{100 * r['cpu']:.0f} % | {r['mb_per_min']:.0f} MB/min |")
                shutil.rmtree(out)
    load1, load5, _ = os.getloadavg()
    return ("\n".join(rows) + f"\n\n{seconds:g} s per configuration, 320×240 mono8; load average "
            f"{load1:.2f} / {load5:.2f} (1 / 5 min) on {os.cpu_count()} cores at the end of the run.")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="publishing time per configuration")
    parser.add_argument("--write-readme", action="store_true", help="rewrite its section of its results page")
    args = parser.parse_args()
    table = run(args.seconds)
    print(table)
    if args.write_readme:
        write_readme_section("record-cost", "Recording cost: ddvs record at 30 and 100 Hz", table, "bench_record.py")
    return 0


if __name__ == "__main__":
    sys.exit(main())
