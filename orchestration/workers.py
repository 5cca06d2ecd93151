"""Where the trials of an experiment run (`Workers`: in this process, on a local Ray, on a cluster) and how a trial
that gave no record ended (`Failure`) or why the cluster could not be joined (`ClusterUnreachable`);
`orchestration.trials` runs them."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Workers:
    """Where trials run: `count` trials at once at most (None: as many as the Ray cluster has CPUs; 1: one after
    another in this process, without Ray), on the Ray cluster at `cluster` (an address `host:port` of a running
    cluster, or "auto" on a node of one; None: a local Ray started for the run with `count` CPUs, default every
    core of this machine)."""

    count: int | None = None
    cluster: str | None = None

    def __post_init__(self) -> None:
        if self.count is not None and self.count < 1:
            raise ValueError(f"workers must be at least 1 (1: one trial after another, without Ray), got {self.count}")
        if self.count == 1 and self.cluster is not None:
            raise ValueError("--workers 1 runs the trials in this process: it takes no --cluster")


SEQUENTIAL = Workers(count=1)


@dataclass(frozen=True)
class Failure:
    """A trial that ended without a record: what went wrong (the exception, with the trial's traceback)."""

    message: str


class ClusterUnreachable(RuntimeError):
    """The Ray cluster named by `Workers.cluster` could not be joined."""
