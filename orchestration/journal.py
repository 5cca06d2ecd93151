"""Resumable runs of an experiment: each record is appended to a JSON Lines journal as its trial ends, records already
in the journal are returned instead of being run again, and once the run stops the journal is put in key order —
so that it is the same file whether the trials ran one after another or on many workers, ending in any order."""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Callable, Hashable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any, TypeVar

from orchestration.trials import run_trials
from orchestration.workers import SEQUENTIAL, Workers

K = TypeVar("K", bound=Hashable)
R = TypeVar("R")


def run_journalled(
    keys: Sequence[K],
    run: Callable[[K], R],
    record: Callable[..., R],
    key_of: Callable[[R], K],
    journal: Path | None,
    shown: Callable[[R], dict[str, Any]] | None = None,
    workers: Workers = SEQUENTIAL,
) -> list[R]:
    """`run(key)` for every key not yet journalled (on `workers`: `orchestration.trials.run_trials`), a dataclass
    record each; returns the records in the order of `keys`. With a `journal` file, records found there (read back
    with `record(**fields)`, matched by `key_of`) are reused and each new one is appended as its trial ends; when the
    run stops (done, failed trials, Ctrl-C) the journal is rewritten in order: lines of keys outside `keys` first, as
    they were, then those of `keys` in their order (a line already there is kept as it was). With `shown`, each new
    record's `shown(record)` is printed as one JSON line when its trial ends. Raises `orchestration.trials.TrialsFailed`
    when some trials failed (the others are journalled)."""
    done: dict[K, R] = {}
    lines: dict[K, str] = {}
    if journal is not None and journal.exists():
        for line in journal.read_text().splitlines():
            found = record(**json.loads(line))
            done[key_of(found)], lines[key_of(found)] = found, line

    def keep(key: K, result: R) -> None:
        done[key] = result
        lines[key] = json.dumps(asdict(result))  # type: ignore[call-overload]  # R is a dataclass
        if journal is not None:
            with open(journal, "a", encoding="utf-8") as f:
                f.write(lines[key] + "\n")
        if shown is not None:
            print(json.dumps(shown(result)), flush=True)

    todo = [key for key in keys if key not in done]
    if todo:
        print(f"{len(todo)} trial(s) to run, {len(keys) - len(todo)} already journalled", file=sys.stderr)
    try:
        run_trials(todo, run, workers, keep)
    finally:
        if journal is not None and todo:
            _write_in_order(journal, lines, keys)
    return [done[key] for key in keys]


def _write_in_order(journal: Path, lines: dict[K, str], keys: Sequence[K]) -> None:
    """Replace `journal` at once (a new file renamed over it) by `lines`: keys outside `keys` first, in their order,
    then `keys`' in order."""
    wanted = set(keys)
    ordered = [line for key, line in lines.items() if key not in wanted]
    ordered += [lines[key] for key in keys if key in lines]
    fresh = journal.with_name(journal.name + ".tmp")
    fresh.write_text("".join(line + "\n" for line in ordered), encoding="utf-8")
    os.replace(fresh, journal)
