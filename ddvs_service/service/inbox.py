"""Hand-off from Zenoh callbacks to the servo loop thread, with a wake-up the moment something arrives.

Zenoh runs subscriber and queryable callbacks on its own threads; they must neither block nor call Zenoh
(PLATFORM-NOTES), so each callback here only stores what arrived under a lock and notifies one condition variable.
The loop thread sleeps on that condition (`wait`) instead of polling: a frame is handed over within one thread
wake-up, not after up to one polling period, and an idle service costs no CPU.

What is kept: the newest frame and the newest camera info only (a slow loop skips frames, never queues them, as
`RingChannel(1)` would), and the pending commands in arrival order, at most `max_queries` (beyond that the oldest is
dropped: its querier gets no reply and times out, and the Zenoh session never stalls behind a full queue).

Frame bookkeeping happens here, where frames arrive, so it does not depend on when the loop looks: each frame gets
its arrival index (1, 2, …) and arrival time (`time.monotonic()`, seconds), the time of the last arrival is what the
watchdog measures, and a frame superseded before the loop took it is counted once, when it is superseded (`dropped`
only grows).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Generic, TypeVar

import zenoh

SampleT = TypeVar("SampleT")


@dataclass(frozen=True)
class Arrival(Generic[SampleT]):
    """A frame as it arrived: the sample, its arrival index (the n-th frame received) and time (monotonic s)."""

    sample: SampleT
    index: int
    t: float


class Inbox:
    """Latest frame, latest camera info and pending commands, filled by Zenoh callbacks, drained by one thread."""

    def __init__(self, max_queries: int = 64) -> None:
        self._ready = threading.Condition()
        self._frame: Arrival[zenoh.Sample] | None = None
        self._info: zenoh.Sample | None = None
        self._queries: deque[zenoh.Query] = deque(maxlen=max_queries)
        self._frames_received = 0
        self._frames_superseded = 0
        self._last_arrival_t = time.monotonic()

    # --- Zenoh callbacks (Zenoh's threads; never block) ---------------------------------------------------------
    def on_frame(self, sample: zenoh.Sample) -> None:
        t = time.monotonic()
        with self._ready:
            if self._frame is not None:
                self._frames_superseded += 1
            self._frames_received += 1
            self._frame = Arrival(sample, self._frames_received, t)
            self._last_arrival_t = t
            self._ready.notify()

    def on_info(self, sample: zenoh.Sample) -> None:
        with self._ready:
            self._info = sample
            self._ready.notify()

    def on_query(self, query: zenoh.Query) -> None:
        with self._ready:
            self._queries.append(query)
            self._ready.notify()

    # --- the loop thread ----------------------------------------------------------------------------------------
    def wait(self, timeout_s: float) -> None:
        """Return as soon as anything is pending, or after `timeout_s` seconds."""
        with self._ready:
            if self._frame is None and self._info is None and not self._queries:
                self._ready.wait(timeout_s)

    def take_query(self) -> zenoh.Query | None:
        """The oldest pending command, or None."""
        with self._ready:
            return self._queries.popleft() if self._queries else None

    def take_info(self) -> zenoh.Sample | None:
        """The newest camera info not yet taken, or None."""
        with self._ready:
            info, self._info = self._info, None
            return info

    def take_frame(self) -> Arrival[zenoh.Sample] | None:
        """The newest frame not yet taken, or None (frames superseded before being taken are dropped)."""
        with self._ready:
            frame, self._frame = self._frame, None
            return frame

    @property
    def frames_received(self) -> int:
        """Frames that arrived, taken or superseded."""
        with self._ready:
            return self._frames_received

    @property
    def frames_superseded(self) -> int:
        """Frames replaced by a newer one before the loop took them (never decreases)."""
        with self._ready:
            return self._frames_superseded

    @property
    def last_arrival_t(self) -> float:
        """`time.monotonic()` of the newest frame's arrival (of the inbox's creation before any frame)."""
        with self._ready:
            return self._last_arrival_t
