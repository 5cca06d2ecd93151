"""Latency overhead of TLS against plain TCP for 320×240 mono8 frames, publisher → router → subscriber (issues 10, 22).

Three processes per measurement: a Zenoh router (a Python session in router mode), a subscriber (this script with
`--subscribe`) and the publisher (this script). Transports, all on loopback and measured in the same run:
- `tcp`: plain TCP, no access control;
- `tls`: mutual TLS (certificates from `scripts/make_dev_certs.sh`), no access control;
- `tls+acl`: mutual TLS and the generated deny-by-default rules of `ddvs_service.protocol.security` (plant → service);
- `tls+acl+audit`: the same rules with the real `ddvs router`, whose audit reads Zenoh's access-control trace.
One-way latency = subscriber's `time.time_ns()` at the sample callback − the frame's header stamp (publisher's
`time.time_ns()` just before `put`; one host, one clock). Shared memory is off so that every frame crosses the link.
Rounds alternate the transports so that load from other processes on the machine hits all of them alike.

    .venv/bin/python benchmarks/bench_tls.py [--frames 300] [--rate 100] [--rounds 3] [--markdown]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
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

import zenoh  # noqa: E402

from ddvs_service.protocol import Header, Keys, Time, decode_image, encode_image, image_from_array  # noqa: E402
from ddvs_service.protocol.security import (  # noqa: E402
    TlsFiles,
    certificate_identities,
    client_config,
    router_config,
)

W, H = 320, 240
KEYS = Keys("ddvs", "bench")
TRANSPORTS = ("tcp", "tls", "tls+acl", "tls+acl+audit")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def open_config(config: dict[str, Any]) -> zenoh.Session:
    out = zenoh.Config()
    for key, value in {**config, "transport/shared_memory/enabled": False}.items():
        out.insert_json5(key, json.dumps(value))
    return zenoh.open(out)


def configs(transport: str, certs: Path) -> dict[str, dict[str, Any]]:
    """Router, publisher (plant) and subscriber (service) configurations of one transport on a fresh port."""
    port = free_port()
    if transport == "tcp":
        endpoint = f"tcp/127.0.0.1:{port}"
        router: dict[str, Any] = {"mode": "router", "listen": {"endpoints": [endpoint]},
                                  "scouting": {"multicast": {"enabled": False}}}
        return {"router": router, "plant": client_config("plant", [endpoint]),
                "service": client_config("service", [endpoint])}
    endpoint = f"tls/localhost:{port}"
    router = router_config(KEYS, certificate_identities(KEYS.base), [endpoint], TlsFiles.for_role(certs, "router"))
    if transport == "tls":
        del router["access_control"]
    return {"router": router, **{role: client_config(role, [endpoint], TlsFiles.for_role(certs, role))
                                 for role in ("plant", "service")}}


def run_router(config_file: str) -> int:
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    session = open_config(json.loads(Path(config_file).read_text()))
    print("ready", flush=True)
    stop.wait()
    session.close()
    return 0


def run_subscriber(config_file: str, count: int, out_file: str) -> int:
    """Collect `count` latencies (ns) after the first frame, write them as JSON; prints `ready` at the first."""
    latencies: list[int] = []
    done = threading.Event()
    first = threading.Event()

    def on_frame(sample: zenoh.Sample) -> None:
        arrival = time.time_ns()
        stamp = decode_image(sample.payload.to_bytes()).header.stamp.to_ns()
        if not first.is_set():
            first.set()
            return
        if len(latencies) < count:
            latencies.append(arrival - stamp)
        if len(latencies) >= count:
            done.set()

    session = open_config(json.loads(Path(config_file).read_text()))
    sub = session.declare_subscriber(KEYS.camera_image, on_frame)
    first.wait(60)
    print("ready", flush=True)
    done.wait(120)
    sub.undeclare()
    session.close()
    Path(out_file).write_text(json.dumps(latencies))
    return 0 if len(latencies) >= count else 1


def spawn(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, __file__, *args], stdout=subprocess.PIPE, text=True)


def wait_line(proc: subprocess.Popen[str], what: str, first_word: str = "ready") -> None:
    assert proc.stdout is not None
    line = proc.stdout.readline().strip()
    if line.split(" ", 1)[0] != first_word:
        raise SystemExit(f"{what} did not start (said {line!r}, exit code {proc.poll()})")


def measure(transport: str, certs: Path, work: Path, frames: int, rate: float) -> list[int]:
    cfg = configs(transport, certs)
    files = {}
    for name, config in cfg.items():
        files[name] = work / f"{transport}-{name}.json"
        files[name].write_text(json.dumps(config))
    out = work / f"{transport}-latencies.json"
    if transport.endswith("+audit"):
        router = subprocess.Popen([sys.executable, "-m", "ddvs.cli", "router", "--zenoh-config", str(files["router"]),
                                   "--listen", cfg["router"]["listen"]["endpoints"][0]], stdout=subprocess.PIPE,
                                  stderr=subprocess.DEVNULL, text=True, cwd=ROOT)
    else:
        router = spawn("--router", str(files["router"]))
    try:
        wait_line(router, "router", "router" if transport.endswith("+audit") else "ready")
        subscriber = spawn("--subscribe", str(files["service"]), "--count", str(frames), "--out", str(out))
        publisher = open_config(cfg["plant"])
        try:
            pub = publisher.declare_publisher(KEYS.camera_image, congestion_control=zenoh.CongestionControl.BLOCK)
            rng = np.random.default_rng(0)
            image = rng.integers(0, 256, (H, W), dtype=np.uint8)
            ready = threading.Thread(target=wait_line, args=(subscriber, "subscriber"))
            ready.start()
            while ready.is_alive():  # until the subscriber has its first frame (routes established)
                pub.put(encode_image(image_from_array(image, "mono8", Header(Time.now(), "camera"))))
                ready.join(0.05)
            period = 1.0 / rate
            next_t = time.monotonic()
            while subscriber.poll() is None:
                next_t += period
                time.sleep(max(0.0, next_t - time.monotonic()))
                pub.put(encode_image(image_from_array(image, "mono8", Header(Time.now(), "camera"))))
            if subscriber.returncode != 0:
                raise SystemExit(f"subscriber failed over {transport} (exit code {subscriber.returncode})")
        finally:
            publisher.close()
    finally:
        router.send_signal(signal.SIGTERM)
        router.wait(30)
    return list(json.loads(out.read_text()))


def summary(latencies_ns: list[int]) -> dict[str, float]:
    ms = np.asarray(latencies_ns, dtype=np.float64) / 1e6
    return {"n": int(ms.size), "median_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)),
            "mean_ms": float(ms.mean()), "max_ms": float(ms.max())}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--router", metavar="CONFIG", help=argparse.SUPPRESS)
    parser.add_argument("--subscribe", metavar="CONFIG", help=argparse.SUPPRESS)
    parser.add_argument("--count", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    parser.add_argument("--frames", type=int, default=300, help="frames measured per transport and round")
    parser.add_argument("--rate", type=float, default=100.0, help="frames per second")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--markdown", action="store_true", help="print a markdown table")
    args = parser.parse_args()
    if args.router:
        return run_router(args.router)
    if args.subscribe:
        return run_subscriber(args.subscribe, args.count, args.out)

    with tempfile.TemporaryDirectory(prefix="bench_tls_") as tmp:
        work = Path(tmp)
        subprocess.run(["bash", str(ROOT / "scripts" / "make_dev_certs.sh"), str(work / "certs"), "--robot",
                        KEYS.robot, "--prefix", KEYS.prefix], check=True, capture_output=True)
        pooled: dict[str, list[int]] = {t: [] for t in TRANSPORTS}
        for _ in range(args.rounds):
            for transport in TRANSPORTS:
                pooled[transport] += measure(transport, work / "certs", work, args.frames, args.rate)
    results = {t: summary(v) for t, v in pooled.items()}
    base = results["tcp"]
    for t in TRANSPORTS:
        results[t]["median_overhead_ms"] = results[t]["median_ms"] - base["median_ms"]
        results[t]["p99_overhead_ms"] = results[t]["p99_ms"] - base["p99_ms"]
    report = {"frame": f"{W}x{H} mono8 ({W * H} B)", "rate_hz": args.rate, "rounds": args.rounds,
              "machine": f"{platform.machine()}, {os.cpu_count()} CPUs", "results": results}
    print(json.dumps(report))
    if args.markdown:
        print("\n| transport | n | median ms | p99 ms | median overhead ms | p99 overhead ms |")
        print("|---|---|---|---|---|---|")
        for t, r in results.items():
            print(f"| {t} | {r['n']} | {r['median_ms']:.3f} | {r['p99_ms']:.3f} | {r['median_overhead_ms']:+.3f} | "
                  f"{r['p99_overhead_ms']:+.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
