"""`ddvs serve --arch X` where Taichi cannot start X: it says so and exits 3, unless `--cpu-fallback` lets it serve
on the CPU. The Vulkan loader is pointed at a driver list that does not exist (`VK_ICD_FILENAMES`), so no machine
has a Vulkan device for these runs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from kernels.backend import satisfies

ROOT = Path(__file__).resolve().parents[1]


def serve_without_vulkan(tmp_path: Path, *args: str) -> tuple[int, list[dict]]:
    """`ddvs serve --arch vulkan --warmup-only *args` with no Vulkan driver: exit status and JSON log records."""
    env = {**os.environ, "VK_ICD_FILENAMES": str(tmp_path / "no-driver.json")}
    done = subprocess.run([sys.executable, "-m", "ddvs.cli", "serve", "--arch", "vulkan", "--warmup-only", *args],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    return done.returncode, [json.loads(line) for line in done.stderr.splitlines() if line.startswith("{")]


def test_serve_refuses_a_backend_it_cannot_start(tmp_path: Path) -> None:
    code, logs = serve_without_vulkan(tmp_path)
    assert code == 3, logs
    refusal = next(record for record in logs if record["msg"] == "taichi backend unavailable")
    assert "'vulkan'" in refusal["error"] and "--cpu-fallback" in refusal["error"]
    assert "warm-up done" not in [record["msg"] for record in logs]


@pytest.mark.slow  # compiles the default configuration's kernels
def test_serve_falls_back_to_the_cpu_when_asked(tmp_path: Path) -> None:
    code, logs = serve_without_vulkan(tmp_path, "--cpu-fallback")
    assert code == 0, logs
    chosen = next(record for record in logs if record["msg"] == "taichi backend")
    assert chosen["requested"] == "vulkan" and chosen["running"] == "cpu"


def test_gpu_means_any_backend_but_the_cpu() -> None:
    assert satisfies("gpu", "vulkan") and satisfies("gpu", "cuda") and not satisfies("gpu", "cpu")
    assert satisfies("vulkan", "vulkan") and not satisfies("vulkan", "cpu") and satisfies("cpu", "cpu")
