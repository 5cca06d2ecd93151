"""Trials as Ray tasks (docs/sweeps.md): each trial runs in a Ray worker process — never in a thread of this one —
with its own Taichi runtime (Taichi is not thread-safe), one CPU each, on a local Ray started for the run or on a
running cluster. The trial function and its key travel to the worker pickled (cloudpickle), the record comes back
through Ray's object store to this process, which keeps it (journal, files). A task is not retried: a trial whose
worker dies is a failure for the caller to report, and a second run of the command runs it again.

Workers import the same `ddvs` as this process: on a local Ray they inherit its environment (PYTHONPATH included);
on a cluster every node needs the same installation (docs/sweeps.md). Each worker runs Taichi's CPU backend on
`TAICHI_THREADS` threads (the task's one CPU) rather than on every core of its node, so that the node's workers
share its cores instead of oversubscribing them."""

from __future__ import annotations

import os
from collections.abc import Callable, Generator, Hashable, Sequence
from typing import Any, TypeVar

import ray
from ray.exceptions import RayError

from orchestration.workers import ClusterUnreachable, Failure, Workers

K = TypeVar("K", bound=Hashable)
R = TypeVar("R")

OBJECT_STORE_BYTES = 128 * 1024**2  # a local Ray's shared-memory object store: records are small (files spill to disk)
TAICHI_THREADS = 1  # Taichi CPU threads per worker (its `cpu_max_num_threads`, read from the environment at ti.init)


def trial(run: Callable[[Any], Any], key: Any) -> Any:
    """The task: one trial, in a Ray worker process."""
    return run(key)


def on_ray(keys: Sequence[K], run: Callable[[K], R], workers: Workers) -> Generator[tuple[K, R | Failure], None, None]:
    """`(key, record or Failure)` of every trial, in the order the trials end; at most `workers.count` tasks at once
    (None: all are submitted and Ray runs as many as there are CPUs). Connects to the cluster, or starts a local Ray,
    for the run; on leaving (the end, an exception, Ctrl-C, `close()`) cancels the tasks still running and
    disconnects (stops the local Ray)."""
    started_here = not ray.is_initialized()
    if started_here:
        _connect(workers)
    pending: dict[ray.ObjectRef, K] = {}
    try:
        task = ray.remote(num_cpus=1, max_retries=0)(trial).options(
            runtime_env={"env_vars": {"TI_CPU_MAX_NUM_THREADS": str(TAICHI_THREADS)}})
        run_ref = ray.put(run)
        queue = list(reversed(keys))  # popped from the end: in key order
        limit = workers.count or len(keys)
        while queue and len(pending) < limit:
            key = queue.pop()
            pending[task.remote(run_ref, key)] = key
        while pending:
            [ready], _ = ray.wait(list(pending), num_returns=1)
            key = pending.pop(ready)
            try:
                outcome: R | Failure = ray.get(ready)
            except RayError as error:
                outcome = Failure(str(error))
            if queue:
                following = queue.pop()
                pending[task.remote(run_ref, following)] = following
            yield key, outcome
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)
        if started_here:
            ray.shutdown()


def _connect(workers: Workers) -> None:
    """Join the cluster at `workers.cluster`, or start a local Ray with `workers.count` CPUs (default every core) and
    a small object store. Worker output stays in Ray's logs: this process's stdout carries the records."""
    if workers.cluster is not None:
        try:
            ray.init(address=workers.cluster, log_to_driver=False, configure_logging=False)
        except ConnectionError as error:
            raise ClusterUnreachable(
                f"cannot join the Ray cluster at {workers.cluster!r} ({error}); expected a running cluster whose head "
                "listens there, this host one of its nodes, and RAY_AUTH_MODE / RAY_AUTH_TOKEN as on the cluster "
                "(docs/sweeps.md)") from error
        return
    ray.init(num_cpus=workers.count or os.cpu_count() or 1, object_store_memory=OBJECT_STORE_BYTES,
             include_dashboard=False, log_to_driver=False, configure_logging=False)
