"""The servo loop's timing rules, over real Zenoh sessions on loopback against `ddvs serve` in a subprocess: the
watchdog measures frame arrival, frames in IDLE are not answered, counters never decrease, a stale twist is
withheld, and persistence never runs on the loop thread (an in-process node, since the test watches its threads)."""

from __future__ import annotations

import base64
import sys
import threading
import time
from itertools import pairwise
from pathlib import Path

import cv2
import numpy as np
from conftest import free_port
from test_service_node import Operator, running_service, scene, service_config, shifted

from ddvs_service.protocol import encode_image, image_from_array
from ddvs_service.protocol.ros import Header, Time
from ddvs_service.service.node import ServoNode

NO_WARMUP = ("--no-warmup",)  # the first frame after an upload must be slow: no kernels compiled ahead
STAMP0_NS = 1_000_000_000  # frame stamps of these tests: 1 s + k periods, far from any wall-clock stamp


def upload_command(image: np.ndarray) -> dict:
    ok, png = cv2.imencode(".png", image)
    assert ok
    return {"op": "set_reference", "source": "upload",
            "image": {"format": "png", "data": base64.b64encode(png.tobytes()).decode()}}


class Stream:
    """Publishes frames at `rate_hz` from a thread (as a camera does, whatever the service is doing)."""

    def __init__(self, op: Operator, frames: list[np.ndarray], rate_hz: float) -> None:
        self.op, self.frames, self.period = op, frames, 1.0 / rate_hz
        self.stamps: list[int] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run)

    def __enter__(self) -> Stream:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def payload(self, k: int) -> bytes:
        """The `k`-th frame (0, 1, …), stamped 1 s + `k` periods (recorded in `stamps`)."""
        stamp = STAMP0_NS + k * int(self.period * 1e9)
        self.stamps.append(stamp)
        return encode_image(image_from_array(self.frames[k % len(self.frames)], "mono8",
                                             Header(Time.from_ns(stamp), "camera")))

    def _run(self) -> None:
        t_next = time.monotonic()
        k = 0
        while not self._stop.is_set():
            self.op.frames.put(self.payload(k))
            k += 1
            t_next += self.period
            time.sleep(max(t_next - time.monotonic(), 0.0))


def answered(op: Operator, n: int, timeout_s: float = 120.0) -> None:
    """Wait until `n` frames were answered with a twist (the first after an upload takes seconds on a loaded host)."""
    deadline = time.monotonic() + timeout_s
    while len(op.twists) < n:
        assert time.monotonic() < deadline, f"{len(op.twists)} twists in {timeout_s} s"
        time.sleep(0.05)


def servo_frames(img: np.ndarray) -> list[np.ndarray]:
    """Views 6.5–7.5 px and 2° away from the reference: every frame keeps the servo SERVOING with a non-zero twist,
    and any two differ by at most 1 px (the service's error guard treats a jump of the error as a suspect fit)."""
    return [shifted(img, 7.0 + 0.5 * np.cos(a), 0.5 * np.sin(a), 2.0) for a in np.linspace(0, 2 * np.pi, 8,
                                                                                         endpoint=False)]


def test_watchdog_measures_frame_arrival_not_processing(tmp_path: Path) -> None:
    """The first frames after an upload are slow (first use of the kernels in this process, in the background
    search and the loop, which waits for the Taichi gate meanwhile: longer than `frame_timeout_s`) while the camera
    keeps sending at 50 Hz: no watchdog zero twist may interrupt the servo (the frames answered LOST while the
    search runs carry their own stamps), and once the camera stops the watchdog does send one."""
    port = free_port()
    config = service_config(port, tmp_path / "state").model_copy(update={"frame_timeout_s": 0.15})
    img = scene()
    with running_service(config, tmp_path, port, *NO_WARMUP) as (_, op):
        assert op.command(**upload_command(img)).ok
        assert op.command(op="start").ok
        with Stream(op, servo_frames(img), rate_hz=50.0) as stream:
            answered(op, 15)
            deadline = time.monotonic() + 120.0  # and servoing for a while: the search's pose adopted
            while sum(st["state"] == "SERVOING" for st in op.statuses) < 15:
                assert time.monotonic() < deadline, [st["state"] for st in op.statuses]
                time.sleep(0.05)
        sent = set(stream.stamps)
        time.sleep(0.1)  # the last frame's twist
        n_streamed = len(op.twist_stamps)
        time.sleep(0.6)  # > frame_timeout_s without a frame: the watchdog's zero twist
        slowest_ms = max(s["latency_ms"]["registration"] for s in op.statuses)
        assert slowest_ms > 1e3 * config.frame_timeout_s, f"no frame slower than the timeout ({slowest_ms:.0f} ms)"
        states = [s["state"] for s in op.statuses]
        servoing = states.index("SERVOING")
        assert set(states[:servoing]) <= {"LOST"} and set(states[servoing:]) == {"SERVOING"}, states
        # a zero twist answering no frame repeats the newest stamp published (each frame is answered once)
        stamps = op.twist_stamps
        watchdog = [k for k in range(1, n_streamed) if stamps[k] == stamps[k - 1]]
        assert not watchdog, f"zero twists while frames kept arriving: {len(watchdog)} (twists {watchdog})"
        assert set(stamps[:n_streamed]) <= sent
        assert all(np.any(st["twist"]) == (st["state"] == "SERVOING") for st in op.statuses[:n_streamed])
        assert len(op.twists) > n_streamed and not np.any(op.twists[-1]) and stamps[-1] == stamps[n_streamed - 1]


def test_a_stale_twist_is_withheld_and_counted(tmp_path: Path) -> None:
    """While the slow first frame after an upload is registered, more than two newer frames arrive: its twist would
    be older than the frames behind it, so it is not published; its status says so and `stale` counts it. The loop's
    slow frame waits for the background search's first compile (the Taichi gate): 0.28–0.43 s with the offline cache
    warm, too close to the default `frame_timeout_s` (0.3 s) to be late every time; 0.15 s, as the watchdog test."""
    port = free_port()
    config = service_config(port, tmp_path / "state").model_copy(update={"frame_timeout_s": 0.15})
    img = scene()
    with running_service(config, tmp_path, port, *NO_WARMUP) as (_, op):
        assert op.command(**upload_command(img)).ok
        assert op.command(op="start").ok
        with Stream(op, servo_frames(img), rate_hz=50.0):
            answered(op, 15)
        time.sleep(0.3)
    stale = [s for s in op.statuses if s["message"].startswith("stale")]
    assert stale, "no stale frame while the first registration took longer than two frame periods"
    assert op.statuses[-1]["counters"]["stale"] >= len(stale)
    published = set(op.twist_stamps)
    assert not [s["frame_stamp_ns"] for s in stale if s["frame_stamp_ns"] in published]


def test_frames_in_idle_are_not_answered(tmp_path: Path) -> None:
    port = free_port()
    config = service_config(port, tmp_path / "state")
    img = scene()
    with running_service(config, tmp_path, port) as (_, op):
        for _ in range(3):
            op.frames.put(encode_image(image_from_array(img, "mono8")))
            time.sleep(0.3)  # each frame taken before the next arrives (none superseded)
        assert not op.statuses and not op.twists, "a frame was answered while IDLE"
        assert op.command(op="set_reference", source="next_frame").ok
        status = op.send(img)
        assert status["state"] == "READY" and status["counters"]["idle"] == 3, status


def test_counters_never_decrease(tmp_path: Path) -> None:
    """Pairs of frames back to back: the second often arrives while the first is processed. `dropped` counts only
    frames superseded before processing, so no counter goes down, and at the end every frame is counted once."""
    port = free_port()
    config = service_config(port, tmp_path / "state")
    img = scene()
    frames = servo_frames(img)
    with running_service(config, tmp_path, port) as (_, op):
        assert op.command(**upload_command(img)).ok
        assert op.command(op="start").ok
        sent = 0
        for k in range(40):
            for frame in (frames[k % 8], frames[(k + 1) % 8]):
                op.frames.put(encode_image(image_from_array(frame, "mono8")))
                sent += 1
            time.sleep(0.05)
        time.sleep(0.5)
        final = op.command(op="get_state").data["last_status"]["counters"]
    names = ("frames", "dropped", "rejected", "stale", "idle")
    for name in names:
        series = [s["counters"][name] for s in op.statuses]
        assert all(b >= a for a, b in pairwise(series)), f"{name} decreased: {series}"
    assert final["frames"] + final["dropped"] + final["rejected"] + final["idle"] == sent, final


def test_persistence_is_off_the_loop_thread(tmp_path: Path) -> None:
    """A node served on this thread: every write into its state directory (temporary file, rename, removal; each
    fsync'ed) happens on another thread, and the files are complete once the node has stopped."""
    port = free_port()
    config = service_config(port, tmp_path / "state")
    state_dir = str(config.state_dir)
    writers: list[tuple[str, int]] = []
    watching = [True]

    def audit(event: str, args: tuple) -> None:
        if not (watching[0] and event in ("open", "os.rename", "os.remove") and str(args[0]).startswith(state_dir)):
            return
        if event != "open" or "w" in str(args[1]) or (isinstance(args[2], int) and args[2] & 0o3):
            writers.append((event, threading.get_ident()))

    sys.addaudithook(audit)
    img = scene()
    replies: list[bool] = []
    stop = threading.Event()

    def operate() -> None:
        op = Operator(port)
        try:
            deadline = time.monotonic() + 60.0
            while True:  # until the node's queryable answers (no reply at all before it is declared)
                try:
                    if op.command(op="get_state", timeout=1.0).ok:
                        break
                except AssertionError:
                    assert time.monotonic() < deadline, "the node did not come up"
            for command in (upload_command(img), {"op": "start"},
                            {"op": "set_config", "config": {"control": {"gains": 0.3}}}, {"op": "stop"}):
                replies.append(op.command(**command).ok)
            op.send(shifted(img, 3.0, 2.0))
            replies.append(op.command(op="reset").ok)
        finally:
            op.close()
            stop.set()

    node = ServoNode(config)
    operator = threading.Thread(target=operate)
    operator.start()
    try:
        node.run(stop)  # this thread is the loop thread
    finally:
        operator.join()
        watching[0] = False
    assert replies == [True] * 5
    loop = threading.get_ident()
    assert writers and not [w for w in writers if w[1] == loop], f"the loop thread wrote: {writers}"
    state = ServoNode(config)  # what a restart reads
    assert state.config.control.gains == 0.3 and state.pipeline.reference is None
    state.writer.close()


def test_status_only_on_state_changes_when_not_every_frame(tmp_path: Path) -> None:
    """`status_every_frame: false`: every frame is still answered with a twist, a Status only when the state changes."""
    port = free_port()
    config = service_config(port, tmp_path / "state").model_copy(update={"status_every_frame": False})
    img = scene()
    frames = servo_frames(img)
    with running_service(config, tmp_path, port) as (_, op):
        assert op.command(op="set_reference", source="next_frame").ok
        assert op.send(img)["state"] == "READY"  # a new state: a Status
        assert op.command(op="start").ok
        for k in range(6):
            op.frames.put(encode_image(image_from_array(frames[k % len(frames)], "mono8")))
            time.sleep(0.2)
        answered(op, 7)
    assert [s["state"] for s in op.statuses] == ["READY", "SERVOING"], [s["state"] for s in op.statuses]
    assert all(np.any(t) for t in op.twists[1:7])
