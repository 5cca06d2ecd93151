"""What `ddvs serve` does before it declares itself alive: the kernels' warm-up.

Warm-up: Taichi compiles (or, with its offline cache warm, loads and links) each kernel on its first launch, which
made the first frame after a start or an upload take tens of frame periods (docs/performance.md). `warm_up` runs the
configuration's whole frame path once on a synthetic scene — reference preparation, the global initialiser of the
first frame, tracking, the control law — so that those launches happen before the service answers anything.
Kernels are specialised on their template arguments (gain grid, model, ρ* degree), not on image sizes, so any
frame size compiles the same code; the configured or persisted intrinsics are used when known.

Ahead of time: Taichi's offline cache keeps what a warm-up compiled, keyed by each kernel's code and template
arguments, for every later process. `warm_up_configured` (`ddvs serve --warmup-only`, run by `scripts/setup.sh` for
the shipped configurations) fills it for a configuration's robots without serving, so a first start is a warm one.
Taichi compiles on one thread of a process, so a general configuration's cold warm-up is split between two
processes sharing the offline cache: a forked helper (`start_general_steps`) compiles the general engine's step
kernels (`warm_up_general_steps`, about half of the compile time), while this process compiles the rest — what the
configuration's warm-up with the planar model compiles: the pyramids, the global initialiser and the planar engine
of the general model's first stage. Taichi's offline cache merges the entries of both processes under its file
lock; the helper writes its entries before this process writes its own (`warm_up_configured` waits for it), so the
two writes never contend for that lock (Taichi drops a write it cannot lock within 0.2 s).
"""

from __future__ import annotations

import multiprocessing
import os
import time
from collections.abc import Sequence
from multiprocessing.process import BaseProcess

import cv2
import numpy as np
from numpy.typing import NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.registration.general_basis import coefficient_count
from ddvs_service.service.config import ServiceConfig
from ddvs_service.service.fleet_config import FleetConfig
from ddvs_service.service.pipeline import ServoPipeline, template_roi

WARM_UP_INTRINSICS = Intrinsics(420.0, 420.0, 159.5, 119.5, 320, 240)  # when none is configured or persisted


def _fitting(intrinsics: Intrinsics, roi: tuple[int, int, int, int] | None) -> Intrinsics:
    """`intrinsics` grown (principal point kept centred) until a configured ROI fits in the image."""
    if roi is None:
        return intrinsics
    width, height = max(intrinsics.width, roi[0] + roi[2]), max(intrinsics.height, roi[1] + roi[3])
    return Intrinsics(intrinsics.fx, intrinsics.fy, (width - 1) / 2, (height - 1) / 2, width, height)


def synthetic_scene(intrinsics: Intrinsics, seed: int = 0) -> np.ndarray:
    """A textured 8-bit grey image of the camera's size: smoothed noise, enough structure to register."""
    rng = np.random.default_rng(seed)
    noise = rng.uniform(0.0, 255.0, (intrinsics.height, intrinsics.width)).astype(np.float32)
    return np.clip(cv2.GaussianBlur(noise, (0, 0), 2.0) * 3.0 - 255.0, 0, 255).astype(np.uint8)


def warm_up(config: ServiceConfig, intrinsics: Intrinsics | None, initialiser: bool = True) -> float:
    """Run the configured frame path once on a synthetic scene; return the seconds it took. `initialiser` False:
    the tracking path only (a robot resuming alone from its persisted last good estimate; `needs_initialiser`):
    a planar one from the identity, a general one resumed as a restart does, from the identity with ρ* known (zero:
    the synthetic scene is a plane)."""
    t0 = time.monotonic()
    intrinsics = intrinsics or _fitting(WARM_UP_INTRINSICS, config.registration.roi)
    if not initialiser:  # nor its reference side (the tracking kernels do not depend on this setting)
        config = config.model_copy(update={"registration": config.registration.model_copy(
            update={"global_init": False})})
    pipeline = ServoPipeline(config, intrinsics, background_reacquisition=False)  # the initialiser on this thread
    reference = synthetic_scene(intrinsics)
    if initialiser:
        pipeline.set_reference(reference)
    elif config.registration.model == "general":
        rho = [0.0] * coefficient_count(config.registration.general_config().rho_degree)
        pipeline.set_reference(reference, rho_coeffs=rho, last_good=np.eye(3))
    else:
        pipeline.set_reference(reference, G0=np.eye(3))
    pipeline.machine.start()
    for dx in (1.5, 2.0):  # the first frame from the global initialiser's start (or the identity), then tracked
        pipeline.step(_shifted(reference, dx))
    return time.monotonic() - t0


def _shifted(image: np.ndarray, dx: float) -> np.ndarray:
    """`image` moved by (dx, −dx) pixels, borders reflected: a frame that a warm-up's registration converges on."""
    height, width = image.shape[:2]
    return cv2.warpAffine(image, np.array([[1.0, 0.0, dx], [0.0, 1.0, -dx]]), (width, height),
                          borderMode=cv2.BORDER_REFLECT)


def warm_up_general_steps(config: ServiceConfig, intrinsics: Intrinsics | None) -> float:
    """Compile the general engine's step kernels of `config` (general model): `kernels.general_step` with the ρ*
    columns and without. One frame of the synthetic scene is tracked at full resolution from a start with parallax
    (ρ* and `e` non-zero; twice `min_parallax_px`, at least 1 px RMS), so that its first launch is the information
    launch of `GeneralRegistration.track` (with the ρ* columns) and the next ones are not. Returns the seconds it
    took."""
    from ddvs_service.registration.general import GeneralRegistration

    t0 = time.monotonic()
    intrinsics = intrinsics or _fitting(WARM_UP_INTRINSICS, config.registration.roi)
    reference = synthetic_scene(intrinsics)
    general = config.registration.general_config()
    engine = GeneralRegistration.prepare(reference.astype(np.float32), template_roi(config, intrinsics), config=general)
    e = np.linalg.solve(engine.N0, np.array([1.0, 0.0, 0.0]))  # a lateral epipole, ‖N₀ e‖ = 1
    rho = np.zeros(engine.basis.size)
    rho[0] = 1.0
    rho *= max(1.0, 2.0 * general.min_parallax_px) / engine.parallax_rms(np.eye(3), e, rho)  # ∝ ρ* (G = I)
    engine.track(_shifted(reference, 1.5).astype(np.float32), np.eye(3), e, rho, first_level=0)
    return time.monotonic() - t0


def needs_initialiser(config: ServiceConfig, last_good: NDArray[np.float64] | None, alone: bool,
                      rho_coeffs: Sequence[float] = ()) -> bool:
    """Whether a robot's warm-up must compile the global initialiser's kernels too: always without a last good
    estimate to re-acquire from (a new reference, a first start), for the general model without persisted ρ*
    coefficients `rho_coeffs` (its first frame estimates ρ* from the initialiser's start) and when the process
    serves other robots (`alone` False). A robot resuming alone from its persisted estimate (and ρ*) does not: its
    warm-up leaves the initialiser's kernels (about half of a warm planar start's compile time, more than half of a
    general one's) to the first search that needs them, on the re-acquisition worker. That compile holds the GIL
    (Taichi's code generation does not release it), so the loop pauses for it once (about 0.4 s of CPU for the
    planar model, more wall time on a loaded host) while the robot is LOST and its twist zero — a pause other robots
    of the process would share while they move, hence not with them."""
    unknown_rho = config.registration.model == "general" and not rho_coeffs
    return last_good is None or unknown_rho or not alone


def _distinct(fleet: FleetConfig) -> dict[str, tuple[ServiceConfig, Intrinsics | None]]:
    """The configured robots of `fleet` with distinct registration settings (the first robot of each), robot name →
    its configuration and configured intrinsics (robots with the same registration settings share their kernels)."""
    distinct: dict[str, tuple[ServiceConfig, Intrinsics | None]] = {}
    keys: set[str] = set()
    for name, settings in fleet.configured.items():
        config = fleet.robot_config(name, settings)
        key = config.registration.model_dump_json()
        if key not in keys:
            keys.add(key)
            distinct[name] = (config, config.intrinsics.to_intrinsics() if config.intrinsics is not None else None)
    return distinct


def start_general_steps(fleet: FleetConfig, arch: str | None, fallback: bool) -> BaseProcess | None:
    """Fork the helper process that compiles the general engine's step kernels of `fleet`'s general configurations
    (`warm_up_general_steps`) into the offline cache on Taichi backend `arch` (`kernels.backend.init`'s `arch` and
    `fallback`), or None when no robot uses the general model or this process may run on one core only (the helper
    would then only add its own start-up). Call it before Taichi starts in this process (a fork would copy a started
    program without its threads) and pass it to `warm_up_configured`."""
    general = [robot for robot in _distinct(fleet).values() if robot[0].registration.model == "general"]
    if not general or len(os.sched_getaffinity(0)) < 2:
        return None
    helper = multiprocessing.get_context("fork").Process(target=_general_steps, args=(general, arch, fallback),
                                                        name="ddvs-warm-up-general-steps")
    helper.start()
    return helper


def _general_steps(robots: list[tuple[ServiceConfig, Intrinsics | None]], arch: str | None, fallback: bool) -> None:
    """The helper process of `start_general_steps`: exit status 3 when the backend cannot start (as `ddvs serve`;
    the parent, which fails to start it too, says why)."""
    from kernels.backend import BackendUnavailable, finish, init

    try:
        init(arch, fallback=fallback)
    except BackendUnavailable:
        raise SystemExit(3) from None
    for config, intrinsics in robots:
        warm_up_general_steps(config, intrinsics)
    finish()  # writes the offline cache: a forked process exits without the interpreter's exit handlers


def warm_up_configured(fleet: FleetConfig, general_steps: BaseProcess | None = None) -> dict[str, float]:
    """Warm up the kernels of each configured robot of `fleet` (robots with the same registration settings share
    their kernels: 0 s for all but the first); robot name → seconds this process spent on them. `general_steps`:
    the helper of `start_general_steps`, which compiles the general engines' step kernels; this process then warms
    each general configuration as the planar model (the rest of its kernels, module docstring) and waits for the
    helper (`RuntimeError` when it failed). Reads and writes no state directory."""
    distinct = _distinct(fleet)
    seconds: dict[str, float] = {}
    for name in fleet.configured:
        if name not in distinct:
            seconds[name] = 0.0
            continue
        config, intrinsics = distinct[name]
        if general_steps is not None and config.registration.model == "general":
            config = config.model_copy(update={"registration": config.registration.model_copy(
                update={"model": "planar"})})
        seconds[name] = warm_up(config, intrinsics)
    if general_steps is not None:
        general_steps.join()
        if general_steps.exitcode != 0:
            raise RuntimeError(f"the general engines' warm-up process failed (exit status {general_steps.exitcode})")
    return seconds
