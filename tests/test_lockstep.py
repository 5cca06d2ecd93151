"""registration.lockstep: several robots' frames registered together — one `planar_step` launch per level and
iteration for all of them — give each robot the result it gets alone, on rendered frames (`evaluation.fleet_frames`).

Tolerance: a robot's row of a lock-step launch runs the same compiled kernel on the same data with the same band
split as its own launch, so the sums are expected to agree to the bit; the tests allow 1e-4 px at the ROI corners
(float32 rounding, should a backend's compiled code order a robot's row differently). Runs on the CPU here and on
the Vulkan/CUDA devices through tests/test_kernels_devices.py (`KERNEL_TESTS`).
"""

from __future__ import annotations

import numpy as np
import pytest

from ddvs_service.registration.lockstep import Lockstep
from ddvs_service.registration.planar import PlanarRegistration
from ddvs_service.registration.result import RegistrationResult
from ddvs_service.registration.tracker import Tracker
from evaluation.fleet_frames import RobotFrames, robot_frames
from evaluation.pairs import corner_error
from kernels.backend import init
from kernels.exclusive import GATE

init()
N_FRAMES = 6
CORNERS_PX = 1e-4


@pytest.fixture(scope="module")
def robots() -> list[RobotFrames]:
    return [robot_frames(k, N_FRAMES) for k in range(3)]


def trackers(robots: list[RobotFrames]) -> list[Tracker]:
    out = []
    for robot in robots:
        tracker = Tracker.prepare(robot.reference, roi=robot.roi)
        tracker.reset(robot.start)
        out.append(tracker)
    return out


def held_track(tracker: Tracker, frame: np.ndarray) -> RegistrationResult:
    with GATE.hold():  # as the service's pipeline does: the run lends its hold to the jobs
        return tracker.track(frame)


def test_lockstep_tracking_gives_each_robot_its_own_result_in_one_launch_per_iteration(robots) -> None:
    alone, together = trackers(robots), trackers(robots)
    lockstep = Lockstep()
    expected_launches = 0
    iterations_differ = False
    try:
        for f in range(N_FRAMES):
            solo = [tracker.track(robot.frames[f]) for tracker, robot in zip(alone, robots, strict=True)]
            batched = lockstep.run([lambda t=t, frame=r.frames[f]: held_track(t, frame)
                                    for t, r in zip(together, robots, strict=True)])
            for robot, a, b in zip(robots, solo, batched, strict=True):
                assert a.converged and b.converged, (a.reason, b.reason)
                assert a.iterations == b.iterations and len(a.iterations) == 1  # the finest level only
                assert corner_error(a.G, b.G, robot.roi) <= CORNERS_PX
            counts = [sum(r.iterations) for r in solo]
            expected_launches += max(counts)  # robots that converged first have no bands in the last launches
            iterations_differ |= len(set(counts)) > 1
    finally:
        lockstep.close()
    assert iterations_differ, "the frames should make the robots converge after different iteration counts"
    assert lockstep.launches == expected_launches


def test_robots_at_different_levels_share_the_run_in_one_launch_per_level(robots) -> None:
    """A whole-pyramid registration beside two trackers: its coarse levels are launches of their own, each robot
    still gets its own result."""
    engines = [PlanarRegistration.prepare(robot.reference, roi=robot.roi) for robot in robots]
    tracked = trackers(robots[1:])
    jobs = [lambda: engines[0].run(robots[0].frames[0], G0=robots[0].start),
            lambda: tracked[0].track(robots[1].frames[0]), lambda: tracked[1].track(robots[2].frames[0])]
    lockstep = Lockstep()
    try:
        batched = lockstep.run(jobs)
    finally:
        lockstep.close()
    alone = [PlanarRegistration.prepare(robots[0].reference, roi=robots[0].roi).run(robots[0].frames[0],
                                                                                     G0=robots[0].start),
             *(t.track(r.frames[0]) for t, r in zip(trackers(robots[1:]), robots[1:], strict=True))]
    for robot, a, b in zip(robots, alone, batched, strict=True):
        assert a.converged and b.converged and a.iterations == b.iterations
        assert corner_error(a.G, b.G, robot.roi) <= CORNERS_PX
    assert len(batched[0].iterations) > 1  # it went through coarser levels than the trackers
    assert lockstep.launches < sum(sum(r.iterations) for r in batched)


def test_a_job_that_raises_lets_the_others_finish_and_is_raised(robots) -> None:
    tracked = trackers(robots[:2])

    def broken() -> None:
        raise ValueError("this robot's frame is bad")

    lockstep = Lockstep()
    try:
        with pytest.raises(ValueError, match="frame is bad"):
            lockstep.run([lambda: tracked[0].track(robots[0].frames[0]), broken])
        assert tracked[0].G is not None and not np.allclose(tracked[0].G, robots[0].start)  # it was tracked
        again = lockstep.run([lambda: tracked[1].track(robots[1].frames[0])])  # the run is usable afterwards
        assert again[0].converged
    finally:
        lockstep.close()
