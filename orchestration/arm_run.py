"""One servo run on the simulated arm: sim, bridge and service as separate processes over Zenoh on loopback,
driven and recorded from this process. Used by `ddvs demo` (real-time clock) and `tests/test_e2e_arm.py` (lockstep).

Sequence:
1. Render the reference image I* here, with an `ArmSim` of the same scene placed at the reference camera pose
   (`start.reference` of the scene file), and keep that pose `T_world_ref` (ground truth, evaluation only).
2. Start `ddvs sim arm --start start` (camera at reference · displacement), `ddvs serve` and `ddvs bridge`, each in
   its own process, logs in `<out>/logs/`. Topology: the sim listens on one loopback port, the service on another;
   the service, the bridge and this process connect to the ports they need (a full mesh; multicast scouting off).
3. Upload I* with `set_reference` (source upload, with the template ROI) until the service accepts it (it needs
   the camera info first), then `start`. The service globally initialises the first frame against I*.
4. Record the run into a bag (`clients.bag_recorder.BagRecorder`: frames, camera info, twists, joint states,
   reference, status, state, ground truth, configuration; meta holds `reference_pose`) until the servo is
   CONVERGED for `settle_images` images, or `max_images` / `time_limit` is reached; `<out>/foxglove-layout.json`
   is the Foxglove layout of the run's topics.
5. Stop every child (SIGINT, then SIGKILL after a grace period) — also on an exception or Ctrl-C.

The ROI: `template` (w, h) centred on the control point p* (the principal point by default), as the paper's 70×70.

Other topologies (tests/test_distributed.py: sim and bridge on one network namespace, the service on another, each
host with its own `ddvs router`): `ArmRunSettings.launch` gives per child a command wrapper (e.g. `ip netns exec
hostA`) and Zenoh flags replacing the loopback endpoints, `driver_session` this process's session. `open_arm_run`
yields the started run (`ArmRun`) so that a caller can kill and restart a child mid-run before waiting for
convergence; `run_arm` is `open_arm_run` + `ArmRun.wait_for_convergence`.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

if TYPE_CHECKING:
    from ddvs_service.service.config import ServiceConfig

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "configs" / "arm" / "ur5_poster.json"
BRIDGE = ROOT / "configs" / "arm" / "ur5_bridge.json"
STOP_GRACE_S = 10.0
CHILDREN = ("sim", "serve", "bridge")


@dataclass(frozen=True)
class ChildLaunch:
    """How one child (`sim`, `serve` or `bridge`) starts instead of the loopback default: `wrapper` command words put
    before the interpreter (e.g. `("ip", "netns", "exec", "hostA")`: run it on another network namespace; the
    wrapper must exec the command, so that the child's pid is the node's), and `zenoh` the Zenoh flags replacing the
    loopback endpoints (e.g. `("--mode", "client", "--connect", "tcp/127.0.0.1:7447")`; None: loopback mesh)."""

    wrapper: tuple[str, ...] = ()
    zenoh: tuple[str, ...] | None = None


@dataclass(frozen=True)
class ArmRunSettings:
    """`law` dvs | dvs_reduced | ddvs; `template` (w, h) pixels centred on p*; `clock` of the sim; `fps` frames per
    second; `gain` λ (1/s, Sec. 4: 0.4); `stop_threshold` on the error norm (Sec. 4: 1e-3); `gain_grid` (rows,
    cols) of the registration's gain surface (None: the service's default; the arm's light is uniform, so one gain is
    its exact model, and on a 70×70 template the 3×3 surface biases the weakly seen tilt: docs/results/servoing.md);
    limits: `max_images`
    processed while servoing, `time_limit` seconds of wall time for the whole run; `settle_images` CONVERGED
    images required before finishing; `robot`/`prefix` of the keys; `launch` per child name how it starts
    (default: loopback mesh, this interpreter); `driver_session` the `SessionConfig` fields of this process's session
    (default: a peer connecting to the sim's and the service's loopback ports); `start_servo` False: `open_arm_run`
    uploads the reference but leaves the `start` to the caller (`ArmRun.command(Command(op="start"))`);
    `ros_domain_id` runs every node in ROS 2 mode over rmw_zenoh in that domain (docs/ros2.md; realtime clock);
    `model` the registration's: "planar" (a poster) or "general" (eq. (2): a non-planar target such as the saddle of
    `configs/arm/ur5_saddle.json`)."""

    out_dir: Path
    law: Literal["dvs", "dvs_reduced", "ddvs"] = "ddvs"
    template: tuple[int, int] = (70, 70)
    clock: Literal["realtime", "lockstep"] = "lockstep"
    fps: float = 30.0
    gain: float = 0.4
    stop_threshold: float = 1e-3
    gain_grid: tuple[int, int] | None = None
    max_images: int = 2000
    time_limit: float = 600.0
    settle_images: int = 5
    scene: Path = SCENE
    bridge: Path = BRIDGE
    robot: str = "arm0"
    prefix: str = "ddvs"
    launch: Mapping[str, ChildLaunch] = field(default_factory=dict)
    driver_session: Mapping[str, Any] | None = None
    start_servo: bool = True
    ros_domain_id: int | None = None
    model: Literal["planar", "general"] = "planar"

    def __post_init__(self) -> None:
        if self.ros_domain_id is not None and self.clock != "realtime":
            raise ValueError("ROS 2 mode needs the realtime clock: ros2_control commands carry no stamp for lockstep")
        unknown = sorted(set(self.launch) - set(CHILDREN))
        if unknown:
            raise ValueError(f"launch names unknown children {unknown}; expected some of {list(CHILDREN)}")


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
def child(name: str, args: list[str], log_dir: Path, wrapper: tuple[str, ...] = (),
          append: bool = False) -> Iterator[subprocess.Popen]:
    """`[wrapper…] python -m ddvs.cli ARGS` in its own process (output to `<log_dir>/<name>.log`, appended
    when `append`), stopped at exit: SIGINT, then SIGKILL after `STOP_GRACE_S` seconds."""
    log_dir.mkdir(parents=True, exist_ok=True)
    with open(log_dir / f"{name}.log", "a" if append else "w", encoding="utf-8") as log:
        proc = subprocess.Popen([*wrapper, sys.executable, "-m", "ddvs.cli", *args], cwd=ROOT, stdout=log,
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


def service_config(settings: ArmRunSettings, listen: int, sim_port: int) -> ServiceConfig:
    """The `ddvs serve` configuration of this run (written to `<out>/serve.json`), built and checked by the schema."""
    from ddvs_service.protocol.ros_settings import RosSettings
    from ddvs_service.protocol.session import SessionConfig
    from ddvs_service.service.config import ControlSettings, RegistrationSettings, ServiceConfig

    # levels 3: the pyramid of the measured arm runs (the schema's default lets the ROI size choose, 8 at most)
    registration = RegistrationSettings(template_size=settings.template, levels=3, global_init=True,
                                        model=settings.model)
    if settings.gain_grid is not None:
        registration = registration.replaced(gain_grid=settings.gain_grid)
    return ServiceConfig(
        prefix=settings.prefix,
        robot=settings.robot,
        zenoh=SessionConfig(mode="peer", listen=[f"tcp/127.0.0.1:{listen}"], connect=[f"tcp/127.0.0.1:{sim_port}"]),
        state_dir=settings.out_dir / "state",
        registration=registration,
        control=ControlSettings(law=settings.law, gains=settings.gain, stop_threshold=settings.stop_threshold),
        ros=RosSettings(domain_id=settings.ros_domain_id),
    )


def run_arm(settings: ArmRunSettings, progress: Callable[[dict[str, Any]], None] | None = None) -> ArmRunResult:
    """Run the whole sequence of the module docstring; `progress(snapshot)` is called about once per second with
    a `clients.monitor.Monitor` snapshot plus `images` and `elapsed_s`."""
    with open_arm_run(settings) as run:
        return run.wait_for_convergence(progress)


class ArmRun:
    """A started run (steps 1–3 done, recording): its children by name, this process's Zenoh `session`, the
    `monitor` of the servo and the `keys`. Children may be killed and restarted; `wait_for_convergence` is step 4."""

    def __init__(self, settings: ArmRunSettings, stack: ExitStack, commands: dict[str, list[str]],
                 session: Any, started: float) -> None:
        from clients.monitor import Monitor
        from ddvs_service.protocol import Keys
        from ddvs_service.protocol.ros_settings import RosSettings

        self.settings, self.session, self.started = settings, session, started
        self.keys = Keys(settings.prefix, settings.robot, RosSettings(domain_id=settings.ros_domain_id))
        self.log_dir = settings.out_dir / "logs"
        self._stack, self._commands = stack, commands
        self._killed: set[str] = set()  # killed on purpose and not restarted yet: not an error
        self.children = {name: self._start(name, args) for name, args in commands.items()}
        self.monitor = Monitor(session, self.keys, window=1.0)
        stack.callback(self.monitor.close)

    def _start(self, name: str, args: list[str], append: bool = False) -> subprocess.Popen:
        wrapper = self.settings.launch.get(name, ChildLaunch()).wrapper
        return self._stack.enter_context(child(name, args, self.log_dir, wrapper, append))

    def kill(self, name: str) -> None:
        """SIGKILL the child `name` (no clean-up on its side: no last zero twist, no goodbye) and reap it."""
        proc = self.children[name]
        proc.kill()
        proc.wait()
        self._killed.add(name)

    def restart(self, name: str) -> None:
        """Start the child `name` again with its original arguments except `--fresh` (a service resumes from its
        persisted state); its output is appended to its log."""
        if self.children[name].poll() is None:
            raise RuntimeError(f"`ddvs {name}` is still running (pid {self.children[name].pid}); kill it first")
        args = [a for a in self._commands[name] if a != "--fresh"]
        self.children[name] = self._start(name, args, append=True)
        self._killed.discard(name)

    def command_when_ready(self, command: Any, poll_s: float = 0.5) -> None:
        """Send `command` until the service accepts it, within the run's time limit: a service that has no camera
        info yet (it answers no frame while IDLE) refuses a reference."""
        while True:
            self.check_children()
            try:
                self.command(command)
                return
            except RuntimeError as exc:
                if time.monotonic() - self.started > self.settings.time_limit:
                    raise RuntimeError(f"the service did not accept {command.op} within the time limit ({exc}); "
                                       f"see {self.log_dir}") from exc
            time.sleep(poll_s)

    def command(self, command: Any) -> None:
        """Send a `ddvs_service.protocol.Command` to the service; `RuntimeError` when refused or unanswered (30 s)."""
        from clients.ctl import send_command

        reply = send_command(self.session, self.keys, command, timeout=30.0)
        if reply is None or not reply.ok:
            raise RuntimeError(f"{command.op} failed: {'no reply' if reply is None else reply.error}")

    def check_children(self) -> None:
        """Raise `RuntimeError` with the end of its log when a child process has exited (unless it was `kill`ed)."""
        _check_children(self._expected_alive(), self.log_dir)

    def _expected_alive(self) -> dict[str, subprocess.Popen]:
        return {name: proc for name, proc in self.children.items() if name not in self._killed}

    def wait_for_convergence(self, progress: Callable[[dict[str, Any]], None] | None = None) -> ArmRunResult:
        """Step 4: until CONVERGED for `settle_images` images, or a limit; images count across service restarts."""
        return _wait_for_convergence(self.settings, self.monitor, self.started, progress, self.settings.out_dir,
                                     self._expected_alive())


@contextmanager
def open_arm_run(settings: ArmRunSettings) -> Iterator[ArmRun]:
    """Steps 1–3 of the module docstring; yields the started, recording run; step 5 (stop everything) at exit."""
    from clients.bag import BagWriter
    from clients.bag_recorder import BagRecorder
    from clients.channels import run_channels
    from clients.foxglove_layout import layout_json
    from clients.record import recording_meta
    from ddvs_service.protocol import Command, ReferenceImage, SessionConfig, encode_upload, open_session

    out = settings.out_dir
    out.mkdir(parents=True, exist_ok=True)
    reference, T_world_ref = render_reference(settings.scene)
    import cv2

    cv2.imwrite(str(out / "reference.png"), reference)
    sim_port, serve_port = _free_port(), _free_port()
    serve = service_config(settings, serve_port, sim_port)
    if settings.launch.get("serve", ChildLaunch()).zenoh is not None:
        serve = serve.model_copy(update={"zenoh": type(serve.zenoh)()})  # the launch flags give the endpoints
    (out / "serve.json").write_text(serve.model_dump_json(indent=2))
    common = ["--prefix", settings.prefix, "--robot", settings.robot]
    if settings.ros_domain_id is not None:
        common += ["--ros-domain-id", str(settings.ros_domain_id)]
    loopback = {
        "sim": ["--listen", f"tcp/127.0.0.1:{sim_port}"],
        "serve": [],
        "bridge": ["--connect", f"tcp/127.0.0.1:{sim_port},tcp/127.0.0.1:{serve_port}"],
    }
    launch_flags = {name: settings.launch.get(name, ChildLaunch()).zenoh for name in CHILDREN}
    zenoh_args = {name: loopback[name] if flags is None else list(flags) for name, flags in launch_flags.items()}
    commands = {
        "sim": ["sim", "arm", "--config", str(settings.scene), "--clock", settings.clock, "--fps", str(settings.fps),
                "--lockstep-timeout", "2", "--start", "start", *zenoh_args["sim"], *common],
        "serve": ["serve", "--config", str(out / "serve.json"), "--fresh", *zenoh_args["serve"]],
        "bridge": ["bridge", "--config", str(settings.bridge), *zenoh_args["bridge"], *common],
    }
    driver = (SessionConfig.model_validate(dict(settings.driver_session)) if settings.driver_session is not None
              else SessionConfig(connect=[f"tcp/127.0.0.1:{sim_port}", f"tcp/127.0.0.1:{serve_port}"]))
    started = time.monotonic()
    with ExitStack() as stack:
        session = stack.enter_context(open_session(driver))
        run = ArmRun(settings, stack, commands, session, started)
        meta = {"reference_pose": T_world_ref.reshape(-1).tolist(), "law": settings.law,
                "template": list(settings.template), "clock": settings.clock, "fps": settings.fps,
                "gain": settings.gain, "stop_threshold": settings.stop_threshold, "scene": str(settings.scene),
                "gain_grid": None if settings.gain_grid is None else list(settings.gain_grid)}
        writer = BagWriter(out / "recording", run_channels(run.keys), recording_meta(run.keys, meta))
        (out / "foxglove-layout.json").write_text(layout_json(run.keys), encoding="utf-8")
        stack.callback(writer.close)
        recorder = BagRecorder(session, run.keys, writer)
        stack.callback(recorder.close)
        stop_recording = threading.Event()
        recorder_thread = threading.Thread(target=recorder.run, args=(stop_recording,), daemon=True)
        recorder_thread.start()
        stack.callback(recorder_thread.join)
        stack.callback(stop_recording.set)
        upload = ReferenceImage(format="png", data=encode_upload(reference, "png"))
        run.command_when_ready(Command(op="set_reference", source="upload", image=upload))
        if settings.start_servo:
            run.command(Command(op="start"))
        yield run


def _check_children(children: dict[str, subprocess.Popen], log_dir: Path) -> None:
    """Raise `RuntimeError` with the end of its log when a child process has exited."""
    for name, proc in children.items():
        if proc.poll() is not None:
            tail = (log_dir / f"{name}.log").read_text(encoding="utf-8", errors="replace")[-2000:]
            raise RuntimeError(f"`ddvs {name}` exited with status {proc.returncode}; end of its log:\n{tail}")


def _wait_for_convergence(settings: ArmRunSettings, monitor: Any, started: float,
                          progress: Callable[[dict[str, Any]], None] | None, out: Path,
                          children: dict[str, subprocess.Popen]) -> ArmRunResult:
    images = 0
    last_seq: int | None = None
    next_report = time.monotonic()
    converged_since: int | None = None
    while True:
        snap = monitor.snapshot()
        elapsed = time.monotonic() - started
        seq = snap.get("seq")
        if snap["state"] in ("SERVOING", "CONVERGED") and seq is not None:
            if last_seq is not None:
                images += seq - last_seq if seq >= last_seq else seq  # seq restarts with a restarted service
            last_seq = seq
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
