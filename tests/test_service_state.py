"""State machine transitions and atomic persistence of the servo service."""

from __future__ import annotations

import os

import numpy as np
import pytest

from ddvs_service.camera import Intrinsics
from ddvs_service.service.config import ServiceConfig
from ddvs_service.service.persistence import StateStore, atomic_write_bytes
from ddvs_service.service.pipeline import ServoPipeline
from ddvs_service.service.state import FrameOutcome, ServoState, StateMachine, TransitionError


def machine() -> StateMachine:
    return StateMachine(stop_threshold=1e-3, resume_threshold=5e-3)


def test_full_cycle_with_hysteresis() -> None:
    sm = machine()
    assert sm.state == ServoState.IDLE
    with pytest.raises(TransitionError, match="no reference"):
        sm.start()
    assert sm.state == ServoState.IDLE
    sm.reference_set()
    assert sm.state == ServoState.READY
    assert sm.on_frame(FrameOutcome(True, 1.0)) == ServoState.READY  # not started: frames do not drive it
    sm.start()
    assert sm.on_frame(FrameOutcome(True, 0.5)) == ServoState.SERVOING and sm.moves
    assert sm.on_frame(FrameOutcome(True, 5e-4)) == ServoState.CONVERGED and not sm.moves
    assert sm.on_frame(FrameOutcome(True, 3e-3)) == ServoState.CONVERGED  # inside the hysteresis band
    assert sm.on_frame(FrameOutcome(True, 6e-3)) == ServoState.SERVOING
    assert sm.on_frame(FrameOutcome(False, np.nan)) == ServoState.LOST and not sm.moves
    for _ in range(sm.confirm_frames - 1):  # re-acquired: held still until the fit is confirmed
        assert sm.on_frame(FrameOutcome(True, 0.2)) == ServoState.LOST and not sm.moves
    assert sm.on_frame(FrameOutcome(True, 0.2)) == ServoState.SERVOING
    sm.stop()
    assert sm.on_frame(FrameOutcome(True, 0.2)) == ServoState.STOPPED
    sm.reset()
    assert sm.state == ServoState.IDLE
    with pytest.raises(TransitionError):
        sm.stop()


def test_a_resumed_servo_holds_still_until_its_first_frames_confirm_the_estimate() -> None:
    """A restart resumes an active servo LOST: its first tracked frames are confirmation frames, even when the first
    one is already tracked (from the persisted estimate) and even if it had converged before."""
    sm = machine()
    with pytest.raises(TransitionError, match="no reference"):
        sm.resume()
    sm.reference_set()
    sm.start()
    sm.on_frame(FrameOutcome(True, 5e-4))
    assert sm.state == ServoState.CONVERGED
    assert sm.resume() == ServoState.LOST and not sm.moves
    for _ in range(sm.confirm_frames - 1):
        assert sm.on_frame(FrameOutcome(True, 0.2)) == ServoState.LOST and not sm.moves
    assert sm.on_frame(FrameOutcome(True, 0.2)) == ServoState.SERVOING and sm.moves


def test_thresholds_validated() -> None:
    for stop in (1e-2, -1e-3, float("nan")):
        with pytest.raises(ValueError, match="stop_threshold < resume_threshold"):
            StateMachine(stop_threshold=stop, resume_threshold=1e-3)


def test_a_zero_stop_threshold_never_converges() -> None:
    """`control.stop_threshold` 0 ("never", as the setting documents): the servo keeps following the reference, even
    on a zero error whose long window holds."""
    sm = ServoPipeline(ServiceConfig.model_validate({"control": {"stop_threshold": 0.0}}),
                       Intrinsics(420.0, 420.0, 159.5, 119.5, 320, 240), background_reacquisition=False).machine
    assert (sm.stop_threshold, sm.resume_threshold, sm.scatter_threshold) == (0.0, 0.0, 0.0)
    sm.reference_set()
    sm.start()
    for _ in range(5):
        assert sm.on_frame(FrameOutcome(True, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)) == ServoState.SERVOING and sm.moves


def test_store_round_trip(tmp_path) -> None:
    store = StateStore(tmp_path / "state")
    assert store.load_reference() is None and store.load_json("state.json") is None
    ref = (np.arange(240 * 320) % 251).astype(np.uint8).reshape(240, 320)
    store.save_reference(ref)
    np.testing.assert_array_equal(store.load_reference(), ref)
    store.save_json("state.json", {"state": "READY", "G": np.eye(3).tolist()})
    assert store.load_json("state.json")["state"] == "READY"
    assert not [p for p in os.listdir(store.dir) if p.endswith(".tmp")]


def test_atomic_write_keeps_old_file_on_failure(tmp_path) -> None:
    target = tmp_path / "config.json"
    atomic_write_bytes(target, b"old")

    with pytest.raises(TypeError):
        atomic_write_bytes(target, object())  # type: ignore[arg-type]
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["config.json"]


def test_convergence_needs_consecutive_frames_below_threshold() -> None:
    sm = StateMachine(stop_threshold=1e-3, resume_threshold=5e-3, converge_frames=3)
    sm.reference_set()
    sm.start()
    for norm in (5e-4, 5e-4, 2e-3, 5e-4, 5e-4):  # a dip interrupted by one frame above: the count restarts
        assert sm.on_frame(FrameOutcome(True, norm)) == ServoState.SERVOING
    assert sm.on_frame(FrameOutcome(True, 5e-4)) == ServoState.CONVERGED
    with pytest.raises(ValueError, match="converge_frames"):
        StateMachine(stop_threshold=1e-3, resume_threshold=5e-3, converge_frames=0)


def test_convergence_needs_the_scatter_below_its_threshold() -> None:
    """Issue 20: a mean error below the stop threshold whose frames scatter by more than `scatter_threshold` (or
    whose window is not yet full: scatter inf) is not CONVERGED; the same mean with a small scatter is."""
    sm = StateMachine(stop_threshold=1e-3, resume_threshold=5e-3, converge_frames=2, scatter_threshold=2e-3)
    sm.reference_set()
    sm.start()
    for scatter in (np.inf, 1e-2, 3e-3, 1.5e-3, 2.5e-3, 1e-3):
        assert sm.on_frame(FrameOutcome(True, 8e-3, 4e-4, scatter)) == ServoState.SERVOING and sm.moves
    assert sm.on_frame(FrameOutcome(True, 8e-3, 4e-4, 1e-3)) == ServoState.CONVERGED and not sm.moves
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="scatter_threshold"):
            StateMachine(stop_threshold=1e-3, resume_threshold=5e-3, scatter_threshold=bad)


def test_a_noisy_estimate_converges_on_the_long_window() -> None:
    """Issue 20: a short window that scatters by more than `scatter_threshold` still converges when the long
    window's mean and the standard error of that mean are below the stop threshold and its scatter is at most
    `max_noise_ratio` × the one the image noise predicts; any of the three failing (or the long window not full:
    nan, inf, inf) keeps it SERVOING. So stopped, it resumes on the long window's mean, not on a frame's norm."""
    sm = StateMachine(stop_threshold=1e-3, resume_threshold=5e-3, converge_frames=2, scatter_threshold=2e-3,
                      max_noise_ratio=3.0)
    sm.reference_set()
    sm.start()
    for long in ((np.nan, np.inf, np.inf), (2e-3, 5e-4, 1.2), (5e-4, 1.5e-3, 1.2), (5e-4, 5e-4, 3.5)):
        assert sm.on_frame(FrameOutcome(True, 8e-3, 4e-4, 7e-3, *long)) == ServoState.SERVOING and sm.moves
    assert sm.on_frame(FrameOutcome(True, 8e-3, 4e-4, 7e-3, 5e-4, 7e-4, 1.6)) == ServoState.SERVOING
    assert sm.on_frame(FrameOutcome(True, 8e-3, 4e-4, 7e-3, 5e-4, 7e-4, 1.6)) == ServoState.CONVERGED
    # stopped on the long window: a frame's own norm above the resume threshold is the noise, the mean's a move
    assert sm.on_frame(FrameOutcome(True, 1.5e-2, 4e-4, 7e-3, 5e-4, 7e-4, 1.6)) == ServoState.CONVERGED
    assert sm.on_frame(FrameOutcome(True, 1.5e-2, 4e-3, 9e-3, 6e-3, 9e-4, 1.6)) == ServoState.SERVOING
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="max_noise_ratio"):
            StateMachine(stop_threshold=1e-3, resume_threshold=5e-3, max_noise_ratio=bad)
