"""`ddvs serve --warmup-only`: the configured robots' kernels compiled into Taichi's offline cache ahead of a start,
without serving or touching the state directory; a second process finds them there (real Taichi, its own cache)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import cached_kernels

from ddvs_service.service.config import ServiceConfig
from ddvs_service.service.startup import needs_initialiser

ROOT = Path(__file__).resolve().parents[1]


def serve(config: Path, cache: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("DDVS_ZENOH_")}
    env["TI_OFFLINE_CACHE_FILE_PATH"] = str(cache)
    return subprocess.run([sys.executable, "-m", "ddvs.cli", "serve", "--config", str(config), *args],
                          env=env, cwd=ROOT, capture_output=True, text=True, timeout=600)


def records(log: str) -> list[dict]:
    return [json.loads(line) for line in log.splitlines() if line.startswith("{")]


@pytest.mark.slow
def test_warmup_only_fills_the_offline_cache_that_the_next_process_hits(tmp_path: Path) -> None:
    state, cache = tmp_path / "state", tmp_path / "ticache"
    config = tmp_path / "serve.json"
    config.write_text(json.dumps({
        "robot": "w0", "state_dir": str(state),
        "registration": {"template_size": [40, 30], "gain_grid": [1, 1], "global_init": False},
        "robots": [{"robot": "w0"}, {"robot": "w1"}],  # the same settings: compiled once
    }))
    first = serve(config, cache, "--warmup-only")
    assert first.returncode == 0, first.stderr
    warmed = {r["robot"]: r["seconds"] for r in records(first.stderr) if r["msg"] == "kernels warmed up"}
    assert set(warmed) == {"w0", "w1"} and warmed["w0"] > 0.0 and warmed["w1"] == 0.0
    assert [r["robots"] for r in records(first.stderr) if r["msg"] == "warm-up done"] == [2]
    assert not state.exists()  # nothing served, nothing persisted
    kernels = cached_kernels(cache)
    assert kernels, "the warm-up left no compiled kernel in the offline cache"

    second = serve(config, cache, "--warmup-only")  # every kernel found: none compiled, none written again
    assert second.returncode == 0, second.stderr
    assert cached_kernels(cache) == kernels


WHOLE_WARM_UP = """
import sys
from ddvs_service.service.fleet_config import FleetConfig, read_file
from ddvs_service.service.startup import warm_up_configured
from kernels.backend import finish, init
init()
warm_up_configured(FleetConfig(*read_file(sys.argv[1])))  # one process, the general model's whole frame path
finish()
"""


@pytest.mark.slow
def test_a_general_warmup_split_over_two_processes_leaves_no_kernel_to_compile(tmp_path: Path) -> None:
    """`--warmup-only` compiles a general configuration's engine step kernels in a helper process and the rest as
    the planar model here: together every kernel that the general model's whole warm-up (global initialiser, first
    frame, tracking) launches, which a later process then loads without compiling or writing any."""
    cache = tmp_path / "ticache"
    config = tmp_path / "serve.json"
    config.write_text(json.dumps({"robot": "g0", "state_dir": str(tmp_path / "state"), "registration": {
        "model": "general", "template_size": [40, 30], "gain_grid": [1, 1], "global_init": True}}))
    first = serve(config, cache, "--warmup-only")
    assert first.returncode == 0, first.stderr
    kernels = cached_kernels(cache)
    assert len(kernels) >= 3, kernels  # at least the two general step kernels and the planar one
    env = {**os.environ, "TI_OFFLINE_CACHE_FILE_PATH": str(cache)}
    whole = subprocess.run([sys.executable, "-c", WHOLE_WARM_UP, str(config)], env=env, cwd=ROOT,
                           capture_output=True, text=True, timeout=600)
    assert whole.returncode == 0, whole.stderr
    assert cached_kernels(cache) == kernels


def test_warmup_only_refuses_no_warmup(tmp_path: Path) -> None:
    config = tmp_path / "serve.json"
    config.write_text(json.dumps({"robot": "w0", "state_dir": str(tmp_path / "state")}))
    done = serve(config, tmp_path / "ticache", "--warmup-only", "--no-warmup")
    assert done.returncode == 2
    assert any("--warmup-only and --no-warmup" in r.get("error", "") for r in records(done.stderr))


def test_only_a_robot_resuming_alone_leaves_the_initialiser_to_its_first_search() -> None:
    """The warm-up skips the global initialiser's kernels only where the first frame is re-acquired from a persisted
    estimate (and, general model, ρ*) and no other robot of the process would share the pause of their later
    compile."""
    planar = ServiceConfig()
    general = planar.model_copy(update={"registration": planar.registration.model_copy(update={"model": "general"})})
    last_good, rho = np.eye(3), [0.0] * 6
    assert not needs_initialiser(planar, last_good, alone=True)
    assert needs_initialiser(planar, None, alone=True)
    assert needs_initialiser(planar, last_good, alone=False)
    assert not needs_initialiser(general, last_good, alone=True, rho_coeffs=rho)
    assert needs_initialiser(general, last_good, alone=True)  # ρ* unknown: estimated from the initialiser's start
    assert needs_initialiser(general, None, alone=True, rho_coeffs=rho)
    assert needs_initialiser(general, last_good, alone=False, rho_coeffs=rho)


OPENBLAS_THREADS = """
import ctypes, sys
from ddvs.cli import build_parser
build_parser("serve")  # what `ddvs serve` does first: imports its module, then its arguments' (numpy, OpenCV)
import cv2, numpy
libraries = sorted({line.split()[-1] for line in open("/proc/self/maps") if "openblas" in line.split()[-1]})
for path in libraries:
    lib = ctypes.CDLL(path)
    name = next(n for n in ("scipy_openblas_get_num_threads64_", "openblas_get_num_threads") if hasattr(lib, n))
    print(path.rsplit("/", 1)[-1], getattr(lib, name)())
"""


@pytest.mark.parametrize("configured", [None, "2"])
def test_serve_runs_openblas_on_one_thread_unless_configured(configured: str | None) -> None:
    """numpy's and OpenCV's OpenBLAS start with one thread under `ddvs serve` (their thread pools spun at start-up,
    docs/performance.md); an OPENBLAS_NUM_THREADS the user set is kept."""
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}
    if configured is not None:
        env["OPENBLAS_NUM_THREADS"] = configured
    done = subprocess.run([sys.executable, "-c", OPENBLAS_THREADS], env=env, cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    threads = dict(line.split() for line in done.stdout.splitlines())
    assert len(threads) == 2, f"expected numpy's and OpenCV's OpenBLAS loaded, found {sorted(threads)}"
    expected = configured or "1"
    if configured is not None and os.cpu_count() == 1:
        expected = "1"  # OpenBLAS caps its threads at the cores it finds
    assert set(threads.values()) == {expected}, threads
