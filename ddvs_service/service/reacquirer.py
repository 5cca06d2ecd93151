"""Re-acquisition beside the servo loop: the global initialiser on its own thread, at its own rate.

A LOST frame must cost the loop at most a frame period, and the global initialiser takes 0.1–2 s.
`BackgroundReacquisition` is a `registration.reacquisition.Reacquisition` whose call returns at once:
- a search that finished since the last call hands over its result: an OK one (`G` of the frame it searched, a
  few frames old: the servo holds the camera still while LOST, and the caller validates `G` by tracking the newest
  frame from it before acting on it), or a LOST one (its reason is reported, and the newest frame is searched next);
- otherwise the call answers LOST ("searching in the background") and leaves `current` as the frame to search next,
  replacing any frame left before (the worker always takes the newest frame when it becomes free, never a queue).
A call may also hand over `start`, the caller's last good estimate: the worker's search then first tries `retry`
(the caller's tracking from it, on the worker's engine), and when that registers the frame answers OK with `start`
itself and the reason `LAST_GOOD` (the caller tracks on from its own state: the cheapest re-acquisition, and the only
one that survives a large occluder), else runs the global initialiser. A failing attempt from the last good
estimate costs a full registration budget: on the worker, never on the loop.

The worker thread starts on the first call and holds the Taichi gate (`kernels.exclusive.GATE`) in the background
while it searches, so the loop's registrations (and other servos' in the same process) go first at each of its
checkpoints. The initialiser's reference side (the reference's spectra) is built by the first global search, on the
worker, not with the reference on the caller's thread. `cancel()` drops the frame waiting and any result not yet
handed over (the tracker re-acquired by itself); `close()` ends the thread after its current search (a new
reference: the search is for the old one).
Its engines (`engine`, `general`) must not be the caller's tracker's (a prepared reference may be shared, a
workspace may not): the tracker keeps registering frames while the worker searches.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from ddvs_service.registration.general import GeneralRegistration
from ddvs_service.registration.global_init import GlobalInitConfig
from ddvs_service.registration.planar import PlanarRegistration
from ddvs_service.registration.reacquisition import LAST_GOOD, Acquisition, Reacquisition
from kernels.exclusive import GATE

log = logging.getLogger("ddvs.reacquisition")
F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
SEARCHING = "searching in the background"
Retry = Callable[[NDArray[np.float32], NDArray[np.float64]], bool]  # (frame, start) -> registered from `start`


class BackgroundReacquisition(Reacquisition):
    """`Reacquisition` on a worker thread (module docstring); `searches` counts the searches finished, `adopted` the
    initialiser's OK results handed over (not `LAST_GOOD` answers). `retry`: the caller's attempt from its last good
    estimate, run on the worker (it must use the worker's engines only)."""

    beside = True

    def __init__(self, engine: PlanarRegistration, general: GeneralRegistration | None = None,
                 config: GlobalInitConfig | None = None, retry: Retry | None = None) -> None:
        super().__init__(engine, general, config, prepare=False)  # the reference side: on the worker, when needed
        self._retry = retry
        self._cond = threading.Condition()
        # the newest frame left to search, the tracker's G and where `retry` starts (None: no attempt)
        self._frame: tuple[F32, F64 | None, F64 | None] | None = None
        self._result: Acquisition | None = None
        self._busy = False
        self._closed = False
        self._generation = 0  # bumped by cancel/close: a search started before gives no result
        self._thread: threading.Thread | None = None
        self.searches = 0

    @property
    def busy(self) -> bool:
        """True while a search runs, a frame waits for one, or an OK result waits to be handed over: the next call
        answers from the search, so a caller need not try anything else first (a tracker's attempt from its last
        good estimate would cost the frame a full registration budget when it fails)."""
        with self._cond:
            return self._searching() or (self._result is not None and self._result.status == "OK")

    def __call__(self, current: F32, tracking_G: F64 | None = None, start: F64 | None = None) -> Acquisition:
        """A finished search's result, or LOST while searching; `current` is searched next (from `start` first, when
        given) unless an OK result is handed over (module docstring)."""
        if not self.enabled:
            return self.search(current, tracking_G)
        with self._cond:
            if self._closed:
                raise RuntimeError("re-acquisition is closed")
            result, self._result = self._result, None
            if result is not None and result.status == "OK":
                self._frame = None  # the caller tracks from it: no search unless it asks again
                self.adopted += result.reason != LAST_GOOD  # the initialiser's poses only
                return result
            self._frame = (np.array(current, dtype=np.float32, copy=True), _copy(tracking_G), _copy(start))
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="ddvs-reacquisition", daemon=True)
                self._thread.start()
            self._cond.notify_all()
        reason = SEARCHING if result is None else f"{result.reason}; {SEARCHING} on a newer frame"
        return Acquisition("LOST", None, reason, found=None if result is None else result.found)

    def cancel(self) -> None:
        """Forget the frame waiting and any result not handed over yet (a search under way finishes unused)."""
        with self._cond:
            if self._frame is None and self._result is None and not self._busy:
                return
            self._frame, self._result = None, None
            self._generation += 1

    def close(self, timeout_s: float | None = None) -> None:
        """End the worker after its current search; wait for it up to `timeout_s` (None: do not wait)."""
        with self._cond:
            self._closed = True
            self._frame, self._result = None, None
            self._generation += 1
            self._cond.notify_all()
            thread = self._thread
        if thread is not None and timeout_s is not None:
            thread.join(timeout_s)

    def wait_idle(self, timeout_s: float) -> bool:
        """Block until no search runs and no frame waits (True), or `timeout_s` passed (False). For tests and
        benchmarks, never in the servo loop."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._searching(), timeout_s)

    def search(self, current: F32, tracking_G: F64 | None = None, start: F64 | None = None) -> Acquisition:
        """The worker's search, on the calling thread: `retry` from `start` first (when both are given), then the
        global initialiser (`Reacquisition.search`)."""
        if start is not None and self._retry is not None and self._retry(current, start):
            return Acquisition("OK", start, LAST_GOOD)
        return super().search(current, tracking_G)

    def _searching(self) -> bool:
        """A search runs, or one will start on the frame left (none starts while a result waits to be handed over;
        the condition's lock held)."""
        return self._busy or (self._frame is not None and self._result is None)

    def _run(self) -> None:
        while True:
            with self._cond:
                # a result not handed over yet comes first: the frame left meanwhile may not need a search
                self._cond.wait_for(lambda: self._closed or (self._frame is not None and self._result is None))
                if self._closed:
                    return
                assert self._frame is not None
                (current, tracking_G, start), self._frame = self._frame, None
                generation, self._busy = self._generation, True
            try:
                with GATE.background():
                    result = self.search(current, tracking_G, start)
            except Exception as exc:  # a failed search is a LOST answer, never the end of the worker
                log.exception("re-acquisition failed")
                result = Acquisition("LOST", None, f"re-acquisition error: {type(exc).__name__}: {exc}")
            with self._cond:
                self._busy = False
                self.searches += 1
                if generation == self._generation:
                    self._result = result
                self._cond.notify_all()


def _copy(G: F64 | None) -> F64 | None:
    return None if G is None else np.array(G, dtype=np.float64)
