"""Device check for a machine with a GPU: the device tests, then the speed benchmarks, on one Taichi backend; one table.

Steps, each a subprocess with `DDVS_TAICHI_ARCH` set to the backend (docs/gpu.md):
1. `tests/test_kernels_devices.py` for the backend, required (`DDVS_REQUIRE_DEVICES`: a missing device fails);
2. `bench_registration.py`, `bench_general.py`, `bench_global_init.py`, `bench_frame_cost.py` and `bench_batched.py`
   (the inputs of the robots-per-device models, docs/performance.md) with shortened settings.
The table lists each step's result, wall time and headline figures (a benchmark's lines with a median, or its
markdown rows), with the machine and its load average before and after.

`--dry-run`: on any machine, the same steps with Taichi on the CPU — the device tests collected, not run — to check
the script itself; its figures are the CPU's.

    .venv/bin/python benchmarks/device_check.py [--arch cuda|vulkan] [--dry-run]
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = (
    ("bench_registration", ["--reps", "8", "--frames", "20"]),
    ("bench_general", ["--frames", "20"]),
    ("bench_global_init", ["--repeats", "3"]),
    ("bench_frame_cost", ["--frames", "60", "--warm-up", "15"]),  # launches and cost per frame: docs/performance.md
    # the batched fleet path's launch cost t_0 and per-pixel cost on this backend ("{arch}": the step's backend)
    ("bench_batched", ["--arch", "{arch}", "--robots", "1", "4", "16", "--cycles", "8"]),
)


@dataclass
class Step:
    name: str
    ok: bool
    seconds: float
    figures: list[str]


def figures_of(output: str) -> list[str]:
    """Headline lines of a step's output: a benchmark's lines with a median and its markdown tables' data rows
    (cells joined by " · "), else the last line (pytest's summary)."""
    lines = [line.strip() for line in output.splitlines() if line.strip()]
    picked = []
    for index, line in enumerate(lines):
        header = index + 1 < len(lines) and lines[index + 1].replace(" ", "").startswith("|--")
        if line.startswith("|") and not header and not line.replace(" ", "").startswith("|--"):
            picked.append(" · ".join(cell.strip() for cell in line.strip("|").split("|")))
        elif "median" in line and not line.startswith("|"):
            picked.append(line)
    return picked or lines[-1:]


def run_step(name: str, command: list[str], arch: str, required: str, timeout: float) -> Step:
    """Run `command` with Taichi on `arch` (and `required` in `DDVS_REQUIRE_DEVICES`); echo its output."""
    env = {**os.environ, "DDVS_TAICHI_ARCH": arch, "DDVS_REQUIRE_DEVICES": required, "PYTHONPATH": str(ROOT)}
    start = time.perf_counter()
    try:
        done = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
        ok, output = done.returncode == 0, done.stdout + done.stderr[-2000:] * (done.returncode != 0)
    except subprocess.TimeoutExpired as exc:
        ok, output = False, f"timed out after {timeout:.0f} s: {exc.stdout!r}"[-2000:]
    seconds = time.perf_counter() - start
    print(f"### {name} ({'ok' if ok else 'FAILED'}, {seconds:.0f} s)\n{output.rstrip()}\n", flush=True)
    return Step(name, ok, seconds, figures_of(output))


def table(steps: list[Step], backend: str, loads: tuple[float, float]) -> str:
    rows = [f"Device check: Taichi backend {backend}; {platform.node()} {platform.machine()}, {os.cpu_count()} CPUs; "
            f"load average {loads[0]:.2f} before, {loads[1]:.2f} after", "",
            "| Step | Result | Wall s | Figures |", "|---|---|---|---|"]
    for step in steps:
        figures = "<br>".join(step.figures)
        rows.append(f"| {step.name} | {'ok' if step.ok else 'FAILED'} | {step.seconds:.0f} | {figures} |")
    return "\n".join(rows)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--arch", default="cuda", choices=["cuda", "vulkan"], help="the backend to check")
    parser.add_argument("--dry-run", action="store_true",
                        help="Taichi on the CPU, the device tests collected only: checks this script anywhere")
    args = parser.parse_args()
    backend = "cpu" if args.dry_run else args.arch
    tests = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/test_kernels_devices.py",
             "-k", args.arch, *(["--collect-only"] if args.dry_run else [])]
    loads = os.getloadavg()[0]
    steps = [run_step(f"device tests ({args.arch}{', collected' if args.dry_run else ''})", tests, backend,
                      "" if args.dry_run else args.arch, timeout=240)]
    for name, options in BENCHMARKS:
        command = [sys.executable, f"benchmarks/{name}.py", *(option.format(arch=backend) for option in options)]
        steps.append(run_step(name, command, backend, "", timeout=180))
    print(table(steps, backend, (loads, os.getloadavg()[0])))
    return 0 if all(step.ok for step in steps) else 1


if __name__ == "__main__":
    sys.exit(main())
