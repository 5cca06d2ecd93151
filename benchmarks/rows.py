"""How the benchmarks print their results: one JSON object per row, or a markdown table (`--markdown`)."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any


def print_rows(rows: list[dict[str, Any]], markdown: bool, header: list[str],
               cells: Callable[[dict[str, Any]], list[str]]) -> None:
    """Print `rows` as JSON lines, or as a markdown table with `header` and each row's `cells(row)`."""
    if not markdown:
        for row in rows:
            print(json.dumps(row))
        return
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for row in rows:
        print("| " + " | ".join(cells(row)) + " |")
