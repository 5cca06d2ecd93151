"""Floods from an authorised camera, and the order of twist stamps, over real Zenoh sessions on loopback against
`ddvs serve` in a subprocess.

A flood of malformed frames beside the valid stream: every valid frame is still answered with its own twist (no
zero twist answers a rejected frame, none interleaves with the servo's), the rejections are counted and reported at
a bounded rate. A flood of valid frames faster than the loop: the surplus is superseded (counted `dropped`), never
queued. After the no-frame watchdog's zero twist, the next frames' twists never carry an older stamp.
(`benchmarks/bench_flood.py` measures the flood at 5000 frames/s against a baseline.)
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
from conftest import free_port
from test_service_loop import STAMP0_NS, Stream, answered, servo_frames
from test_service_node import Operator, Service, scene, service_config

from ddvs_service.protocol import encode_image, image_from_array
from ddvs_service.protocol.ros import Header, Time
from ddvs_service.service.robot import REJECTION_REPORT_S


def malformed_payloads(img: np.ndarray) -> list[bytes]:
    """Frames the service must reject: garbage, truncated CDR, an unknown encoding, the wrong size."""
    good = encode_image(image_from_array(img, "mono8", Header(Time.from_ns(STAMP0_NS), "camera")))
    return [b"\x00\x01\x00\x00garbage", good[: len(good) // 2], good.replace(b"mono8", b"mnoo8", 1),
            encode_image(image_from_array(img[:, :200].copy(), "mono8"))]


class Flood(Stream):
    """Publishes `payloads` in turn on the camera key at `rate_hz` from a thread, until closed; `sent` counts."""

    def __init__(self, op: Operator, payloads: list[bytes], rate_hz: float) -> None:
        super().__init__(op, [], rate_hz)
        self.payloads = payloads
        self.sent = 0

    def payload(self, k: int) -> bytes:
        self.sent = k + 1
        return self.payloads[k % len(self.payloads)]


@contextmanager
def servoing(tmp_path: Path) -> Iterator[tuple[Operator, np.ndarray, list[str]]]:
    """`ddvs serve` servoing to the scene (the reference from the next frame), an operator, and — once the block
    has ended and the service has stopped (exit 0) — its stderr as the list's one item."""
    port = free_port()
    config = service_config(port, tmp_path / "state")
    img = scene()
    service = Service(config, tmp_path)
    op = Operator(port)
    stderr: list[str] = []
    try:
        service.wait_ready(op)
        start_servo(op, img)
        yield op, img, stderr
    finally:
        code, text = service.stop()
        op.close()
        stderr.append(text)
    assert code == 0


def start_servo(op: Operator, img: np.ndarray) -> None:
    """The reference is the current frame (no global search): frames are answered from the first one on."""
    assert op.command(op="set_reference", source="next_frame").ok
    assert op.send(img)["state"] == "READY"
    assert op.command(op="start").ok


@pytest.mark.slow
def test_a_flood_of_malformed_frames_changes_no_twist(tmp_path: Path) -> None:
    with servoing(tmp_path) as (op, img, stderr):
        n_twists, n_statuses = len(op.twists), len(op.statuses)
        with Stream(op, servo_frames(img), rate_hz=15.0) as stream:
            answered(op, n_twists + 5)
            with Flood(op, malformed_payloads(img), rate_hz=2000.0) as flood:
                time.sleep(4.0)
            time.sleep(0.5)
        time.sleep(REJECTION_REPORT_S + 0.5)  # the last report
    sent = set(stream.stamps)
    stamps = op.twist_stamps[n_twists:]
    assert set(stamps) <= sent, f"{len(set(stamps) - sent)} twists answered no valid frame"
    statuses = op.statuses[n_statuses:]
    # every valid frame answered, or superseded by the next valid one (this process's threads, the flood's among them,
    # bunch the stream's frames on a loaded host; benchmarks/bench_flood.py floods from another process)
    dropped = statuses[-1]["counters"]["dropped"] - op.statuses[n_statuses - 1]["counters"]["dropped"]
    assert len(stamps) + dropped >= len(sent) - 1 and len(stamps) >= 0.75 * len(sent), (len(stamps), dropped, len(sent))
    frames = [s for s in statuses if s["frame_stamp_ns"] in sent]
    assert all(s["state"] == "SERVOING" and np.any(s["twist"]) for s in frames)
    zero = [k for k in range(n_twists, len(op.twists)) if not np.any(op.twists[k])]
    assert zero == list(range(len(op.twists) - 2, len(op.twists))), zero  # only the watchdog's and the shutdown's
    reports = [s for s in statuses if "rejected" in s["message"]]
    seconds = 4.5 + REJECTION_REPORT_S
    assert 2 <= len(reports) <= seconds / REJECTION_REPORT_S + 1, len(reports)
    assert flood.sent > 1000
    assert reports[-1]["counters"]["rejected"] >= 0.95 * flood.sent, (reports[-1]["counters"], flood.sent)
    warnings = [line for line in stderr[0].splitlines()
                if line.startswith("{") and "rejected" in json.loads(line)["msg"]]
    assert 2 <= len(warnings) <= seconds / REJECTION_REPORT_S + 1, len(warnings)


@pytest.mark.slow
def test_a_flood_of_valid_frames_is_superseded_not_queued(tmp_path: Path) -> None:
    with servoing(tmp_path) as (op, img, _):
        with Stream(op, servo_frames(img), rate_hz=1000.0) as stream:
            time.sleep(3.0)
        n_answered = len(op.twist_stamps)  # the camera has stopped: every frame is published
        time.sleep(0.5)
        final = op.command(op="get_state").data["last_status"]
    during = set(op.twist_stamps[:n_answered]) & set(stream.stamps)
    assert len(during) >= 3 * 5, f"{len(during)} frames answered in 3 s of a flood"  # the servo keeps answering
    after = set(op.twist_stamps[n_answered:]) - set(op.twist_stamps[:n_answered])
    # at most a twist on its way, the frame being registered and the latest one waiting (a queue answers hundreds)
    assert len(after) <= 3, f"{len(after)} frames answered after the flood ended: frames were queued"
    assert final["counters"]["dropped"] > len(stream.stamps) / 2, (final["counters"], len(stream.stamps))
    assert all(b >= a for a, b in pairwise(op.twist_stamps)), "answered out of order"


def test_twist_stamps_never_decrease_across_the_watchdog(tmp_path: Path) -> None:
    """Frames stamped on the camera's clock (1 s + k periods, far behind the wall clock); the camera pauses longer
    than `frame_timeout_s` (the watchdog's zero twist) and resumes; a `stop` adds another zero twist."""
    with servoing(tmp_path) as (op, img, _):
        frames = servo_frames(img)
        n0 = len(op.twist_stamps)
        stamp = STAMP0_NS
        for burst in range(3):
            for k in range(5):
                stamp += 33_000_000
                op.send_raw(encode_image(image_from_array(frames[k], "mono8", Header(Time.from_ns(stamp), "camera"))))
            n = len(op.twists)
            time.sleep(1.0)  # > frame_timeout_s
            assert len(op.twists) == n + 1 and not np.any(op.twists[-1]), f"no watchdog zero twist in burst {burst}"
        assert op.command(op="stop").ok
        time.sleep(0.2)
    stamps = op.twist_stamps[n0:]
    # per burst 5 frames and the watchdog's, then the stop's and the shutdown's (a host so loaded that a frame's round
    # trip exceeds `frame_timeout_s` adds a watchdog zero twist between two frames)
    assert len(stamps) >= 3 * 6 + 2, stamps
    assert all(b >= a for a, b in pairwise(stamps)), f"a twist stamp went back: {stamps}"
