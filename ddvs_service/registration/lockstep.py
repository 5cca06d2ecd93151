"""Lock-step registration of several robots' frames: one `kernels.planar_step` launch per pyramid level and
Gauss-Newton iteration for every robot that has a frame, instead of one per robot.

The registration code (tracking session → tracker → engine → `solver.gauss_newton`) is sequential: one iteration
after another, each asking its engine for the normal equations at its estimate, and a robot's iteration count
depends on its frame. `Lockstep.run(jobs)` keeps that code as it is. Each job (one robot's frame, e.g. its
`tracker.track` or its service's `handle_frame`) runs on a worker thread of its own, the jobs one at a time in their
order while the calling thread waits (a baton: never two in Python or in Taichi at once), until the job ends or a
planar engine asks for its normal equations (`PlanarRegistration` sees `current()` and calls `Batch.evaluate`,
which parks the job). When every unfinished job is parked, the parked requests are evaluated together — one launch
per group of requests with the same level shape, gain grid and parameter layout, each robot in its own row of the
group's stacks (`_Stack`: its reference and current level copied once per reference and per frame, its parameters
per iteration, its sums copied back) — and the jobs resume in order. A job that ended, or that is at another level
or not at a planar step at all, has no bands in a launch (`kernels.planar_step`'s robot axis: its row is skipped).

Each robot's launch row runs the arithmetic of its own per-robot launch — the same kernel source and compiled
specialisation (a per-robot launch is a stack of one), the robot's own bands, its own serial tail — so a job's
result is the one it gets alone, up to float32 rounding where the compiled code's instruction order differs
(tests/test_lockstep.py states the tolerance). Everything else a job does (decoding, pyramids, the general model's
kernels, control, publishing) runs as it would alone, on its worker thread; the calling thread holds
`kernels.exclusive.GATE` for the whole run and lends it to the workers (`Gate.lend`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Generic, Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray

from kernels.exclusive import GATE
from kernels.launch import Prepared

T = TypeVar("T")
F32 = NDArray[np.float32]
_local = threading.local()


@dataclass(frozen=True)
class StepInputs:
    """What one robot's `planar_step` reads and writes at one level (`PlanarRegistration.step_inputs`): its
    reference level (read-only, replaced with a new reference), its current-image workspace (`current.buffers`,
    `current.loads`), the level's index, its parameter and work arrays (1-D; the sums are `work[:n_sums]`) and its
    gain grid."""

    reference: F32
    current: CurrentLevels
    index: int
    params: F32
    work: F32
    n_sums: int
    grid: tuple[int, int]


class CurrentLevels(Protocol):
    """The part of `reference.CurrentPyramid` a batch reads: the level buffers and how many images were loaded."""

    buffers: list[F32]
    loads: int


def current() -> Batch | None:
    """The batch of the job running on this thread, or None outside `Lockstep.run` (a per-robot launch)."""
    return getattr(_local, "batch", None)


class Batch:
    """One job's side of a run: `evaluate` hands its step to the next group launch and waits for it."""

    def __init__(self, lockstep: Lockstep, index: int) -> None:
        self.index = index
        self._lockstep = lockstep
        self._go = threading.Semaphore(0)
        self.request: StepInputs | None = None
        self.failure: BaseException | None = None

    def evaluate(self, inputs: StepInputs) -> None:
        """Park this job until its step was evaluated with the other parked jobs' (its sums then in
        `inputs.work[:inputs.n_sums]`); raises what the group launch raised."""
        self.request, self.failure = inputs, None
        self._lockstep._back.release()
        self._go.acquire()
        self.request = None
        if self.failure is not None:
            raise RuntimeError("the lock-step launch failed") from self.failure


class _Worker(Generic[T]):
    """A daemon thread that runs the jobs handed to it, one per run."""

    def __init__(self, lockstep: Lockstep, index: int) -> None:
        self.batch = Batch(lockstep, index)
        self.job: Callable[[], T] | None = None
        self.result: T | None = None
        self.error: BaseException | None = None
        self.done = False
        self._lockstep = lockstep
        self.thread = threading.Thread(target=self._serve, name=f"ddvs-lockstep-{index}", daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        _local.batch = self.batch
        while True:
            self.batch._go.acquire()
            job = self.job
            if job is None:
                return
            try:
                self.result = job()
            except BaseException as exc:  # handed to the caller of `run`
                self.error = exc
            self.done = True
            self._lockstep._back.release()


class _Stack:
    """Stacked arrays of one launch group (one level shape, gain grid and layout) for `capacity` robots, and the
    prepared launch on them; `sources[k]`: what row `k`'s images were copied from (reference level array, current
    workspace and its load count), so that each is copied once."""

    def __init__(self, first: StepInputs, capacity: int) -> None:
        from kernels.backend import compile_settings
        from kernels.planar_step import PARAMS_BANDS, planar_step

        shape = first.reference.shape
        self.ref = np.zeros((capacity, *shape), dtype=np.float32)
        self.cur = np.zeros((capacity, *shape), dtype=np.float32)
        self.params = np.zeros((capacity, first.params.size), dtype=np.float32)
        self.work = np.zeros((capacity, first.work.size), dtype=np.float32)
        self.sources: list[tuple[object, object, int]] = [(None, None, -1)] * capacity
        self._bands = PARAMS_BANDS
        with compile_settings():  # the per-robot launch's specialisation (a stack of one): compiled once for both
            self._launch = Prepared(planar_step, self.ref, self.cur, self.params, self.work, *first.grid)

    def launch(self, rows: list[tuple[int, StepInputs]]) -> None:
        """Evaluate each `(row, inputs)` in its row, the other rows without bands; copy the sums back."""
        self.params[:, self._bands] = 0.0
        for k, inputs in rows:
            ref_source, cur_source, loads = self.sources[k]
            current = inputs.current
            if ref_source is not inputs.reference:
                self.ref[k] = inputs.reference
            if cur_source is not current or loads != current.loads or ref_source is not inputs.reference:
                self.cur[k] = current.buffers[inputs.index]
            self.sources[k] = (inputs.reference, current, current.loads)
            self.params[k] = inputs.params
        self._launch()
        for k, inputs in rows:
            inputs.work[: inputs.n_sums] = self.work[k, : inputs.n_sums]


class Lockstep:
    """Runs jobs in lock-step (module docstring); `launches` counts its group launches. Not re-entrant; `close`
    ends its worker threads."""

    def __init__(self) -> None:
        self._back = threading.Semaphore(0)
        self._workers: list[_Worker[object]] = []
        self._stacks: dict[tuple[object, ...], _Stack] = {}
        self.launches = 0

    def run(self, jobs: Sequence[Callable[[], T]]) -> list[T]:
        """Run `jobs` in lock-step and return their results in order; when jobs raised, the first one's exception
        is raised after every job ended."""
        while len(self._workers) < len(jobs):
            self._workers.append(_Worker(self, len(self._workers)))
        workers = self._workers[: len(jobs)]
        for worker, job in zip(workers, jobs, strict=True):
            worker.job, worker.result, worker.error, worker.done = job, None, None, False
        with GATE.hold(), GATE.lend(worker.thread.ident for worker in workers if worker.thread.ident is not None):
            running = list(workers)
            while running:
                for worker in running:  # each runs until it ends or parks at a step
                    worker.batch._go.release()
                    self._back.acquire()
                running = [worker for worker in running if not worker.done]
                if running:
                    self._evaluate([worker.batch for worker in running])
        errors = [worker.error for worker in workers if worker.error is not None]
        for worker in workers:
            worker.job = None
        if errors:
            raise errors[0]
        return [worker.result for worker in workers]  # type: ignore[misc]  # T: set by each job that ended

    def _evaluate(self, parked: list[Batch]) -> None:
        """One launch per group of the parked steps (module docstring)."""
        groups: dict[tuple[object, ...], list[tuple[int, StepInputs]]] = {}
        for batch in parked:
            inputs = batch.request
            assert inputs is not None  # a job not done is parked at a step
            key: tuple[object, ...] = (inputs.index, inputs.reference.shape, inputs.grid, inputs.params.size,
                                       inputs.work.size)
            groups.setdefault(key, []).append((batch.index, inputs))
        for group, rows in groups.items():
            try:
                stack = self._stacks.get(group)
                if stack is None or stack.ref.shape[0] < len(self._workers):
                    stack = self._stacks[group] = _Stack(rows[0][1], len(self._workers))
                stack.launch(rows)
                self.launches += 1
            except Exception as exc:  # the jobs waiting for it raise it (`Batch.evaluate`)
                for index, _inputs in rows:
                    self._workers[index].batch.failure = exc

    def close(self) -> None:
        """End the worker threads (between runs)."""
        for worker in self._workers:
            worker.job = None
            worker.batch._go.release()
        for worker in self._workers:
            worker.thread.join()
        self._workers.clear()
