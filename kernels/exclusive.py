"""Taichi from several Python threads: one thread at a time, the servo loop first.

Taichi 1.7 is not thread-safe (taichi-dev/taichi#2022): compiling a kernel sets process-wide runtime state
(`compiling_callable`, the C++ program's kernel tables) while Python may switch threads in the middle, so two threads
must never be inside Taichi at once. Kernel *execution* already holds the GIL (a launch blocks every other Python
thread until it returns), so serialising the launches costs no parallelism.

`GATE` is the process-wide lock. A thread that answers frames holds it with `GATE.hold()` around its Taichi work
(one frame's registration: milliseconds). A background thread (re-acquisition) holds it with `GATE.background()`
around a long job and calls `GATE.checkpoint()` between kernel launches and between its longer numpy steps (the
lock is held over them too): when a `hold()` is waiting, the background thread hands the lock over there and takes
it back afterwards, so a frame waits at most for the work between two checkpoints (one launch or one step, a few
milliseconds), never for the whole job. Both are re-entrant on the thread that holds the lock (a job run on the loop
thread itself passes its checkpoints straight through). `longest_wait_s` records the longest a `hold()` waited
for the lock — the figure to keep well under a frame period. A holder may `lend` its hold to threads that run one at
a time while it waits for them (a lock-step group: `ddvs_service.registration.lockstep`): they enter as if they were
the holder.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager


class Gate:
    """A re-entrant lock whose foreground holders (`hold`) go before background ones (`background`, `checkpoint`)."""

    def __init__(self) -> None:
        self._cond = threading.Condition(threading.Lock())
        self._owner: int | None = None
        self._depth = 0
        self._background = False
        self._waiting = 0  # foreground threads waiting for the lock
        self._guests: frozenset[int] = frozenset()  # threads the owner lent its hold to (`lend`)
        self.longest_wait_s = 0.0

    @contextmanager
    def hold(self) -> Iterator[None]:
        """Hold the lock as a foreground thread (waits at most for a background holder's next checkpoint)."""
        self._acquire(background=False)
        try:
            yield
        finally:
            self._release()

    @contextmanager
    def background(self) -> Iterator[None]:
        """Hold the lock as a background thread: it yields to foreground waiters at each `checkpoint`."""
        self._acquire(background=True)
        try:
            yield
        finally:
            self._release()

    @contextmanager
    def lend(self, threads: Iterable[int]) -> Iterator[None]:
        """Let `threads` (idents) enter the lock the calling thread holds as if they were it, re-entrantly, while
        the context lasts. Only for threads that run one at a time while the holder waits for them: they share its
        hold, not a lock among themselves."""
        me = threading.get_ident()
        with self._cond:
            if self._owner != me:
                raise RuntimeError("only the thread that holds the Taichi gate can lend it")
            self._guests = frozenset(threads)
        try:
            yield
        finally:
            with self._cond:
                self._guests = frozenset()

    def close(self) -> None:
        """Take the lock in the foreground for good, on this thread: for the end of a process, after which no other
        thread may enter Taichi (`kernels.backend.finish`); a background holder's next checkpoint waits for ever."""
        self._acquire(background=False)

    def checkpoint(self) -> None:
        """Hand the lock to waiting foreground threads, if the calling thread holds it in the background."""
        if self._waiting == 0:  # the common case, without the condition's lock (a stale read waits one launch)
            return
        me = threading.get_ident()
        with self._cond:
            if self._owner != me or not self._background or self._waiting == 0:
                return
            depth = self._depth
            self._owner, self._depth, self._background = None, 0, False
            self._cond.notify_all()
            while self._owner is not None or self._waiting > 0:
                self._cond.wait()
            self._owner, self._depth, self._background = me, depth, True

    def _acquire(self, background: bool) -> None:
        me = threading.get_ident()
        with self._cond:
            if self._owner == me or (self._owner is not None and me in self._guests):
                self._depth += 1
                return
            if background:
                while self._owner is not None or self._waiting > 0:
                    self._cond.wait()
            else:
                self._waiting += 1
                start = time.perf_counter()
                try:
                    while self._owner is not None:
                        self._cond.wait()
                finally:
                    self._waiting -= 1
                self.longest_wait_s = max(self.longest_wait_s, time.perf_counter() - start)
            self._owner, self._depth, self._background = me, 1, background

    def _release(self) -> None:
        with self._cond:
            me = threading.get_ident()
            if self._owner != me and me not in self._guests:
                raise RuntimeError("the Taichi gate is released by a thread that does not hold it")
            self._depth -= 1
            if self._depth == 0:
                self._owner, self._background = None, False
                self._cond.notify_all()


GATE = Gate()
