"""`ddvs monitor`: rates and the newest status over real Zenoh sessions; `--once` JSON and its exit codes."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
from conftest import free_port

from clients.monitor import Monitor, render
from ddvs_service.protocol import (
    CompressedImage,
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
    encode_compressed_image,
    encode_image,
    encode_twist_stamped,
    image_from_array,
    open_session,
)

ROOT = Path(__file__).resolve().parents[1]
KEYS = Keys("ddvs", "montest")


def _publish(port: int, stop: threading.Event, hz: float = 50.0, rejected_per_status: int = 0) -> None:
    """Status and twist at `hz`, frames at `hz / 2` (half of them JPEG CompressedImage on camera/image/compressed),
    until `stop`; the `rejected` counter grows by `rejected_per_status` with each status."""
    with open_session(SessionConfig(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        names = ("servo_status", "servo_twist", "camera_image", "camera_image_compressed")
        pubs = {name: declare_publisher(session, KEYS, name) for name in names}
        image = encode_image(image_from_array(np.zeros((24, 32), np.uint8), "mono8"))
        jpeg = cv2.imencode(".jpg", np.zeros((24, 32), np.uint8))[1].tobytes()
        compressed = encode_compressed_image(CompressedImage(Header(Time.now(), "camera"), "jpeg", jpeg))
        seq = 0
        while not stop.is_set():
            status = Status(robot=KEYS.robot, state="SERVOING", frame_stamp_ns=seq, seq=seq,
                            error=[0.01, 0, 0, 0, 0, 0], error_norm=0.01, iterations=2, residual_rms=1.0,
                            inlier_ratio=0.9, twist=[0.001, 0, 0, 0, 0, 0.002],
                            latency_ms=Latency(decode=0.1, registration=5.0, control=0.3, publish=0.1, total=5.5),
                            counters=Counters(frames=seq, dropped=seq // 2, rejected=seq * rejected_per_status),
                            backend="vulkan")
            pubs["servo_status"].put(dump(status))
            pubs["servo_twist"].put(encode_twist_stamped(TwistStamped(Header(Time.now(), "camera"), [0, 0, 0],
                                                                      [0, 0, 0])))
            if seq % 4 == 0:
                pubs["camera_image"].put(image)
            elif seq % 4 == 2:
                pubs["camera_image_compressed"].put(compressed)
            seq += 1
            stop.wait(1.0 / hz)


def test_snapshot_has_the_newest_status_and_the_arrival_rates():
    """Rates of arrival, and of the counters of a service under a flood: ~100 rejected frames per status at 50
    statuses/s (5000 frames/s) and one superseded frame every other status, shown as frames/s."""
    port = free_port()
    stop = threading.Event()
    publisher = threading.Thread(target=_publish, args=(port, stop, 50.0, 100), daemon=True)
    publisher.start()
    try:
        time.sleep(0.3)
        with open_session(SessionConfig(connect=[f"tcp/127.0.0.1:{port}"])) as session:
            monitor = Monitor(session, KEYS, window=1.0)
            assert monitor.status_received.wait(5.0)
            time.sleep(1.2)
            snap = monitor.snapshot()
            monitor.close()
    finally:
        stop.set()
        publisher.join(5)
    assert snap["state"] == "SERVOING" and snap["error_norm"] == 0.01 and snap["seq"] > 0
    assert snap["latency_ms"]["registration"] == 5.0 and snap["backend"] == "vulkan"
    rates = snap["rates_hz"]
    assert 30 <= rates["status"] <= 52 and 30 <= rates["twists"] <= 52, rates
    assert 15 <= rates["frames"] <= 26, rates
    assert 0.6 * 5000 <= rates["rejected"] <= 5000 * 1.1 and 0.6 * 25 <= rates["dropped"] <= 25 * 1.1, rates
    text = render(snap, KEYS.base)
    assert "SERVOING" in text and "1.000e-02" in text and "registration 5.00" in text and "backend      vulkan" in text
    assert "rejected" in text and "superseded" in text


def _once(port: int, timeout: float) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "ddvs.cli", "monitor", "--once", "--window", "0.5", "--timeout", str(timeout),
           "--robot", KEYS.robot, "--connect", f"tcp/127.0.0.1:{port}"]
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=60)


def test_once_prints_json_or_exits_2_without_a_service():
    port = free_port()
    assert _once(port, 0.5).returncode == 2
    stop = threading.Event()
    publisher = threading.Thread(target=_publish, args=(port, stop), daemon=True)
    publisher.start()
    try:
        result = _once(port, 10.0)
    finally:
        stop.set()
        publisher.join(5)
    assert result.returncode == 0, result.stderr
    snap = json.loads(result.stdout)
    assert snap["state"] == "SERVOING" and snap["rates_hz"]["status"] > 10
