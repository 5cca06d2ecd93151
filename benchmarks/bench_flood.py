"""A flood from an authorised camera against the servo service over Zenoh on loopback (issue 32, item 2).

`ddvs serve` (320×240 frames, 200×150 ROI, decoupled law) in a subprocess; this script plays the camera and the
operator. Three phases in one run, each starting the servo afresh (`reset`, the reference from the next frame,
`start`) and streaming the same valid frames (a 2-px circle around the reference, 90 views) at `--rate` Hz for
`--seconds`, each stamped with the wall clock when it is put:

- `baseline`: the valid stream alone;
- `malformed`: the valid stream and, from another process, `--flood-rate` malformed frames/s (garbage, truncated CDR,
  an unknown encoding, the wrong size, in turn);
- `valid`: the valid stream and, from another process, valid frames as fast as `--flood-rate` allows (each
  stamped when put), a camera faster than the loop.

Per phase: the stream's frames answered with a twist (`answered`, ratio against the baseline's) and all frames
answered per second (the flood's valid frames too; ratio against the baseline's), for `malformed` whether each
answered frame's twist equals the baseline's twist of the same frame (largest difference), twists that answer no
streamed frame while it runs (for `valid`: the flood's), the flood's frames put and the service's `rejected` /
`dropped` counters, the service's WARNING lines about rejections, stamp → twist latency of the answered frames
(median, p95; `service_ms`: the part from the frame's arrival in the service's inbox, its status's `latency_ms.total`),
frames answered after the flood ended (a queue would show here), the service's resident memory, the
load average.

    .venv/bin/python benchmarks/bench_flood.py [--rate 15] [--seconds 10] [--flood-rate 5000]
"""

from __future__ import annotations

import argparse
import json
import os
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

from benchmarks.bench_service import F, H, W, command, frame_at, free_port, scene  # noqa: E402
from ddvs_service.protocol import (  # noqa: E402 - after the path set-up for running as a script
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

KEYS = Keys("ddvs", "flood")
VIEWS = 90
BURST_S = 0.01  # the flood puts its frames in bursts this far apart


def malformed_payloads() -> list[bytes]:
    good = encode_image(image_from_array(scene(), "mono8", Header(Time.from_ns(time.time_ns()), "camera")))
    return [b"\x00\x01\x00\x00garbage", good[: len(good) // 2], good.replace(b"mono8", b"mnoo8", 1),
            encode_image(image_from_array(scene()[:, :200].copy(), "mono8"))]


def flood(port: int, kind: str, rate: float, seconds: float) -> None:
    """Flood process: `kind` (malformed, valid) frames at up to `rate`/s for `seconds`; prints the count put. Valid
    frames are the stream's views, each stamped when put (the stamp written into a pre-encoded payload)."""
    session = open_session(SessionConfig(connect=[f"tcp/127.0.0.1:{port}"]))
    pub = declare_publisher(session, KEYS, "camera_image")
    time.sleep(0.5)  # the sessions meet
    img = scene()
    payloads = malformed_payloads() if kind == "malformed" else [
        encode_image(image_from_array(frame_at(img, k), "mono8", Header(Time(0, 0), "camera"))) for k in range(VIEWS)]
    sent = 0
    t0 = time.perf_counter()
    while (elapsed := time.perf_counter() - t0) < seconds:
        for _ in range(max(int(rate * (elapsed + BURST_S)) - sent, 0)):
            payload = payloads[sent % len(payloads)]
            if kind == "valid":
                buf = bytearray(payload)
                sec, nsec = divmod(time.time_ns(), 1_000_000_000)
                buf[4:12] = np.array([sec, nsec], "<u4").tobytes()  # header.stamp after the CDR encapsulation
                payload = bytes(buf)
            pub.put(payload)
            sent += 1
        time.sleep(BURST_S)
    pub.undeclare()
    session.close()
    print(json.dumps({"sent": sent, "seconds": round(time.perf_counter() - t0, 3)}))


class Operator:
    """The operator's and the valid camera's session: twists (frame stamp, twist, arrival ns) and statuses."""

    def __init__(self, port: int) -> None:
        self.session = open_session(SessionConfig(connect=[f"tcp/127.0.0.1:{port}"]))
        self.lock = threading.Lock()
        self.twists: list[tuple[int, np.ndarray, int]] = []
        self.statuses: list[dict[str, Any]] = []
        self.pub = declare_publisher(self.session, KEYS, "camera_image")
        self.subs = [self.session.declare_subscriber(KEYS.key("servo_twist"), self._on_twist),
                     self.session.declare_subscriber(KEYS.key("servo_status"), self._on_status)]

    def _on_twist(self, sample: Any) -> None:
        arrival = time.time_ns()
        msg = decode_twist_stamped(sample.payload.to_bytes())
        with self.lock:
            self.twists.append((msg.header.stamp.to_ns(), msg.vector, arrival))

    def _on_status(self, sample: Any) -> None:
        status = json.loads(sample.payload.to_bytes())
        with self.lock:
            self.statuses.append(status)

    def put(self, image: np.ndarray) -> int:
        stamp = time.time_ns()
        self.pub.put(encode_image(image_from_array(image, "mono8", Header(Time.from_ns(stamp), "camera"))))
        return stamp

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()
        self.pub.undeclare()
        self.session.close()


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return round(int(line.split()[1]) / 1024, 1)
    return float("nan")


def start_servo(op: Operator, img: np.ndarray) -> None:
    """Afresh: no reference, then the next frame (the reference itself) as the reference, then `start`."""
    assert command(op.session, KEYS, op="reset").ok
    assert command(op.session, KEYS, op="set_reference", source="next_frame").ok
    n = len(op.statuses)
    deadline = time.monotonic() + 60
    while not any(s["state"] == "READY" for s in op.statuses[n:]):
        if time.monotonic() > deadline:
            raise SystemExit("the reference frame was not adopted within 60 s")
        op.put(img)
        time.sleep(0.2)
    assert command(op.session, KEYS, op="start").ok


def phase(name: str, op: Operator, service: subprocess.Popen, log: Path, args: argparse.Namespace) -> dict[str, Any]:
    img = scene()
    views = [frame_at(img, k) for k in range(VIEWS)]
    start_servo(op, img)
    time.sleep(0.3)
    warnings0 = rejection_lines(log)
    with op.lock:
        n_twists, n_statuses, counters0 = len(op.twists), len(op.statuses), op.statuses[-1]["counters"]
    flooder = None if name == "baseline" else subprocess.Popen(
        [sys.executable, __file__, "--flood", str(args.port), "--kind", name, "--flood-rate", str(args.flood_rate),
         "--seconds", str(args.seconds + 1.0)], stdout=subprocess.PIPE, text=True)
    time.sleep(0.0 if flooder is None else 0.5)  # the flood's session meets the service's before the stream starts
    stamps: list[int] = []
    period = 1.0 / args.rate
    t0 = time.perf_counter()
    while len(stamps) < int(args.seconds * args.rate):
        stamps.append(op.put(views[len(stamps) % VIEWS]))
        time.sleep(max(t0 + len(stamps) * period - time.perf_counter(), 0.0))
    flood_out = json.loads(flooder.communicate(timeout=120)[0].strip().splitlines()[-1]) if flooder else None
    with op.lock:
        n_end = len(op.twists)
    time.sleep(1.5)  # the last report of rejections; what a queue would still answer
    with op.lock:
        twists, after = op.twists[n_twists:n_end], op.twists[n_end:]
        statuses, counters = op.statuses[n_statuses:], op.statuses[-1]["counters"]
    index = {stamp: k for k, stamp in enumerate(stamps)}
    first: dict[int, tuple[np.ndarray, int]] = {}  # frame stamp → its twist and arrival (repeats: zero twists)
    for stamp, twist, arrival in twists:
        first.setdefault(stamp, (twist, arrival))
    latency_ms = np.array([(arrival - stamp) / 1e6 for stamp, (_, arrival) in first.items()])
    service_ms = np.array([s["latency_ms"]["total"] for s in statuses if s["frame_stamp_ns"] in first])
    return {
        "phase": name, "streamed": len(stamps), "answered": sum(s in index for s in first),
        "frames_answered_per_s": round(len(first) / args.seconds, 2),
        "twists_answering_no_streamed_frame": sum(s not in index for s, _, _ in twists),
        "zero_twists_answering_frames": sum(not np.any(v) for v, _ in first.values()),
        "flood_sent": flood_out["sent"] if flood_out else 0,
        "flood_rate": round(flood_out["sent"] / flood_out["seconds"]) if flood_out else 0,
        "rejected": counters["rejected"] - counters0["rejected"], "dropped": counters["dropped"] - counters0["dropped"],
        "stale": counters["stale"] - counters0["stale"], "warning_lines": rejection_lines(log) - warnings0,
        "answered_after_the_flood": len({s for s, _, _ in after} - set(first) - {stamps[-1]}),
        "latency_ms": {"median": round(float(np.median(latency_ms)), 1),
                       "p95": round(float(np.percentile(latency_ms, 95)), 1)} if len(latency_ms) else None,
        "service_ms": {"median": round(float(np.median(service_ms)), 1),
                       "p95": round(float(np.percentile(service_ms, 95)), 1)} if len(service_ms) else None,
        "service_rss_mib": rss_mib(service.pid), "load_average": round(os.getloadavg()[0], 2),
        "_twists": {index[s]: v for s, (v, _) in first.items() if s in index},
    }


def rejection_lines(log: Path) -> int:
    return sum("rejected" in line for line in log.read_text(errors="replace").splitlines())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--flood", type=int, metavar="PORT", help=argparse.SUPPRESS)
    parser.add_argument("--kind", choices=("malformed", "valid"), help=argparse.SUPPRESS)
    parser.add_argument("--rate", type=float, default=15.0, help="valid frames/s of the stream (default 15)")
    parser.add_argument("--seconds", type=float, default=10.0, help="seconds per phase (default 10)")
    parser.add_argument("--flood-rate", type=float, default=5000.0, help="flood frames/s (default 5000)")
    args = parser.parse_args()
    if args.flood:
        flood(args.flood, args.kind, args.flood_rate, args.seconds)
        return
    print(f"# {os.cpu_count()} cores, load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    args.port = free_port()
    state = Path(tempfile.mkdtemp(prefix="ddvs-flood-"))
    config = {"robot": KEYS.robot, "state_dir": str(state), "zenoh": {"listen": [f"tcp/127.0.0.1:{args.port}"]},
              "intrinsics": {"fx": F, "fy": F, "cx": (W - 1) / 2, "cy": (H - 1) / 2, "width": W, "height": H},
              "registration": {"template_size": [200, 150]}}
    (state / "serve.json").write_text(json.dumps(config))
    log = state / "serve.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith("DDVS_ZENOH_")}
    with log.open("w") as log_file:
        service = subprocess.Popen([sys.executable, "-m", "ddvs.cli", "serve", "--config", str(state / "serve.json"),
                                    "--log-level", "WARNING"], env=env, cwd=ROOT, stderr=log_file)
        op = Operator(args.port)
        try:
            deadline = time.monotonic() + 120
            while True:
                try:
                    command(op.session, KEYS, op="get_state")
                    break
                except Exception:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.3)
            rows = [phase(name, op, service, log, args) for name in ("baseline", "malformed", "valid")]
        finally:
            op.close()
            service.terminate()
            service.wait(timeout=30)
    twists = [row.pop("_twists") for row in rows]
    baseline = rows[0]
    for row, answered in zip(rows, twists, strict=True):
        row["answered_ratio"] = round(row["answered"] / max(baseline["answered"], 1), 3)
        row["frames_answered_per_s_ratio"] = round(row["frames_answered_per_s"] /
                                                   max(baseline["frames_answered_per_s"], 1e-9), 3)
        if row["phase"] == "malformed":  # the same frames: the same twists?
            common = sorted(set(answered) & set(twists[0]))
            row["same_frames_answered"] = len(common)
            diffs = [float(np.max(np.abs(answered[k] - twists[0][k]))) for k in common]
            row["largest_twist_difference"] = max(diffs, default=None)
            row["frames_with_another_twist"] = sum(d > 0.0 for d in diffs)
            row["first_frame_with_another_twist"] = next((k for k, d in zip(common, diffs, strict=True) if d > 0.0),
                                                         None)
            row["frames_not_answered"] = sorted(set(twists[0]) - set(answered))
            row["largest_twist_component"] = max((float(np.max(np.abs(twists[0][k]))) for k in common),
                                                 default=None)
        print(json.dumps(row), flush=True)

if __name__ == "__main__":
    main()
