"""The distributed deployment under faults (issue 8): sim and bridge on host A, the servo service on host B.

Hosts are network namespaces joined by a veth pair (`tests/netns.py`), each with its own `ddvs router`; every node
is a client of its host's router, so all traffic between the hosts crosses the veth between the two routers. The
test process (operator and recorder) is a client of host A's router through a Unix socket.

Set-up (chosen to keep CI time down): the paper's planar poster scene (`configs/arm/ur5_poster.json`, the paper's
real-data displacement t = [0.13, −0.23, −0.08] m, r = [−20.3, 2.17, 14.59]°), the decoupled law, λ = 0.4, a
200×150 ROI, the sim on its **real-time** clock at 30 Hz (deadmen are wall-clock mechanisms; frames the machine
cannot render in time are dropped, the plant is never slowed). Convergence: CONVERGED (‖ε‖ < 1e-3) for 5 images,
still CONVERGED when the run is stopped (the service's hysteresis resumes servoing above 5e-3), and a final camera
pose error (ground truth) below 3 mm / 0.3°.

Stop times are reported twice: at the arrival of the first still joint state (asserted) and at its stamp (the sim's
instant of that state, before rendering and transport).

Stop times are measured in this process: from the fault (`kill -9` of the service, or the veth going down) to the
arrival of the first joint state of the sim whose joint velocities are all below `STILL` rad/s. Arrival time bounds
the plant's own time from above (the Unix socket adds well under a millisecond). Each case writes `summary.json`
(and its recording and logs) under `reports/distributed/<case>/`.
"""

from __future__ import annotations

import json
import re
import shutil
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from netns import TwoHosts, create_two_hosts, netns_unavailable_reason

from clients.analysis import summarize
from clients.recording import load_recording
from ddvs_service.protocol import Command, Keys, decode_joint_state
from orchestration.arm_run import SCENE, ArmRun, ArmRunResult, ArmRunSettings, ChildLaunch, open_arm_run

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
REPORTS = ROOT / "reports" / "distributed"
FPS = 30.0
# The fault cases run the plant at 60 Hz: after the bridge's 100 ms deadman the zero command still waits up to one
# bridge period (10 ms) and one plant period, and at 30 Hz (33 ms) plus rendering that leaves no margin under 150 ms.
FAULT_FPS = 60.0
TEMPLATE = (200, 150)
STILL = 1e-4  # rad/s: every joint velocity below this = the arm stands still
STOP_LIMIT_MS = 150.0  # issue 8: the arm stops within 150 ms of the service's death
CUT_STOP_LIMIT_MS = 250.0  # issue 8 asks only that the arm stops when the link is cut: same deadman chain, looser bound
MOVING = 1e-2  # rad/s: some joint faster than this = the arm is being servoed
MAX_TRANSLATION_MM = 3.0
MAX_ROTATION_DEG = 0.3
TIME_LIMIT_S = 180.0


@pytest.fixture
def hosts(tmp_path: Path) -> Iterator[TwoHosts]:
    reason = netns_unavailable_reason()
    if reason is not None:
        pytest.skip(reason)
    two = create_two_hosts(tmp_path / "net")
    try:
        yield two
    finally:
        two.close()


def case_dir(name: str) -> Path:
    out = REPORTS / name
    shutil.rmtree(out, ignore_errors=True)
    return out


def distributed_settings(hosts: TwoHosts, out: Path, robot: str, scene: Path = SCENE, fps: float = FPS,
                         start_servo: bool = True) -> ArmRunSettings:
    """Sim and bridge on host A, the service on host B, all clients of their host's router."""
    node = hosts.client_flags()
    return ArmRunSettings(
        out_dir=out, law="ddvs", template=TEMPLATE, clock="realtime", fps=fps, max_images=100_000,
        time_limit=TIME_LIMIT_S, robot=robot, scene=scene,
        launch={"sim": ChildLaunch(hosts.wrapper("a"), node), "bridge": ChildLaunch(hosts.wrapper("a"), node),
                "serve": ChildLaunch(hosts.wrapper("b"), node)},
        driver_session={"mode": "client", "connect": [hosts.socket_endpoint("a")]}, start_servo=start_servo,
    )


class JointSpeeds:
    """Arrival time (`time.time_ns()`) and largest |joint velocity| (rad/s) of each joint state of one robot; its
    stamp (the sim's instant of that state) by arrival time in `stamps`."""

    def __init__(self, session: zenoh.Session, keys: Keys) -> None:
        self.samples: list[tuple[int, float]] = []
        self.stamps: dict[int, int] = {}
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(keys.arm_joint_states, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        arrival = time.time_ns()
        msg = decode_joint_state(sample.payload.to_bytes())
        speed = float(np.max(np.abs(msg.velocity)))
        with self._lock:
            self.samples.append((arrival, speed))
            self.stamps[arrival] = msg.header.stamp.to_ns()

    def close(self) -> None:
        self._sub.undeclare()

    def after(self, t_ns: int) -> list[tuple[int, float]]:
        with self._lock:
            return [s for s in self.samples if s[0] > t_ns]

    def wait(self, t_ns: int, still: bool, timeout: float, run: ArmRun) -> int:
        """Arrival time of the first joint state after `t_ns` that is still (all speeds < STILL) or moving (some
        speed > MOVING); `AssertionError` after `timeout` seconds."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for arrival, speed in self.after(t_ns):
                if (speed < STILL) if still else (speed > MOVING):
                    return arrival
            run.check_children()
            time.sleep(0.005)
        raise AssertionError(f"the arm did not become {'still' if still else 'moving'} within {timeout} s")

    def max_speed(self, start_ns: int, end_ns: int) -> float:
        speeds = [speed for arrival, speed in self.after(start_ns) if arrival <= end_ns]
        assert speeds, "no joint state arrived in the window"
        return max(speeds)


def wait_servoing(run: ArmRun, speeds: JointSpeeds, images: int, timeout: float = 120.0) -> None:
    """Until the service has processed `images` images while SERVOING and the arm moves."""
    deadline = time.monotonic() + timeout
    first: int | None = None
    while time.monotonic() < deadline:
        snap = run.monitor.snapshot()
        if snap["state"] == "SERVOING" and snap["seq"] is not None:
            first = snap["seq"] if first is None else first
            if snap["seq"] - first >= images:
                speeds.wait(time.time_ns() - 100_000_000, still=False, timeout=5.0, run=run)
                return
        run.check_children()
        time.sleep(0.02)
    raise AssertionError(f"not SERVOING for {images} images within {timeout} s: {run.monitor.snapshot()}")


def convergence_summary(result: ArmRunResult) -> dict[str, Any]:
    summary = summarize(load_recording(result.recording_dir))
    return {"converged": result.converged, "reason": result.reason, "images": result.images,
            "wall_s": round(result.wall_s, 1), "final_state": summary.final_state,
            "final_error_norm": summary.final_error_norm,
            "initial_translation_error_mm": summary.initial_translation_error_mm,
            "final_translation_error_mm": summary.final_translation_error_mm,
            "final_rotation_error_deg": summary.final_rotation_error_deg}


def assert_converged(summary: dict[str, Any], out: Path) -> None:
    assert summary["converged"], f"{summary['reason']}; logs in {out / 'logs'}"
    assert summary["final_state"] == "CONVERGED", summary  # still converged when the run was stopped
    assert summary["final_translation_error_mm"] < MAX_TRANSLATION_MM, summary
    assert summary["final_rotation_error_deg"] < MAX_ROTATION_DEG, summary


def report(out: Path, figures: dict[str, Any]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps(figures, indent=2))
    print(json.dumps(figures))


def test_servo_converges_across_the_link(hosts: TwoHosts) -> None:
    out = case_dir("across_link")
    with open_arm_run(distributed_settings(hosts, out, "net_arm")) as run:
        result = run.wait_for_convergence()
    summary = convergence_summary(result)
    report(out, summary)
    assert_converged(summary, out)
    assert summary["initial_translation_error_mm"] > 250.0  # it started at the paper's displacement


def test_killed_service_stops_the_arm_and_the_restarted_service_resumes(hosts: TwoHosts) -> None:
    out = case_dir("kill_service")
    with open_arm_run(distributed_settings(hosts, out, "kill_arm", fps=FAULT_FPS)) as run:
        speeds = JointSpeeds(run.session, run.keys)
        try:
            wait_servoing(run, speeds, images=90)
            killed = time.time_ns()
            run.kill("serve")
            stopped = speeds.wait(killed, still=True, timeout=5.0, run=run)
            time.sleep(1.0)
            still_while_down = speeds.max_speed(stopped, time.time_ns())
            run.restart("serve")
            result = run.wait_for_convergence()
        finally:
            speeds.close()
    figures = {"stop_after_kill_ms": (stopped - killed) / 1e6,
               "stop_stamp_after_kill_ms": (speeds.stamps[stopped] - killed) / 1e6,
               "max_speed_while_down": still_while_down,
               **convergence_summary(result)}
    report(out, figures)
    assert figures["stop_after_kill_ms"] < STOP_LIMIT_MS, figures
    assert still_while_down < STILL, figures
    assert "resumed persisted reference" in (out / "logs" / "serve.log").read_text()
    assert_converged(figures, out)


def test_cut_link_stops_the_arm_and_servoing_resumes_when_it_returns(hosts: TwoHosts) -> None:
    out = case_dir("link_cut")
    with open_arm_run(distributed_settings(hosts, out, "cut_arm", fps=FAULT_FPS)) as run:
        speeds = JointSpeeds(run.session, run.keys)
        try:
            wait_servoing(run, speeds, images=90)
            cut = time.time_ns()
            hosts.set_link(up=False)
            try:
                stopped = speeds.wait(cut, still=True, timeout=2.0, run=run)
                time.sleep(max(0.0, 2.0 - (time.time_ns() - cut) / 1e9))
                still_while_cut = speeds.max_speed(stopped, time.time_ns())
            finally:
                restored = time.time_ns()
                hosts.set_link(up=True)
            moving = speeds.wait(restored, still=False, timeout=30.0, run=run)
            result = run.wait_for_convergence()
        finally:
            speeds.close()
    figures = {"stop_after_cut_ms": (stopped - cut) / 1e6,
               "stop_stamp_after_cut_ms": (speeds.stamps[stopped] - cut) / 1e6, "cut_s": (restored - cut) / 1e9,
               "max_speed_while_cut": still_while_cut, "moving_again_after_ms": (moving - restored) / 1e6,
               **convergence_summary(result)}
    report(out, figures)
    assert figures["stop_after_cut_ms"] < CUT_STOP_LIMIT_MS, figures
    assert still_while_cut < STILL, figures
    assert_converged(figures, out)


def displaced_scene(path: Path, t: list[float], r_deg: list[float]) -> Path:
    """`configs/arm/ur5_poster.json` with another start displacement (same reference pose)."""
    scene = json.loads(SCENE.read_text())
    scene["start"]["displacement"] = {"t": t, "r_deg": r_deg}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(scene, indent=2))
    return path


def servo_interval(result: ArmRunResult) -> tuple[float, float]:
    """Wall-clock seconds (Unix time) of the first SERVOING and of the first CONVERGED status of a run."""
    statuses = load_recording(result.recording_dir)["status"]
    first = {state: next(s["recv_ns"] for s in statuses if s["msg"]["state"] == state) / 1e9
             for state in ("SERVOING", "CONVERGED")}
    return first["SERVOING"], first["CONVERGED"]


def published_frames(out: Path) -> int:
    """Frames the sim says it published (its exit log line)."""
    match = re.search(r"published (\d+) frames", (out / "logs" / "sim.log").read_text())
    assert match, f"no 'published N frames' line in {out / 'logs' / 'sim.log'}"
    return int(match.group(1))


def test_two_robots_servo_at_once_without_crosstalk(hosts: TwoHosts, tmp_path: Path) -> None:
    outs = {"arm_a": case_dir("two_robots/arm_a"), "arm_b": case_dir("two_robots/arm_b")}
    scenes = {"arm_a": SCENE,
              "arm_b": displaced_scene(tmp_path / "scene_b.json", [-0.10, 0.12, -0.05], [8.0, -6.0, -12.0])}
    settings = {robot: distributed_settings(hosts, outs[robot], robot, scenes[robot], start_servo=False)
                for robot in outs}
    with ExitStack() as stack:
        runs = {robot: stack.enter_context(open_arm_run(s)) for robot, s in settings.items()}
        for run in runs.values():  # both ready: start them together
            run.command(Command(op="start"))
        with ThreadPoolExecutor(len(runs)) as pool:
            results = dict(zip(runs, pool.map(ArmRun.wait_for_convergence, runs.values())))
        counters = {robot: run.monitor.snapshot()["counters"] for robot, run in runs.items()}
    figures: dict[str, Any] = {}
    for robot, out in outs.items():
        frames = published_frames(out)
        received = counters[robot]["frames"] + counters[robot]["dropped"] + counters[robot]["rejected"]
        figures[robot] = {"sim_frames": frames, "service_received_frames": received,
                          "servoing_s": servo_interval(results[robot]), **convergence_summary(results[robot])}
    report(REPORTS / "two_robots", figures)
    (a_start, a_end), (b_start, b_end) = (figures[robot]["servoing_s"] for robot in outs)
    assert max(a_start, b_start) < min(a_end, b_end), f"the two servo runs did not overlap: {figures}"
    for robot, out in outs.items():
        assert_converged(figures[robot], out)
        # Each service saw only its own sim's frames: with crosstalk it would receive both sims' (about twice).
        assert 0 < figures[robot]["service_received_frames"] <= figures[robot]["sim_frames"], figures
