"""What a LOST frame costs the servo loop: re-acquisition beside the loop (worker thread) against within it (issue 20).

The service's per-frame code (`ServoPipeline`, shipped configuration `configs/serve/ur5_poster.json`, f = 420 px,
320×240 frames of the textured poster, template 70×70, the shipped 140×140 or a 200×150 ROI) servos on the
reference view, then the view turns by 40° about the optical axis and shifts (`--turn-deg`): beyond the tracker's
reach, so the frame is LOST and only the global initialiser finds the pose again. Frames of that view are fed at
30 Hz (each `step` starts on the next 33.3 ms tick, or at once when the previous one ran late) until the servo is
SERVOING again (the error guard holds a view that jumped for `rebase_frames` frames) or `--timeout` s passed.

Per mode: the step time of the frames up to the re-acquisition (median, max); how many were answered while the
worker searched with no registration of their own and the longest of those; the step times of the frames that ran a
tracker registration (the first LOST frame's failed one and the adopting one; inline also the attempt from the last
good estimate, which in background mode the worker makes: a registration's cost, whoever makes it); the time from
the first LOST frame to SERVOING, the searches the worker ran, the longest a `step` waited for the Taichi gate
(`kernels.exclusive.GATE`) while the worker held it, the longest the worker held the gate between two of its
checkpoints (`HoldTimer`: the longest a frame's `hold` can wait) and the median time of its searches (with its
attempt from the last good estimate); and what the gate costs when uncontended (one `hold` per step, one
`checkpoint` per prepared kernel launch). Inline mode (`background_reacquisition=False`) is the baseline: every LOST
frame runs the whole initialiser. Load: this process alone (one loop thread and, in background mode, one worker)
after the service's warm-up (`service.startup`: every kernel compiled); the load average is printed with the
figures.

    .venv/bin/python benchmarks/bench_reacquisition.py [--rois 70 140 200] [--turn-deg 40] [--timeout 20] [--runs 1]
        [--modes background inline] [--holds 7] [--failing 15]

`--failing N`: the registration of the frame that discovers the loss alone (`Tracker.track` of the turned view with
the service's engine settings: the warm attempt and the retry over the pyramid, both failing), N times on the same
state (a failure leaves it unchanged, so each repeat takes the same path): its minimum, which removes a shared
machine's preemptions, and median.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
import timeit
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ddvs_service.camera import Intrinsics  # noqa: E402 - after the path set-up for running as a script
from ddvs_service.lie import so3_exp  # noqa: E402
from ddvs_service.registration.tracker import Tracker  # noqa: E402
from ddvs_service.service.config import ServiceConfig  # noqa: E402
from ddvs_service.service.pipeline import ServoPipeline  # noqa: E402
from ddvs_service.service.startup import warm_up  # noqa: E402
from ddvs_service.service.state import ServoState  # noqa: E402
from kernels.exclusive import GATE, Gate  # noqa: E402
from sim.planar_scene import POSTER_BLUR_SIGMA, PlanarScene  # noqa: E402
from sim.textures import TEXTURES, load_texture  # noqa: E402

CAM = Intrinsics.centred(420.0, 320, 240)
PERIOD_S = 1.0 / 30.0
ROIS = {70: (125, 85, 70, 70), 140: (90, 50, 140, 140), 200: (60, 45, 200, 150)}


class HoldTimer:
    """Times the worker's holds of the gate between two of its checkpoints (a frame's `hold` waits at most for the
    rest of one) and its searches: shadows `GATE.checkpoint` and the worker's `search` until `close()`. `holds`:
    per search, every hold in order as (seconds, where it began → where it ended)."""

    def __init__(self, worker: object) -> None:
        self.searches_s: list[float] = []
        self.holds: list[list[tuple[float, str]]] = []
        self._thread: int | None = None
        self._last: tuple[float, str] | None = None
        self._checkpoint = GATE.checkpoint
        self._worker = worker
        search: Callable[..., object] = worker.search  # type: ignore[attr-defined]

        def timed(*args: object) -> object:
            self._thread = threading.get_ident()
            self.holds.append([])
            start = time.perf_counter()
            self._last = (start, "search start")
            try:
                return search(*args)
            finally:
                self._mark("search end")
                self._last = None
                self.searches_s.append(time.perf_counter() - start)

        worker.search = timed  # type: ignore[attr-defined]
        GATE.checkpoint = self.checkpoint  # type: ignore[method-assign]

    @property
    def longest_hold_s(self) -> float:
        return max((t for holds in self.holds for t, _ in holds), default=float("nan"))

    def checkpoint(self) -> None:
        if threading.get_ident() != self._thread:
            self._checkpoint()
            return
        caller = sys._getframe(1)
        if caller.f_code.co_filename.endswith("launch.py") and caller.f_back is not None:
            caller = caller.f_back  # a prepared launch: where the engine launched it
        where = f"{Path(caller.f_code.co_filename).name}:{caller.f_lineno}"
        if caller.f_back is not None:  # and from where: helpers (sampling, scoring) are called from several places
            where = f"{Path(caller.f_back.f_code.co_filename).name}:{caller.f_back.f_lineno}/{where}"
        self._mark(where)
        self._checkpoint()
        self._last = (time.perf_counter(), where)  # a hand-over's wait is not a hold

    def _mark(self, where: str) -> None:
        if self._last is not None:
            began, source = self._last
            self.holds[-1].append((time.perf_counter() - began, f"{source} → {where}"))

    def close(self) -> None:
        del GATE.checkpoint  # the class's method again
        del self._worker.search  # type: ignore[attr-defined]


def hold_profile(scene: PlanarScene, roi: tuple[int, int, int, int], turn_deg: float, repeats: int
                 ) -> dict[str, object]:
    """The worker's holds of the gate without the noise of a shared machine: the same search `repeats` times on
    this thread (holding the gate in the background, as the worker does); each hold's time is its minimum over the
    repeats (the search is deterministic: the same holds in the same order). Returns the longest such hold, where it
    lies, the sum of all (≈ the search's own time) and the median search time."""
    servo = ServoPipeline(service_config(roi), CAM, background_reacquisition=True)
    reference = np.clip(np.rint(scene.render()), 0, 255).astype(np.uint8)
    servo.set_reference(reference, roi, G0=np.eye(3))
    H = scene.homography(so3_exp(np.radians([0.0, 0.0, turn_deg])), np.array([0.03, 0.0, 0.0]))
    moved = np.clip(np.rint(scene.render(H)), 0, 255).astype(np.float32)
    worker = servo._estimator._acquire  # type: ignore[union-attr]
    timer = HoldTimer(worker)
    try:
        for _ in range(repeats):
            with GATE.background():
                worker.search(moved)
    finally:
        timer.close()
        servo.close()
    if len({len(holds) for holds in timer.holds}) != 1:
        raise RuntimeError("the repeated searches did not take the same path")
    fastest = np.min([[t for t, _ in holds] for holds in timer.holds], axis=0)
    k = int(np.argmax(fastest))
    return {"roi": f"{roi[2]}x{roi[3]}", "holds": len(fastest), "longest_hold_ms": float(fastest[k]) * 1e3,
            "where": timer.holds[0][k][1], "sum_ms": float(fastest.sum()) * 1e3,
            "search_ms_median": float(np.median(timer.searches_s)) * 1e3, "load_average": os.getloadavg()[0]}


def failing_profile(scene: PlanarScene, roi: tuple[int, int, int, int], turn_deg: float, repeats: int
                    ) -> dict[str, object]:
    """The failing registration of the turned view, `repeats` times on one tracker's unchanged state (module
    docstring): minimum and median ms."""
    reference = np.clip(np.rint(scene.render()), 0, 255).astype(np.float32)
    H = scene.homography(so3_exp(np.radians([0.0, 0.0, turn_deg])), np.array([0.03, 0.0, 0.0]))
    moved = np.clip(np.rint(scene.render(H)), 0, 255).astype(np.float32)
    tracker = Tracker.prepare(reference, roi, service_config(roi).registration.engine_config())
    for _ in range(3):
        tracker.track(reference)
    times_ms = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = tracker.track(moved)
        times_ms.append((time.perf_counter() - start) * 1e3)
        if result.converged:
            raise RuntimeError(f"the turned view was tracked: {result.reason}")
    return {"roi": f"{roi[2]}x{roi[3]}", "failing_registration_ms_min": min(times_ms),
            "failing_registration_ms_median": float(np.median(times_ms)), "reason": result.reason,
            "load_average": os.getloadavg()[0]}


def service_config(roi: tuple[int, int, int, int]) -> ServiceConfig:
    return ServiceConfig.from_file(ROOT / "configs" / "serve" / "ur5_poster.json").merged({
        "intrinsics": {"fx": CAM.fx, "fy": CAM.fy, "cx": CAM.cx, "cy": CAM.cy, "width": CAM.width,
                       "height": CAM.height},
        "registration": {"roi": list(roi)}})


def measure(scene: PlanarScene, roi: tuple[int, int, int, int], background: bool, turn_deg: float,
            timeout_s: float) -> dict[str, object]:
    servo = ServoPipeline(service_config(roi), CAM, background_reacquisition=background)
    reference = np.clip(np.rint(scene.render()), 0, 255).astype(np.uint8)
    servo.set_reference(reference, roi, G0=np.eye(3))
    servo.machine.start()
    for _ in range(5):
        servo.step(reference)
    H = scene.homography(so3_exp(np.radians([0.0, 0.0, turn_deg])), np.array([0.03, 0.0, 0.0]))
    moved = np.clip(np.rint(scene.render(H)), 0, 255).astype(np.uint8)
    worker = getattr(servo._estimator, "_acquire", None)
    timer = HoldTimer(worker) if background else None
    GATE.longest_wait_s = 0.0
    searching_ms: list[float] = []  # the frames up to the one that adopted the initialiser's pose
    held_ms: list[float] = []  # LOST frames after it: the error guard holds a view that jumped
    while_searching_ms: list[float] = []  # those answered while the worker searched, with no registration of their own
    registrations_ms: list[float] = []  # those that ran a tracker registration (failed, adoption; inline: last good)
    t_first = time.perf_counter()
    tick = t_first
    state, adopted = ServoState.SERVOING, False
    while time.perf_counter() - t_first < timeout_s:
        tick = max(tick + PERIOD_S, time.perf_counter())
        time.sleep(max(0.0, tick - time.perf_counter()))
        t0 = time.perf_counter()
        step = servo.step(moved)
        dt_ms = (time.perf_counter() - t0) * 1e3
        state = step.state
        if state == ServoState.SERVOING:
            break
        assert not np.any(step.twist), "a LOST frame was answered with a non-zero twist"
        if adopted:
            held_ms.append(dt_ms)
        else:
            searching_ms.append(dt_ms)
            if not step.message.startswith("global initialisation: LOST ("):
                registrations_ms.append(dt_ms)
            elif getattr(worker, "busy", False):
                while_searching_ms.append(dt_ms)
            adopted = step.message.startswith(("global initialisation: ok", "re-acquired by tracking"))
    recovered_s = time.perf_counter() - t_first
    servo.close()
    if timer is not None:
        getattr(worker, "wait_idle", lambda _: True)(10.0)
        timer.close()
    search = np.asarray(searching_ms)
    return {
        "roi": f"{roi[2]}x{roi[3]}", "mode": "background" if background else "inline",
        "frames_to_reacquire": len(searching_ms), "answered_while_searching": len(while_searching_ms),
        "step_ms_median": float(np.median(search)), "step_ms_max": float(search.max()),
        "while_searching_ms_max": max(while_searching_ms, default=float("nan")),
        "registration_frames_ms": [round(t, 1) for t in registrations_ms],
        "held_frames": len(held_ms), "held_step_ms_max": max(held_ms, default=float("nan")),
        "to_servoing_s": recovered_s if state == ServoState.SERVOING else None,
        "searches": getattr(worker, "searches", None), "gate_longest_wait_ms": GATE.longest_wait_s * 1e3,
        "worker_longest_hold_ms": timer.longest_hold_s * 1e3 if timer else float("nan"),
        "search_ms_median": float(np.median(timer.searches_s)) * 1e3 if timer and timer.searches_s else float("nan"),
        "load_average": os.getloadavg()[0],
    }


def gate_overhead(n: int = 100_000) -> dict[str, float]:
    """What the gate costs a step when no other thread wants it: one `hold()` (a step takes it once, the residual
    once more) and one `checkpoint()` (each prepared kernel launch), microseconds."""
    gate = Gate()

    def hold() -> None:
        with gate.hold():
            pass

    return {"hold_us": timeit.timeit(hold, number=n) / n * 1e6,
            "checkpoint_us": timeit.timeit(gate.checkpoint, number=n) / n * 1e6}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rois", type=int, nargs="+", default=[70, 200], choices=sorted(ROIS))
    parser.add_argument("--turn-deg", type=float, default=40.0)
    parser.add_argument("--timeout", type=float, default=20.0)
    parser.add_argument("--runs", type=int, default=1, help="runs of each ROI and mode")
    parser.add_argument("--modes", nargs="+", default=["background", "inline"], choices=["background", "inline"])
    parser.add_argument("--holds", type=int, default=0, metavar="N",
                        help="also profile the worker's holds of the gate over N repeated searches per ROI")
    parser.add_argument("--failing", type=int, default=0, metavar="N",
                        help="also time the failing registration of the first LOST frame N times per ROI")
    args = parser.parse_args()
    scene = PlanarScene(CAM, load_texture(TEXTURES[1], POSTER_BLUR_SIGMA))
    print(f"warm-up (the service's, kernels compiled or loaded): {warm_up(service_config(ROIS[70]), CAM):.1f} s; "
          f"load average before: {os.getloadavg()}", flush=True)
    for _ in range(args.runs):
        for size in args.rois:
            for mode in args.modes:
                row = measure(scene, ROIS[size], mode == "background", args.turn_deg, args.timeout)
                print({k: round(v, 2) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
    for size in args.rois if args.failing else []:
        row = failing_profile(scene, ROIS[size], args.turn_deg, args.failing)
        print({k: round(v, 2) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
    for size in args.rois if args.holds else []:
        row = hold_profile(scene, ROIS[size], args.turn_deg, args.holds)
        print({k: round(v, 2) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
    print(f"uncontended gate: { {k: round(v, 2) for k, v in gate_overhead().items()} }", flush=True)
    print(f"load average after: {os.getloadavg()}", flush=True)


if __name__ == "__main__":
    main()
