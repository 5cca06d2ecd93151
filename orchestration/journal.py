"""Resumable runs of an experiment: each record is appended to a JSON Lines journal as it ends, and records already
in the journal are returned instead of being run again."""

from __future__ import annotations

import json
from collections.abc import Callable, Hashable, Iterable
from dataclasses import asdict
from pathlib import Path
from typing import Any, TypeVar

K = TypeVar("K", bound=Hashable)
R = TypeVar("R")


def run_journalled(
    keys: Iterable[K],
    run: Callable[[K], R],
    record: Callable[..., R],
    key_of: Callable[[R], K],
    journal: Path | None,
    shown: Callable[[R], dict[str, Any]] | None = None,
) -> list[R]:
    """`run(key)` for every key in order, a dataclass record each. With a `journal` file, records found there (read
    back with `record(**fields)`, matched by `key_of`) are reused and each new one is appended as it ends. With
    `shown`, each new record's `shown(record)` is printed as one JSON line."""
    done: dict[K, R] = {}
    if journal is not None and journal.exists():
        for line in journal.read_text().splitlines():
            found = record(**json.loads(line))
            done[key_of(found)] = found
    records: list[R] = []
    for key in keys:
        if key in done:
            records.append(done[key])
            continue
        result = run(key)
        records.append(result)
        if journal is not None:
            with open(journal, "a", encoding="utf-8") as f:
                f.write(json.dumps(asdict(result)) + "\n")  # type: ignore[call-overload]  # R is a dataclass
        if shown is not None:
            print(json.dumps(shown(result)), flush=True)
    return records
