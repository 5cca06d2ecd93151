"""Hand-off from Zenoh callbacks to the servo loop thread, with a wake-up the moment something arrives.

Zenoh runs subscriber and queryable callbacks on its own threads; they must neither block nor call Zenoh
(PLATFORM-NOTES), so each callback here only stores what arrived under a lock and notifies one condition variable.
The loop thread sleeps on that condition (`wait`) instead of polling: a frame is handed over within one thread
wake-up, not after up to one polling period, and an idle service costs no CPU.

What is kept: the newest accepted frame and the newest camera info only (a slow loop skips frames, never queues them, as
`RingChannel(1)` would), and the pending commands in arrival order, at most `max_queries` (beyond that the oldest is
dropped: its querier gets no reply and times out, and the Zenoh session never stalls behind a full queue).

Frame bookkeeping happens here, where frames arrive, so it does not depend on when the loop looks. The subscriber
checks each frame before handing it over (`service.robot`: it decodes, with the camera's size): a rejected frame is
only counted (`reject`, with its reason) and never takes the place of the accepted frame waiting, so a flood of bad
frames neither wakes the loop nor pushes good frames out. Each accepted frame gets its arrival index (1, 2, …) and
arrival time (`time.monotonic()`, seconds), the time of the last accepted arrival is what the watchdog measures, and
a frame superseded before the loop took it is counted once, when it is superseded (`dropped` only grows).

One loop thread serves several robots (`service.process`): each robot has its own inbox, all of them notify one
`Wakeup` (a shared condition), and `wait(timeout, others)` sleeps until any of them holds something. Each frame also
records `Wakeup.turns` at its arrival (how many frames the loop had taken by then, over every robot), from which the
scheduler measures what the frame waited behind (`service.scheduler`).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import zenoh

SampleT = TypeVar("SampleT")
FrameT = TypeVar("FrameT")


@dataclass(frozen=True)
class Arrival(Generic[SampleT]):
    """A frame as it arrived: the sample, its arrival index (the n-th frame received), time (monotonic s) and the
    loop's `Wakeup.turns` at that moment."""

    sample: SampleT
    index: int
    t: float
    turn: int = 0


class Wakeup:
    """What the inboxes of one loop thread share: the condition they notify, and `turns`, the number of frames the
    loop has taken so far over all its inboxes (counted by `Inbox.take_frame`, under the condition)."""

    def __init__(self) -> None:
        self.condition = threading.Condition()
        self.turns = 0


class Inbox(Generic[FrameT]):
    """Latest accepted frame (of type `FrameT`: what the subscriber made of the sample), latest camera info and
    pending commands, filled by Zenoh callbacks, drained by one thread; rejected inputs counted."""

    def __init__(self, max_queries: int = 64, wakeup: Wakeup | None = None) -> None:
        self.wakeup = wakeup or Wakeup()
        self._ready = self.wakeup.condition
        self._frame: Arrival[FrameT] | None = None
        self._info: zenoh.Sample | None = None
        self._queries: deque[zenoh.Query] = deque(maxlen=max_queries)
        self._frames_received = 0
        self._frames_superseded = 0
        self._rejected = 0
        self._last_rejection = ""
        self._waiting_since: float | None = None  # arrival of the oldest frame not taken (superseded ones too)
        self._last_arrival_t = time.monotonic()

    # --- Zenoh callbacks (Zenoh's threads; never block) ---------------------------------------------------------
    def on_frame(self, sample: FrameT, t: float | None = None) -> None:
        """An accepted frame that arrived at `t` (`time.monotonic()`; now when None)."""
        t = time.monotonic() if t is None else t
        with self._ready:
            if self._frame is not None:
                self._frames_superseded += 1
            self._frames_received += 1
            self._frame = Arrival(sample, self._frames_received, t, self.wakeup.turns)
            if self._waiting_since is None:
                self._waiting_since = t
            self._last_arrival_t = t
            self._ready.notify()

    def reject(self, reason: str) -> None:
        """Count an input rejected (any thread): nothing is stored, the loop is not woken."""
        with self._ready:
            self._rejected += 1
            self._last_rejection = reason

    def on_info(self, sample: zenoh.Sample) -> None:
        with self._ready:
            self._info = sample
            self._ready.notify()

    def on_query(self, query: zenoh.Query) -> None:
        with self._ready:
            self._queries.append(query)
            self._ready.notify()

    # --- the loop thread ----------------------------------------------------------------------------------------
    def wait(self, timeout_s: float, others: Iterable[Inbox[Any]] = ()) -> None:
        """Return as soon as anything is pending here or in `others` (inboxes of the same `Wakeup`), or after
        `timeout_s` seconds."""
        with self._ready:
            if not self.pending and not any(other.pending for other in others):
                self._ready.wait(timeout_s)

    @property
    def pending(self) -> bool:
        """Anything waiting: a frame, a camera info or a command."""
        with self._ready:
            return self._frame is not None or self._info is not None or bool(self._queries)

    @property
    def waiting_since(self) -> float | None:
        """`time.monotonic()` of the arrival of the oldest frame the loop has not taken (one superseded since
        included: a robot's claim to a turn does not restart with each newer frame), None when no frame waits."""
        with self._ready:
            return self._waiting_since

    def take_query(self) -> zenoh.Query | None:
        """The oldest pending command, or None."""
        with self._ready:
            return self._queries.popleft() if self._queries else None

    def take_info(self) -> zenoh.Sample | None:
        """The newest camera info not yet taken, or None."""
        with self._ready:
            info, self._info = self._info, None
            return info

    def take_frame(self) -> Arrival[FrameT] | None:
        """The newest frame not yet taken, or None (frames superseded before being taken are dropped); a frame
        taken counts one turn of the loop (`Wakeup.turns`)."""
        with self._ready:
            frame, self._frame = self._frame, None
            if frame is not None:
                self.wakeup.turns += 1
                self._waiting_since = None
            return frame

    @property
    def rejections(self) -> tuple[int, str]:
        """Inputs rejected so far (never decreases) and the reason of the newest rejection."""
        with self._ready:
            return self._rejected, self._last_rejection

    @property
    def frames_received(self) -> int:
        """Accepted frames that arrived, taken or superseded."""
        with self._ready:
            return self._frames_received

    @property
    def frames_superseded(self) -> int:
        """Frames replaced by a newer one before the loop took them (never decreases)."""
        with self._ready:
            return self._frames_superseded

    @property
    def last_arrival_t(self) -> float:
        """`time.monotonic()` of the newest accepted frame's arrival (of the inbox's creation before any frame)."""
        with self._ready:
            return self._last_arrival_t
