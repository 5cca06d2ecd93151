"""The servo service over real Zenoh sessions on loopback: every state transition, command and bad input.

The service runs as its own process (`ddvs serve`; Taichi compiles kernels on the main thread only); the test plays
camera and operator through its own Zenoh session. Frames are a real photograph (Oxford boat) warped by known
homographies.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import pytest
import zenoh
from conftest import free_port

from ddvs_service.protocol import (
    Command,
    Keys,
    Reply,
    SessionConfig,
    decode_image,
    decode_twist_stamped,
    dump,
    encode_image,
    image_from_array,
    open_session,
)
from ddvs_service.protocol.ros import Header, Time
from ddvs_service.service.config import ServiceConfig
from ddvs_service.service.inbox import Inbox
from sim.textures import texture_path

W, H, F = 320, 240, 420.0
BOAT = texture_path("boat")


def scene() -> np.ndarray:
    img = cv2.imread(str(BOAT), cv2.IMREAD_GRAYSCALE)
    assert img is not None, f"missing dataset image {BOAT}"
    return cv2.resize(img[100:580, 150:790], (W, H), interpolation=cv2.INTER_AREA)


def shifted(img: np.ndarray, dx: float, dy: float, angle_deg: float = 0.0) -> np.ndarray:
    A = cv2.getRotationMatrix2D(((W - 1) / 2, (H - 1) / 2), angle_deg, 1.0)
    A[:, 2] += (dx, dy)
    return cv2.warpAffine(img, A, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def service_config(port: int, state_dir: Path) -> ServiceConfig:
    return ServiceConfig.model_validate({
        "robot": "t0",
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"]},
        "state_dir": str(state_dir),
        "intrinsics": {"fx": F, "fy": F, "cx": (W - 1) / 2, "cy": (H - 1) / 2, "width": W, "height": H},
        "registration": {"template_size": [100, 80]},
        "frame_timeout_s": 0.3,
    })


def answered_frames(session: zenoh.Session, key: str) -> zenoh.Publisher:
    """A frame publisher whose every frame reaches the service: BLOCK congestion control. The camera key's own QoS
    (DROP, `TOPICS`) lets Zenoh drop a frame it cannot queue in time; a test that waits for each frame's answer must
    not lose one."""
    return session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)


class Operator:
    """The test's side: publishes frames, sends commands, collects twists and statuses."""

    def __init__(self, port: int, robot: str = "t0") -> None:
        self.keys = Keys("ddvs", robot)
        self.session = open_session(SessionConfig(connect=[f"tcp/127.0.0.1:{port}"]))
        self.twists: list[np.ndarray] = []
        self.twist_stamps: list[int] = []  # header stamp of each twist (ns): its frame's, or for a zero twist that
        # answers no frame (watchdog, stop, shutdown) the newest stamp published before it
        self.statuses: list[dict] = []
        self._subs = [
            self.session.declare_subscriber(self.keys.key("servo_twist"), self._on_twist),
            self.session.declare_subscriber(self.keys.key("servo_status"), self._on_status),
        ]
        self.frames = answered_frames(self.session, self.keys.key("camera_image"))
        self._stamp = 0

    def _on_twist(self, sample: zenoh.Sample) -> None:
        twist = decode_twist_stamped(sample.payload.to_bytes())
        self.twist_stamps.append(twist.header.stamp.to_ns())
        self.twists.append(twist.vector)

    def _on_status(self, sample: zenoh.Sample) -> None:
        self.statuses.append(json.loads(sample.payload.to_bytes()))

    def command(self, raw: bytes | None = None, timeout: float = 20.0, **kwargs: object) -> Reply:
        payload = dump(Command(**kwargs)) if raw is None else raw
        for reply in self.session.get(self.keys.key("servo_command"), payload=payload, timeout=timeout):
            assert reply.ok is not None, "the service answered with a Zenoh error"
            return Reply.model_validate_json(reply.ok.payload.to_bytes())
        raise AssertionError("no reply from the service")

    def send(self, image: np.ndarray) -> dict:
        """Publish one frame and wait for the status and the twist it produced."""
        self._stamp += 1
        header = Header(Time.from_ns(self._stamp * 33_000_000), "camera")
        return self.send_raw(encode_image(image_from_array(image, "mono8", header)))

    def send_raw(self, payload: bytes) -> dict:
        """Publish one valid frame's payload on the image key; wait for the status and the twist it yields."""
        n_status, n_twist = len(self.statuses), len(self.twists)
        self.frames.put(payload)
        deadline = time.monotonic() + 20.0
        while len(self.statuses) <= n_status or len(self.twists) <= n_twist:
            assert time.monotonic() < deadline, "no status and twist from the service"
            time.sleep(0.002)
        return self.statuses[-1]

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self.frames.undeclare()
        self.session.close()


class Service:
    """`ddvs serve` in a subprocess with a given configuration; `stop()` sends SIGTERM and returns the exit code."""

    def __init__(self, config: ServiceConfig, tmp_path: Path, *args: str) -> None:
        cfg_file = tmp_path / "serve.json"
        cfg_file.write_text(config.model_dump_json())
        env = {k: v for k, v in os.environ.items() if not k.startswith("DDVS_ZENOH_")}
        self.proc = subprocess.Popen([sys.executable, "-X", "faulthandler", "-m", "ddvs.cli", "serve",
                                      "--config", str(cfg_file), *args], stderr=subprocess.PIPE, text=True, env=env)

    def wait_ready(self, op: Operator, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while True:
            assert self.proc.poll() is None, f"service exited: {self.proc.stderr.read() if self.proc.stderr else ''}"
            try:
                if op.command(op="get_state", timeout=1.0).ok:
                    return
            except AssertionError:
                pass
            assert time.monotonic() < deadline, "service did not come up"
            time.sleep(0.2)

    def stop(self) -> tuple[int, str]:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            code = self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired as exc:
            self.proc.send_signal(signal.SIGABRT)  # faulthandler prints every thread's stack
            _, stderr = self.proc.communicate(timeout=30)
            raise AssertionError(f"the service ignored SIGTERM for 30 s; its stacks:\n{stderr[-8000:]}") from exc
        return code, self.proc.stderr.read() if self.proc.stderr else ""


@contextmanager
def running_service(config: ServiceConfig, tmp_path: Path, port: int,
                    *args: str) -> Iterator[tuple[Service, Operator]]:
    """`ddvs serve --config … *args` and an operator connected to it; the service must exit 0 at the end."""
    service = Service(config, tmp_path, *args)
    op = Operator(port)
    try:
        service.wait_ready(op)
        yield service, op
    except BaseException:
        _, log = service.stop()
        print(f"the service's log, the test having failed:\n{log[-8000:]}")  # pytest shows it beside the failure
        raise
    finally:
        op.close()
    code, log = service.stop()
    assert code == 0, f"the service exited with {code}:\n{log[-8000:]}"


@pytest.fixture
def served(tmp_path: Path) -> Iterator[tuple[Service, Operator, ServiceConfig]]:
    port = free_port()
    config = service_config(port, tmp_path / "state")
    with running_service(config, tmp_path, port) as (service, op):
        yield service, op, config


def converge(op: Operator, image: np.ndarray) -> dict:
    """Send `image` for `settle_frames` + `converge_frames` (10 + 3) frames: a servo at zero error is then CONVERGED
    (an earlier frame's error has left the mean the stop compares)."""
    for _ in range(13):
        status = op.send(image)
    return status


def past_lost(op: Operator, image: np.ndarray, limit: int = 2000) -> tuple[dict, int]:
    """Send `image` until the state leaves LOST (re-acquisition runs beside the service's loop: how many frames it
    answers meanwhile depends on the search's time), each LOST frame with a zero twist; the first status that is
    not LOST and the count of LOST ones before it."""
    for lost in range(limit):
        status = op.send(image)
        if status["state"] != "LOST":
            return status, lost
        assert not np.any(op.twists[-1]), status
    raise AssertionError(f"still LOST after {limit} frames: {status}")


def state_of(op: Operator) -> str:
    reply = op.command(op="get_state")
    assert reply.ok and reply.data is not None
    return str(reply.data["state"])


def test_state_transitions_and_twists(served: tuple[Service, Operator, ServiceConfig]) -> None:
    _, op, _ = served
    img = scene()
    assert state_of(op) == "IDLE"
    refused = op.command(op="start")
    assert not refused.ok and "no reference" in (refused.error or "")
    assert state_of(op) == "IDLE"

    assert op.command(op="set_reference", source="next_frame").ok
    status = op.send(img)
    assert status["state"] == "READY"
    assert state_of(op) == "READY"
    assert op.command(op="start").ok

    status = op.send(img)  # identical image: zero error, but CONVERGED only after `converge_frames` (3) frames
    assert status["state"] == "SERVOING" and status["error_norm"] < 1e-3
    status = converge(op, img)
    assert status["state"] == "CONVERGED" and status["error_norm"] < 1e-3
    assert not np.any(op.twists[-1])

    # The camera jumped 6 px and 3° in one frame (90°/s, beyond any servoed motion): a suspect fit, held still (LOST,
    # zero twist) while the global initialiser re-acquires in the background (every frame meanwhile answered at
    # once: how many depends on the search's time) and until 30 frames agree on the new error (the error guard),
    # then the servo resumes.
    moved = shifted(img, 6.0, -4.0, 3.0)
    status = op.send(moved)
    assert status["state"] == "LOST" and "suspect fit" in status["message"] and not np.any(op.twists[-1]), status
    status, _ = past_lost(op, moved)
    assert status["state"] == "SERVOING", status
    assert status["error_norm"] > 5e-3
    twist = op.twists[-1]
    assert np.all(np.isfinite(twist)) and np.linalg.norm(twist) > 0
    lat = status["latency_ms"]
    assert set(lat) == {"decode", "registration", "control", "publish", "total", "cpu"} and lat["total"] > 0
    assert 0 < lat["cpu"] < 10 * lat["total"], lat  # the process's CPU time over the frame's work (several threads)

    rng = np.random.default_rng(1)
    status = op.send(rng.integers(0, 256, (H, W), dtype=np.uint8))  # unrelated image → LOST, zero twist
    assert status["state"] == "LOST", status
    assert not np.any(op.twists[-1])

    status, held = past_lost(op, shifted(img, 2.0, 1.0))  # target back in view: re-acquired, held still until
    assert status["state"] in ("SERVOING", "CONVERGED") and held >= 2, (held, status)  # 3 tracked frames confirm it

    assert op.command(op="stop").ok
    assert state_of(op) == "STOPPED"
    assert op.send(shifted(img, 2.0, 1.0))["state"] == "STOPPED"
    assert not np.any(op.twists[-1])
    assert op.command(op="reset").ok
    assert state_of(op) == "IDLE"


def test_bad_frames_are_rejected_and_counted(served: tuple[Service, Operator, ServiceConfig]) -> None:
    _, op, _ = served
    img = scene()
    assert op.command(op="set_reference", source="next_frame").ok
    op.send(img)
    assert op.command(op="start").ok
    base = converge(op, img)["counters"]["rejected"]
    n_twists = len(op.twists)
    bad_payloads = [
        b"\x00\x01\x00\x00garbage",
        encode_image(image_from_array(img[:, :200].copy(), "mono8")),  # wrong size
        encode_image(image_from_array(img, "mono8"))[:-100],  # truncated
        encode_image(image_from_array(img, "mono8")).replace(b"mono8", b"mnoo8", 1),  # unknown encoding
    ]
    for payload in bad_payloads:
        op.frames.put(payload)
    assert op.send(img)["state"] == "CONVERGED"  # still serving
    deadline = time.monotonic() + 10.0  # rejections are reported at most once a second: both reports within 2 s
    while not any(s["counters"]["rejected"] == base + len(bad_payloads) for s in op.statuses):
        assert time.monotonic() < deadline, [s["message"] for s in op.statuses[-5:]]
        time.sleep(0.05)
    reports = [s for s in op.statuses if "rejected" in s["message"]]
    assert 1 <= len(reports) <= 2 and "mnoo8" in reports[-1]["message"], reports  # with the newest reason
    assert all(s["state"] == "CONVERGED" for s in reports)  # state unchanged
    assert len(op.twists) == n_twists + 1  # a rejected frame is answered by no twist: only the good frame was


def test_commands_and_configuration_are_validated(served: tuple[Service, Operator, ServiceConfig]) -> None:
    _, op, _ = served
    before = op.command(op="get_config").data
    for raw in (b"not json", b'{"op": "fly"}', b'{"protocol_version": 99, "op": "start"}', b"[" * 10_000):
        reply = op.command(raw=raw)
        assert not reply.ok and reply.error
    unstable = op.command(op="set_config", config={"control": {"gains": [0.4, 0.4, 0.4, -0.4, 0.4, 0.4]}})
    assert not unstable.ok and "(27)" in (unstable.error or "")
    wrong_type = op.command(op="set_config", config={"frame_timeout_s": "soon"})
    assert not wrong_type.ok
    unknown = op.command(op="set_config", config={"speed": 3})
    assert not unknown.ok
    assert op.command(op="get_config").data == before  # a rejected change changes nothing
    ok = op.command(op="set_config", config={"control": {"law": "dvs_reduced", "gains": 0.5}})
    assert ok.ok and ok.data is not None and ok.data["control"]["law"] == "dvs_reduced"
    assert op.command(op="get_config").data["control"]["gains"] == 0.5


def test_frame_timeout_publishes_zero_twist(served: tuple[Service, Operator, ServiceConfig]) -> None:
    _, op, _ = served
    img = scene()
    assert op.command(op="set_reference", source="next_frame").ok
    op.send(img)
    assert op.command(op="start").ok
    op.send(shifted(img, 8.0, 5.0, 4.0))
    assert np.linalg.norm(op.twists[-1]) > 0
    n = len(op.twists)
    time.sleep(0.8)  # > frame_timeout_s
    assert len(op.twists) > n and not np.any(op.twists[-1])


def test_restart_resumes_persisted_state(tmp_path: Path) -> None:
    port = free_port()
    config = service_config(port, tmp_path / "state")
    img = scene()
    with running_service(config, tmp_path, port) as (_, op):
        assert op.command(op="set_config", config={"control": {"gains": 0.3}}).ok
        assert op.command(op="set_reference", source="next_frame").ok
        op.send(img)
        assert op.command(op="start").ok
        assert op.send(shifted(img, 5.0, 3.0))["state"] == "SERVOING"
    with running_service(config, tmp_path, port) as (_, op):
        snapshot = op.command(op="get_state").data
        assert snapshot is not None and snapshot["has_reference"] and snapshot["state"] == "LOST"  # until confirmed
        assert op.command(op="get_config").data["control"]["gains"] == 0.3
        status = op.send(shifted(img, 5.0, 3.0))  # tracked from the persisted estimate, held still: not confirmed yet
        assert status["state"] == "LOST" and "from the last good estimate" in status["message"], status
        assert not np.any(op.twists[-1])
        status, _ = past_lost(op, shifted(img, 5.0, 3.0))  # until `confirm_frames` tracked frames confirm it
        assert status["state"] == "SERVOING", status


def test_sigterm_publishes_zero_twist_and_exits_cleanly(tmp_path: Path) -> None:
    port = free_port()
    config = service_config(port, tmp_path / "state")
    service = Service(config, tmp_path)
    op = Operator(port)
    try:
        service.wait_ready(op)
        n = len(op.twists)
        code, stderr = service.stop()
        assert code == 0
        time.sleep(0.2)
        assert len(op.twists) > n and not np.any(op.twists[-1])
        logs = [json.loads(line)["msg"] for line in stderr.splitlines() if line.startswith("{")]
        assert "service stopped" in logs
        assert logs.index("kernels warmed up") < logs.index("serving")  # compiled before it is alive
    finally:
        op.close()
        if service.proc.poll() is None:
            service.proc.kill()


@pytest.mark.parametrize("interpolation", ["keys", "bspline"])
def test_general_model_serves_a_planar_target(tmp_path: Path, interpolation: str) -> None:
    """With `registration.model = general` the service runs the eq. (2) tracker (either sampling of the current
    image); on a planar scene ρ* stays ~0."""
    port = free_port()
    config = service_config(port, tmp_path / "state")
    config = config.merged({"registration": {"model": "general", "interpolation": interpolation}})
    img = scene()
    with running_service(config, tmp_path, port) as (_, op):
        assert op.command(op="set_reference", source="next_frame").ok
        op.send(img)
        assert op.command(op="start").ok
        status, _ = past_lost(op, shifted(img, 4.0, -3.0, 2.0))  # the general tracker acquires globally (ρ* too)
        assert status["state"] == "SERVOING", status
        assert np.linalg.norm(status["twist"]) > 0, status
        assert converge(op, img)["state"] == "CONVERGED"
    persisted = json.loads((tmp_path / "state" / "state.json").read_text())
    assert "rho_coeffs" in persisted


def test_inbox_keeps_the_newest_frame_queues_commands_and_wakes_the_loop() -> None:
    """The hand-off from Zenoh callbacks: newest frame only (counted), commands in order and bounded, and `wait`
    returns as soon as something arrives rather than at its timeout."""
    inbox = Inbox(max_queries=2)
    inbox.on_frame("frame 1")  # the inbox stores whatever the callback hands it
    inbox.on_frame("frame 2")
    frame = inbox.take_frame()
    assert frame is not None and frame.sample == "frame 2" and frame.index == 2 and inbox.take_frame() is None
    assert inbox.frames_received == 2 and inbox.frames_superseded == 1 and inbox.last_arrival_t == frame.t
    for q in ("q1", "q2", "q3"):
        inbox.on_query(q)
    assert [inbox.take_query(), inbox.take_query(), inbox.take_query()] == ["q2", "q3", None]
    inbox.on_info("info")
    assert inbox.take_info() == "info" and inbox.take_info() is None

    t0 = time.monotonic()
    inbox.wait(0.05)  # nothing pending: sleeps the whole timeout
    assert time.monotonic() - t0 >= 0.04
    threading.Timer(0.05, inbox.on_frame, args=("frame 3",)).start()
    t0 = time.monotonic()
    inbox.wait(10.0)
    frame = inbox.take_frame()
    assert time.monotonic() - t0 < 5.0 and frame is not None and frame.sample == "frame 3"
    assert inbox.frames_superseded == 1  # frame 3 was taken, not superseded


def test_the_residual_image_is_published_while_subscribed(served: tuple[Service, Operator, ServiceConfig]) -> None:
    """`servo/residual` (issue 19): with a subscriber, 32FC1 images of the ROI at most 5 Hz, small once the frame is
    tracked (that nothing is computed without one: tests/test_residual_publisher.py)."""
    _, op, _ = served
    img = scene()
    assert op.command(op="set_reference", source="next_frame").ok
    op.send(img)
    residuals: list[np.ndarray] = []
    op.send(shifted(img, 2.0, 1.0))  # no subscriber yet
    subscriber = op.session.declare_subscriber(
        op.keys.key("servo_residual"), lambda s: residuals.append(decode_image(s.payload.to_bytes()).array.copy()))
    time.sleep(0.5)  # the service's matching listener learns of the subscriber
    t0 = time.monotonic()
    for _ in range(30):
        op.send(shifted(img, 2.0, 1.0))
    elapsed = time.monotonic() - t0
    time.sleep(0.3)
    subscriber.undeclare()
    assert residuals, "no residual image while subscribed"
    assert len(residuals) <= 5.0 * elapsed + 1.5  # the reduced rate, not one per frame
    r = residuals[-1]
    assert r.dtype == np.float32 and r.shape == (80, 100)  # the configured 100×80 template
    assert np.sqrt(np.mean(r**2)) < 10.0  # tracked: what remains is resampling and noise
