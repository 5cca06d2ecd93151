"""Where a tracker (re)starts: on the first frame after a reference and after LOST, for the planar and the general
model alike.

`Reacquisition` runs the direct global initialiser (`global_init.GlobalInitializer`, with its settings: hypothesis
sources such as `feature_source`, LOST criteria) on the tracker's own engines, so that the prepared reference is
built once for both; when re-acquisition is off (`config` None) it reports "OFF" and the tracker goes on from its
own last estimate.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from ddvs_service.registration.general import GeneralRegistration
from ddvs_service.registration.global_init import GlobalInitConfig, GlobalInitializer, InitResult, reacquire
from ddvs_service.registration.planar import PlanarRegistration

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
LAST_GOOD = "the last good estimate"  # the reason of an OK answer that hands back the caller's own last good estimate


@dataclass(frozen=True)
class Acquisition:
    """`status` "OK" (start from `G`), "LOST" (no confident estimate: `reason`) or "OFF" (re-acquisition disabled);
    `contradicts`: an OK `G` far from the tracker's own estimate (`global_init.reacquire`); `found`: the
    initialiser's whole result (None when off)."""

    status: Literal["OK", "LOST", "OFF"]
    G: F64 | None
    reason: str
    contradicts: bool = False
    found: InitResult | None = None


class Reacquisition:
    """Re-acquisition for a tracker on `engine` (and `general`, the general model's engine, which the initialiser's
    step 5 then uses), with the initialiser's `config`; None: off. `adopted` counts the OK results handed over.
    `prepare`: build the initialiser's reference side now, with the reference, rather than in the first search.
    `beside`: the search runs beside the caller's loop (`service.reacquirer`) and makes the attempt from the
    caller's last good estimate itself; here it runs within the call, and the caller makes that attempt first."""

    beside = False

    def __init__(self, engine: PlanarRegistration, general: GeneralRegistration | None = None,
                 config: GlobalInitConfig | None = None, prepare: bool = True) -> None:
        self.engine = engine
        self.initializer = None if config is None else GlobalInitializer(config, engine=engine, general=general)
        if self.initializer is not None and prepare:
            self.initializer.reference_side(engine.prepared.image, engine.prepared.roi)
        self.adopted = 0  # OK results handed to the caller

    @property
    def enabled(self) -> bool:
        return self.initializer is not None

    @property
    def busy(self) -> bool:
        """Never: this search runs within the call (`service.reacquirer` searches beside the caller)."""
        return False

    def __call__(self, current: F32, tracking_G: F64 | None = None, start: F64 | None = None) -> Acquisition:
        """Initialise `current` against the engine's reference and ROI; `tracking_G`: the tracker's own estimate,
        to report a strong contradiction. `start` (the caller's last good estimate) matters only `beside` the loop:
        within the call the caller has tried it already."""
        found = self.search(current, tracking_G)
        if found.status == "OK":
            self.adopted += 1
        return found

    def search(self, current: F32, tracking_G: F64 | None = None) -> Acquisition:
        """The search itself (what `__call__` hands over), on the calling thread."""
        if self.initializer is None:
            return Acquisition("OFF", None, "re-acquisition is off")
        prepared = self.engine.prepared
        found, contradicts = reacquire(self.initializer, prepared.image, prepared.roi, current, tracking_G)
        if found.status == "OK" and found.G is not None:
            return Acquisition("OK", found.G, found.reason, contradicts, found)
        return Acquisition("LOST", None, found.reason, found=found)

    def cancel(self) -> None:
        """Nothing to forget: this search runs within the call (`service.reacquirer` runs it beside the caller)."""

    def close(self) -> None:
        """Nothing to end (see `cancel`)."""
