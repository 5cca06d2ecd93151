"""`kernels.exclusive.Gate`: one thread in Taichi at a time, a frame before a background search."""

from __future__ import annotations

import threading

from kernels.exclusive import Gate


def test_a_waiting_frame_gets_the_gate_at_the_background_holders_next_checkpoint() -> None:
    gate = Gate()
    started, done = threading.Event(), threading.Event()
    log: list[str] = []

    def search() -> None:
        with gate.background():
            started.set()
            while not done.is_set():
                gate.checkpoint()  # between two kernel launches of a long search
                done.wait(0.001)
            log.append("search still holding")
        log.append("search ended")

    worker = threading.Thread(target=search)
    worker.start()
    started.wait()
    with gate.hold():  # blocks until the search's next checkpoint, not until its end
        log.append("frame")
        done.set()
    worker.join(60.0)
    assert log == ["frame", "search still holding", "search ended"]
    assert gate.longest_wait_s >= 0.0


def test_reentrant_on_its_thread_and_checkpoints_pass_through() -> None:
    gate = Gate()
    with gate.hold(), gate.hold(), gate.background():  # a search run on the loop thread itself
        gate.checkpoint()
    held = threading.Event()

    def frame() -> None:
        with gate.hold():
            held.set()

    other = threading.Thread(target=frame)
    other.start()
    other.join(60.0)
    assert held.is_set()  # the gate was free again


def test_a_background_holder_waits_for_a_foreground_one() -> None:
    gate = Gate()
    entered = threading.Event()

    def search() -> None:
        with gate.background():
            entered.set()

    with gate.hold():
        worker = threading.Thread(target=search)
        worker.start()
        assert not entered.wait(0.05)
    worker.join(60.0)
    assert entered.is_set()
