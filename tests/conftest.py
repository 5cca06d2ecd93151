"""Shared test fixtures."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest


def cached_kernels(cache: Path) -> dict[str, int]:
    """Taichi's compiled kernels in the offline cache directory `cache`: file name → modification time (ns)."""
    return {p.name: p.stat().st_mtime_ns for p in cache.rglob("*.tic")}


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (for loopback Zenoh endpoints)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def port() -> int:
    return free_port()


def pairs(cases: list[tuple[str, int]]) -> list[object]:
    """`(seq, k)` real-pair cases for `pytest.mark.parametrize`: those not shipped (`evaluation/data`) and not in
    the full datasets are skipped with the one line that says what they need."""
    from evaluation.datasets import MISSING
    from evaluation.pairs import is_available

    return [pytest.param(seq, k, marks=() if is_available(seq, k) else pytest.mark.skip(reason=MISSING))
            for seq, k in cases]
