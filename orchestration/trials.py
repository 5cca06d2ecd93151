"""Runs the independent trials of an experiment — one after another in this process, or as Ray tasks on a local Ray
started for the run or on a running cluster (`orchestration.ray_trials`, docs/sweeps.md) — and hands each record
back in the order the trials end. A trial that raises (or whose worker dies) is a failure: the others go on, and
the failures are reported at the end (`TrialsFailed`) so that a second run can retry just those."""

from __future__ import annotations

import importlib.util
import sys
import traceback
from collections.abc import Callable, Generator, Hashable, Sequence
from contextlib import closing
from typing import TypeVar

from orchestration.progress import Progress
from orchestration.workers import Failure, Workers

K = TypeVar("K", bound=Hashable)
R = TypeVar("R")
SHOWN_FAILURES = 10  # failed trials named in the message of `TrialsFailed`


class TrialsFailed(RuntimeError):
    """Some trials ended without a record; the others' records are kept. `failures`: key → what went wrong."""

    def __init__(self, failures: dict[Hashable, Failure]) -> None:
        self.failures = failures
        first_key, first = next(iter(failures.items()))
        more = ", …" if len(failures) > SHOWN_FAILURES else ""
        named = ", ".join(map(repr, list(failures)[:SHOWN_FAILURES])) + more
        super().__init__(f"{len(failures)} trial(s) failed and are not in the record: {named}; run the same command "
                         f"again to retry them. The first, {first_key!r}:\n{first.message}")


def run_trials(keys: Sequence[K], run: Callable[[K], R], workers: Workers, keep: Callable[[K, R], None]) -> None:
    """`run(key)` for every key, `keep(key, record)` for each record as its trial ends (in this process, in the order
    the trials end), a status line on stderr (`orchestration.progress`). Raises `TrialsFailed` after every trial
    ended when some did not give a record. On a KeyboardInterrupt (Ctrl-C) the trials still running are stopped and
    the interrupt goes on; what `keep` got stays kept. Ray is used unless `workers.count` is 1, or there is only one
    trial and no cluster; without Ray installed, the default `Workers()` runs the trials one after another."""
    if not keys:
        return
    progress = Progress(len(keys))
    failures: dict[Hashable, Failure] = {}
    try:
        with closing(_outcomes(keys, run, workers)) as outcomes:
            for key, outcome in outcomes:
                if isinstance(outcome, Failure):
                    failures[key] = outcome
                else:
                    keep(key, outcome)
                progress.update(failed=isinstance(outcome, Failure))
    finally:
        progress.close()
    if failures:
        raise TrialsFailed(failures)


def _outcomes(keys: Sequence[K], run: Callable[[K], R],
              workers: Workers) -> Generator[tuple[K, R | Failure], None, None]:
    if workers.count == 1 or (workers.cluster is None and len(keys) == 1):
        return _in_this_process(keys, run)
    if importlib.util.find_spec("ray") is None:
        if workers != Workers():
            raise RuntimeError("running trials on several workers or a cluster needs Ray: pip install 'ddvs[ray]' "
                               "(or --workers 1: one trial after another, without Ray)")
        print("Ray is not installed (pip install 'ddvs[ray]'): running the trials one after another",
              file=sys.stderr)
        return _in_this_process(keys, run)
    from orchestration.ray_trials import on_ray

    return on_ray(keys, run, workers)


def _in_this_process(keys: Sequence[K], run: Callable[[K], R]) -> Generator[tuple[K, R | Failure], None, None]:
    for key in keys:
        try:
            result: R | Failure = run(key)
        except Exception:
            result = Failure(traceback.format_exc())
        yield key, result
