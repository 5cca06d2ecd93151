"""`benchmarks/device_check.py --dry-run`: the CUDA machine's script runs end to end here (the device tests collected,
the benchmarks on the CPU) and prints its one table with a row per step."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_the_dry_run_prints_one_table_of_passed_steps() -> None:
    done = subprocess.run([sys.executable, "benchmarks/device_check.py", "--dry-run"], cwd=ROOT, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    table = done.stdout[done.stdout.index("Device check: Taichi backend cpu"):].splitlines()
    rows = [line for line in table if line.startswith("| ") and not line.startswith("| Step")]
    assert [row.split(" | ")[0] for row in rows] == ["| device tests (cuda, collected)", "| bench_registration",
                                                     "| bench_general", "| bench_global_init", "| bench_frame_cost",
                                                     "| bench_batched"]
    assert all(row.split(" | ")[1] == "ok" for row in rows), rows
    assert "tests collected" in rows[0] and "ms" in rows[1]
