"""Which robot's frame the loop thread takes next when one process serves several robots: the one waiting longest.

The loop takes one frame per turn (each robot keeps only its newest frame, `Inbox`). `Scheduler.pick` returns the
robot whose waiting started first — `Inbox.waiting_since`, the arrival of its oldest frame not taken, superseded
ones included, so a robot's claim does not restart with each newer frame — ties going round robin from the robot
after the one served last. A frame is therefore never taken after a frame of another robot that started waiting
later, and between a frame's arrival and its turn every other robot is served at most once (its next frame starts
waiting after ours), besides the turn already running: a robot's frame waits behind at most one frame of each other
robot, N − 1 in all with N robots. Against plain round robin (same bound) this keeps a frame from waiting behind
frames that arrived after it, which is what sets the tail when frames of several robots meet. Nothing is queued: a
robot whose frame was superseded while it waited serves its newest one (`dropped` counts the other).

`Scheduler.take(name, arrival_turn, turn)` records what the frame waited behind, measured in turns (`Wakeup.turns`
at its arrival against its own turn's number), as `Fairness`: the most turns one frame waited behind, the most of
those that belonged to a single other robot, and the frames taken. Those figures, not wall-clock times, are what the
tests check (`list_robots` reports them).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass


@dataclass
class Fairness:
    """One robot's scheduling figures: `frames` taken, `max_waited` (the most other frames taken between one of
    its frames' arrival and its turn, the one running at its arrival excluded), `max_waited_one_robot` (the most of
    those that belonged to one robot: 1 under round robin)."""

    frames: int = 0
    max_waited: int = 0
    max_waited_one_robot: int = 0


class Scheduler:
    """Longest-waiting-first choice among named robots (ties round robin), and the `Fairness` it achieved."""

    def __init__(self) -> None:
        self._order: list[str] = []
        self._next = 0  # index in `_order` where the next search starts
        self._last_two: dict[str, tuple[int, int]] = {}  # robot -> the turns of its last two frames (1-based)
        self.fairness: dict[str, Fairness] = {}

    def add(self, name: str) -> None:
        if name in self.fairness:
            raise ValueError(f"robot {name!r} is already scheduled")
        self._order.append(name)
        self._last_two[name] = (0, 0)
        self.fairness[name] = Fairness()

    def remove(self, name: str) -> None:
        i = self._order.index(name)
        del self._order[i]
        if i < self._next:
            self._next -= 1
        self._next = self._next % len(self._order) if self._order else 0
        del self._last_two[name], self.fairness[name]

    def pick(self, waiting_since: Callable[[str], float | None]) -> str | None:
        """The robot that has waited longest for a turn (`Inbox.waiting_since`; None: no frame), ties in round-robin
        order from the robot after the one served last; None when no robot has a frame."""
        n = len(self._order)
        best: tuple[float, int] | None = None
        for k in range(n):
            since = waiting_since(self._order[(self._next + k) % n])
            if since is not None and (best is None or since < best[0]):
                best = (since, k)
        if best is None:
            return None
        i = (self._next + best[1]) % n
        self._next = (i + 1) % n
        return self._order[i]

    def take(self, name: str, arrival_turn: int, turn: int) -> None:
        """Count the frame of `name` taken as the loop's `turn`-th frame (1-based), which arrived when
        `arrival_turn` frames had been taken (the turn running then, number `arrival_turn`, is not waiting)."""
        waited = turn - 1 - arrival_turn
        one_robot = max((sum(t > arrival_turn for t in turns) for other, turns in self._last_two.items()
                         if other != name), default=0)
        self._last_two[name] = (self._last_two[name][1], turn)
        stats = self.fairness[name]
        stats.frames += 1
        stats.max_waited = max(stats.max_waited, waited)
        stats.max_waited_one_robot = max(stats.max_waited_one_robot, one_robot)
