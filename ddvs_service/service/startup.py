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
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from ddvs_service.camera import Intrinsics
from ddvs_service.registration.general_basis import coefficient_count
from ddvs_service.service.config import ServiceConfig
from ddvs_service.service.fleet_config import FleetConfig
from ddvs_service.service.pipeline import ServoPipeline

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
        pipeline.step(cv2.warpAffine(reference, np.array([[1.0, 0.0, dx], [0.0, 1.0, -dx]]),
                                     (intrinsics.width, intrinsics.height), borderMode=cv2.BORDER_REFLECT))
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


def warm_up_configured(fleet: FleetConfig) -> dict[str, float]:
    """Warm up the kernels of each configured robot of `fleet` (robots with the same registration settings share
    their kernels: 0 s for all but the first); robot name → seconds. Reads and writes no state directory."""
    seconds: dict[str, float] = {}
    warmed: set[str] = set()
    for name, settings in fleet.configured.items():
        config = fleet.robot_config(name, settings)
        key = config.registration.model_dump_json()
        intrinsics = config.intrinsics.to_intrinsics() if config.intrinsics is not None else None
        seconds[name] = 0.0 if key in warmed else warm_up(config, intrinsics)
        warmed.add(key)
    return seconds
