"""Hand-off from Zenoh callbacks to the servo loop thread, with a wake-up the moment something arrives.

Zenoh runs subscriber and queryable callbacks on its own threads; they must neither block nor call Zenoh
(PLATFORM-NOTES), so each callback here only stores what arrived under a lock and notifies one condition variable.
The loop thread sleeps on that condition (`wait`) instead of polling: a frame is handed over within one thread
wake-up, not after up to one polling period, and an idle service costs no CPU.

What is kept: the newest frame and the newest camera info only (a slow loop skips frames, never queues them, as
`RingChannel(1)` would), and the pending commands in arrival order, at most `max_queries` (beyond that the oldest is
dropped: its querier gets no reply and times out, and the Zenoh session never stalls behind a full queue).
"""

from __future__ import annotations

import threading
from collections import deque

import zenoh


class Inbox:
    """Latest frame, latest camera info and pending commands, filled by Zenoh callbacks, drained by one thread."""

    def __init__(self, max_queries: int = 64) -> None:
        self._ready = threading.Condition()
        self._frame: zenoh.Sample | None = None
        self._info: zenoh.Sample | None = None
        self._queries: deque[zenoh.Query] = deque(maxlen=max_queries)
        self._frames_received = 0

    # --- Zenoh callbacks (Zenoh's threads; never block) ---------------------------------------------------------
    def on_frame(self, sample: zenoh.Sample) -> None:
        with self._ready:
            self._frame = sample
            self._frames_received += 1
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

    def take_frame(self) -> zenoh.Sample | None:
        """The newest frame not yet taken, or None (frames superseded before being taken are dropped)."""
        with self._ready:
            frame, self._frame = self._frame, None
            return frame

    @property
    def frames_received(self) -> int:
        """Frames that arrived, taken or superseded."""
        with self._ready:
            return self._frames_received
