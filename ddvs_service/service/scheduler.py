"""Which robot's frame the loop thread takes next when one process serves several robots: round robin.

The loop takes one frame per turn (each robot keeps only its newest frame, `Inbox`). `RoundRobin.pick` returns the
first robot after the one served last, in the order robots were added, that has a frame waiting. So between a
frame's arrival and the turn that takes it, every other robot's frame is taken at most once, besides the turn
already running when it arrived: a robot's frame waits behind at most one frame of each other robot, and behind
N − 1 frames in all with N robots. Nothing is queued: a robot whose frame was superseded while it waited serves its
newest one (`dropped` counts the other).

`RoundRobin.take(name, arrival_turn, turn)` records what the frame waited behind, measured in turns (`Wakeup.turns`
at its arrival against its own turn's number), as `Fairness`: the most turns one frame waited behind, the most of those
that belonged to a single other robot, and the frames taken. Those figures, not wall-clock times, are what the
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


class RoundRobin:
    """Round-robin choice among named robots with a frame waiting, and the `Fairness` it achieved per robot."""

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

    def pick(self, has_frame: Callable[[str], bool]) -> str | None:
        """The next robot, in round-robin order from the one after the last served, with a frame waiting."""
        n = len(self._order)
        for k in range(n):
            name = self._order[(self._next + k) % n]
            if has_frame(name):
                self._next = (self._next + k + 1) % n
                return name
        return None

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
