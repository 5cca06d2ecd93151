"""Never a confident wrong answer (issue 20): the servo acts only on fits it has reasons to trust.

State machine and error guard (pure logic) here; the engine-level integrity (anchored robust scale, implausible
fits) and the service pipeline on real frames below them."""

from __future__ import annotations

import numpy as np
import pytest

from ddvs_service.service.guard import ErrorGuard
from ddvs_service.service.state import FrameOutcome, ServoState, StateMachine


def test_lost_servo_resumes_only_after_confirmed_frames() -> None:
    sm = StateMachine(stop_threshold=1e-3, resume_threshold=5e-3, confirm_frames=3)
    sm.reference_set()
    sm.start()
    assert sm.on_frame(FrameOutcome(True, 0.3)) == ServoState.SERVOING
    assert sm.on_frame(FrameOutcome(False, np.nan)) == ServoState.LOST
    # one re-acquired frame, then a failure: the confirmation restarts
    assert sm.on_frame(FrameOutcome(True, 0.3)) == ServoState.LOST and not sm.moves
    assert sm.on_frame(FrameOutcome(False, np.nan)) == ServoState.LOST
    assert sm.on_frame(FrameOutcome(True, 0.3)) == ServoState.LOST
    assert sm.on_frame(FrameOutcome(True, 0.3)) == ServoState.LOST
    assert sm.on_frame(FrameOutcome(True, 0.3)) == ServoState.SERVOING and sm.moves
    with pytest.raises(ValueError, match="confirm_frames"):
        StateMachine(stop_threshold=1e-3, resume_threshold=5e-3, confirm_frames=0)


def test_error_guard_flags_a_jump_and_adopts_only_a_consistent_run() -> None:
    guard = ErrorGuard(jump_abs=0.1, jump_rel=0.25, rebase_frames=4)
    e = np.array([0.1, 0.0, 0.05, 0.0, 0.02, 0.0])
    assert guard.check(e) == ""  # the first tracked error is trusted
    assert guard.check(e * 0.98) == ""  # a servo step
    wrong = np.array([3.0, -1.0, 2.0, 0.5, 0.1, 1.0])  # the occluder fit of issue 20: norm 0.12 → 4.3
    assert "jumped" in guard.check(wrong)
    assert guard.check(e * 0.97) == ""  # back on the trusted track
    # a wrong fit wandering with the noise never builds a consistent run
    rng = np.random.default_rng(0)
    for _ in range(20):
        assert "jumped" in guard.check(wrong + rng.normal(scale=0.5, size=6))
    # a genuine displacement (the camera moved by hand while LOST) is adopted after rebase_frames agreeing frames
    moved = np.array([0.6, 0.2, 0.1, 0.0, 0.3, 0.1])
    assert "jumped" in guard.check(moved)
    moved = moved + 0.01
    for k in range(1, 3):
        assert f"{k + 1}/4" in guard.check(moved)
    assert guard.check(moved) == ""
    assert guard.check(moved * 0.99) == ""
