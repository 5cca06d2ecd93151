"""One servo run on the simulated arm: sim, bridge and service as separate processes over Zenoh on loopback,
driven and recorded from this process. Used by `ddvs demo` (real-time clock) and `tests/test_e2e_arm.py` (lockstep).

Sequence:
1. Render the reference image I* here, with an `ArmSim` of the same scene placed at the reference camera pose
   (`start.reference` of the scene file), and keep that pose `T_world_ref` (ground truth, evaluation only).
2. Start `ddvs sim arm --start start` (camera at reference · displacement), `ddvs serve` and `ddvs bridge`, each in
   its own process, logs in `<out>/logs/`. Topology: the sim listens on one loopback port, the service on another;
   the service, the bridge and this process connect to the ports they need (a full mesh; multicast scouting off).
3. Wait for the service's first status (it has the camera info then), upload I* with `set_reference` (source
   upload, with the template ROI), then `start`. The service globally initialises the first frame against I*.
4. Record status, twists, joint states and ground truth (`clients.record.Recorder`, meta holds `reference_pose`)
   until the servo is CONVERGED for `settle_images` images, or `max_images` / `time_limit` is reached.
5. Stop every child (SIGINT, then SIGKILL after a grace period) — also on an exception or Ctrl-C.

The ROI: `template` (w, h) centred on the control point p* (the principal point by default), as the paper's 70×70.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "configs" / "arm" / "ur5_poster.json"
BRIDGE = ROOT / "configs" / "arm" / "ur5_bridge.json"
STOP_GRACE_S = 10.0


@dataclass(frozen=True)
class ArmRunSettings:
    """`law` dvs | dvs_reduced | ddvs; `template` (w, h) pixels centred on p*; `clock` of the sim; `fps` frames per
    second; `gain` λ (1/s, Sec. 4: 0.4); `stop_threshold` on the error norm (Sec. 4: 1e-3); limits: `max_images`
    processed while servoing, `time_limit` seconds of wall time for the whole run; `settle_images` CONVERGED
    images required before finishing; `robot`/`prefix` of the keys."""

    out_dir: Path
    law: Literal["dvs", "dvs_reduced", "ddvs"] = "ddvs"
    template: tuple[int, int] = (70, 70)
    clock: Literal["realtime", "lockstep"] = "lockstep"
    fps: float = 30.0
    gain: float = 0.4
    stop_threshold: float = 1e-3
    max_images: int = 2000
    time_limit: float = 600.0
    settle_images: int = 5
    scene: Path = SCENE
    bridge: Path = BRIDGE
    robot: str = "arm0"
    prefix: str = "ddvs"


@dataclass
class ArmRunResult:
    """How the run ended (`converged`, `reason`), where its recording is, and the rendered reference image."""

    converged: bool
    reason: str
    recording_dir: Path
    wall_s: float
    images: int
    extra: dict[str, Any] = field(default_factory=dict)


def _free_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def render_reference(scene_path: Path) -> tuple[Any, Any]:
    """(I* as grey uint8, `T_world_ref` 4×4) for the scene's reference camera pose, rendered with SAPIEN here."""
    from sim.arm import ArmSim
    from sim.arm_scene import load_scene_config

    config = load_scene_config(scene_path)
    if config.start is None:
        raise ValueError(f"{scene_path} has no 'start' section: no reference pose to servo to")
    sim = ArmSim(config)
    sim.place_camera(config.start.T_target_ref, config.start.target)
    return sim.render().copy(), sim.camera_pose()


@contextmanager
def child(name: str, args: list[str], log_dir: Path) -> Iterator[subprocess.Popen]:
    """`python -m ddvs_service.cli ARGS` in its own process (output to `<log_dir>/<name>.log`), stopped at exit:
    SIGINT, then SIGKILL after `STOP_GRACE_S` seconds."""
    log_dir.mkdir(parents=True, exist_ok=True)
    with open(log_dir / f"{name}.log", "w", encoding="utf-8") as log:
        proc = subprocess.Popen([sys.executable, "-m", "ddvs_service.cli", *args], cwd=ROOT, stdout=log,
                                stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        try:
            yield proc
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
                try:
                    proc.wait(STOP_GRACE_S)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()


def service_config(settings: ArmRunSettings, listen: int, sim_port: int) -> dict[str, Any]:
    """The `ddvs serve` configuration of this run (written to `<out>/serve.json`)."""
    return {
        "prefix": settings.prefix,
        "robot": settings.robot,
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{listen}"], "connect": [f"tcp/127.0.0.1:{sim_port}"]},
        "state_dir": str(settings.out_dir / "state"),
        "registration": {"template_size": list(settings.template), "global_init": True},
        "control": {"law": settings.law, "gains": settings.gain, "stop_threshold": settings.stop_threshold},
    }


def run_arm(settings: ArmRunSettings, progress: Callable[[dict[str, Any]], None] | None = None) -> ArmRunResult:
    """Run the whole sequence of the module docstring; `progress(snapshot)` is called about once per second with
    a `clients.monitor.Monitor` snapshot plus `images` and `elapsed_s`."""
    from clients.ctl import send_command
    from clients.monitor import Monitor
    from clients.record import Recorder, recording_meta
    from clients.recording import RecordingWriter
    from ddvs_service.protocol import Command, Keys, ReferenceImage, SessionConfig, encode_upload, open_session

    out = settings.out_dir
    out.mkdir(parents=True, exist_ok=True)
    reference, T_world_ref = render_reference(settings.scene)
    import cv2

    cv2.imwrite(str(out / "reference.png"), reference)
    keys = Keys(settings.prefix, settings.robot)
    sim_port, serve_port = _free_port(), _free_port()
    (out / "serve.json").write_text(json.dumps(service_config(settings, serve_port, sim_port), indent=2))
    common = ["--prefix", settings.prefix, "--robot", settings.robot]
    started = time.monotonic()
    with ExitStack() as stack:
        commands = {
            "sim": ["sim", "arm", "--config", str(settings.scene), "--clock", settings.clock, "--fps",
                    str(settings.fps), "--lockstep-timeout", "2", "--start", "start",
                    "--listen", f"tcp/127.0.0.1:{sim_port}", *common],
            "serve": ["serve", "--config", str(out / "serve.json"), "--fresh"],
            "bridge": ["bridge", "--config", str(settings.bridge), "--connect",
                       f"tcp/127.0.0.1:{sim_port},tcp/127.0.0.1:{serve_port}", *common],
        }
        children = {name: stack.enter_context(child(name, args, out / "logs")) for name, args in commands.items()}
        session = stack.enter_context(open_session(SessionConfig(
            connect=[f"tcp/127.0.0.1:{sim_port}", f"tcp/127.0.0.1:{serve_port}"])))
        monitor = Monitor(session, keys, window=1.0)
        stack.callback(monitor.close)
        while not monitor.status_received.wait(0.2):
            _check_children(children, out / "logs")
            if time.monotonic() - started > settings.time_limit:
                raise RuntimeError(f"no status from the service within the time limit; see {out / 'logs'}")
        meta = {"reference_pose": T_world_ref.reshape(-1).tolist(), "law": settings.law,
                "template": list(settings.template), "clock": settings.clock, "fps": settings.fps,
                "gain": settings.gain, "stop_threshold": settings.stop_threshold, "scene": str(settings.scene)}
        writer = RecordingWriter(out / "recording", recording_meta(keys, meta))
        stack.callback(writer.close)
        recorder = Recorder(session, keys, writer)
        stack.callback(recorder.close)
        stop_recording = threading.Event()
        recorder_thread = threading.Thread(target=recorder.run, args=(stop_recording,), daemon=True)
        recorder_thread.start()
        stack.callback(recorder_thread.join)
        stack.callback(stop_recording.set)
        upload = ReferenceImage(format="png", data=encode_upload(reference, "png"))
        for command in (Command(op="set_reference", source="upload", image=upload), Command(op="start")):
            reply = send_command(session, keys, command, timeout=30.0)
            if reply is None or not reply.ok:
                raise RuntimeError(f"{command.op} failed: {'no reply' if reply is None else reply.error}")
        return _wait_for_convergence(settings, monitor, started, progress, out, children)


def _check_children(children: dict[str, subprocess.Popen], log_dir: Path) -> None:
    """Raise `RuntimeError` with the end of its log when a child process has exited."""
    for name, proc in children.items():
        if proc.poll() is not None:
            tail = (log_dir / f"{name}.log").read_text(encoding="utf-8", errors="replace")[-2000:]
            raise RuntimeError(f"`ddvs {name}` exited with status {proc.returncode}; end of its log:\n{tail}")


def _wait_for_convergence(settings: ArmRunSettings, monitor: Any, started: float,
                          progress: Callable[[dict[str, Any]], None] | None, out: Path,
                          children: dict[str, subprocess.Popen]) -> ArmRunResult:
    first_seq: int | None = None
    next_report = time.monotonic()
    converged_since: int | None = None
    while True:
        snap = monitor.snapshot()
        elapsed = time.monotonic() - started
        seq = snap.get("seq")
        if snap["state"] == "SERVOING" and first_seq is None and seq is not None:
            first_seq = seq
        images = 0 if first_seq is None or seq is None else seq - first_seq
        if snap["state"] == "CONVERGED":
            converged_since = images if converged_since is None else converged_since
            if images - converged_since >= settings.settle_images:
                return ArmRunResult(True, "converged", out / "recording", elapsed, images)
        else:
            converged_since = None
        if images >= settings.max_images:
            return ArmRunResult(False, f"not converged after {images} images", out / "recording", elapsed, images)
        if elapsed >= settings.time_limit:
            return ArmRunResult(False, f"time limit {settings.time_limit:.0f} s reached", out / "recording", elapsed,
                                images)
        _check_children(children, out / "logs")
        if progress is not None and time.monotonic() >= next_report:
            progress({**snap, "images": images, "elapsed_s": round(elapsed, 1)})
            next_report += 1.0
        time.sleep(0.02)
