"""Wall time of a convergence-domain sweep one trial after another (`--workers 1`) against a local Ray of 2 workers
(docs/sweeps.md), and what Ray adds to each trial.

Run: `.venv/bin/python benchmarks/bench_sweep.py [--trials 10 --sizes 1 2 3 4 --max-images 400]` (4 sizes × 10
trials with the domain sweep's own image budget: a sweep of 40 planar DDVS trials, 0.05 m / 15° to 0.2 m / 60°).
Prints, with the load average before and after each phase:
- the sweep's wall time both ways (the Ray one includes starting and stopping the local Ray, and each worker's Taichi
  start-up), the speed-up, and whether the two journals are the same file;
- Ray's own cost: starting and stopping a local Ray, and per trial the time from submitting a trial to having its
  record back less the time the trial ran in its worker (one trial at a time on a Ray of one worker; median and
  max over `--overhead-trials` trials, the first one, which pays the worker's Taichi start-up, apart).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import ray

from orchestration.experiment_domain import DomainSettings, run_domain, run_trial
from orchestration.ray_trials import OBJECT_STORE_BYTES, on_ray
from orchestration.workers import SEQUENTIAL, Workers


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def timed_sweep(settings: DomainSettings, workers: Workers, out: Path) -> float:
    start = time.perf_counter()
    run_domain(settings, out, workers=workers)
    return time.perf_counter() - start


def in_worker(run: Callable[[Any], Any]) -> Callable[[Any], tuple[Any, float]]:
    """`run` that also returns how long it ran (s), measured where it runs."""
    def timed(key: Any) -> tuple[Any, float]:
        start = time.perf_counter()
        record = run(key)
        return record, time.perf_counter() - start
    return timed


def ray_overhead(settings: DomainSettings, trials: int) -> tuple[float, list[float], list[float]]:
    """(seconds to start and stop a local Ray, [round trip − time in the worker] and [time in the worker] per trial,
    one at a time)."""
    start = time.perf_counter()
    ray.init(num_cpus=1, object_store_memory=OBJECT_STORE_BYTES, include_dashboard=False, log_to_driver=False,
             configure_logging=False)
    ray.shutdown()
    startup = time.perf_counter() - start
    keys = [("planar", "ddvs", settings.sizes[0], k) for k in range(trials)]
    timed = in_worker(lambda key: run_trial(*key, settings))
    extra, ran = [], []
    ray.init(num_cpus=1, object_store_memory=OBJECT_STORE_BYTES, include_dashboard=False, log_to_driver=False,
             configure_logging=False)
    try:
        for key in keys:  # one generator per trial: the round trip of that trial alone
            submitted = time.perf_counter()
            [(_, outcome)] = list(on_ray([key], timed, Workers(count=1)))
            assert isinstance(outcome, tuple), outcome
            extra.append(time.perf_counter() - submitted - outcome[1])
            ran.append(outcome[1])
    finally:
        ray.shutdown()
    return startup, extra, ran


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    defaults = DomainSettings()
    parser.add_argument("--trials", type=int, default=defaults.trials, help="trials per size (default %(default)s)")
    parser.add_argument("--sizes", type=float, nargs="+", default=[1.0, 2.0, 3.0, 4.0],
                        help="sizes (default 1 2 3 4)")
    parser.add_argument("--max-images", type=int, default=defaults.max_images,
                        help="image budget per trial (default %(default)s, the domain sweep's)")
    parser.add_argument("--overhead-trials", type=int, default=8, help="trials timed one at a time (default 8)")
    args = parser.parse_args()
    settings = DomainSettings(targets=("planar",), laws=("ddvs",), sizes=tuple(args.sizes), trials=args.trials,
                              max_images=args.max_images)
    n = args.trials * len(args.sizes)
    with tempfile.TemporaryDirectory() as tmp:
        print(f"load before: {load()} ({os.cpu_count()} cores)", flush=True)
        sequential = timed_sweep(settings, SEQUENTIAL, Path(tmp) / "sequential")
        print(f"--workers 1: {n} trials in {sequential:.1f} s; load {load()}", flush=True)
        parallel = timed_sweep(settings, Workers(count=2), Path(tmp) / "ray")
        print(f"local Ray, 2 workers: {n} trials in {parallel:.1f} s; load {load()}", flush=True)
        journals = [(Path(tmp) / name / "trials.jsonl").read_bytes() for name in ("sequential", "ray")]
        same = journals[0] == journals[1]
        print(f"speed-up {sequential / parallel:.2f}x; journals identical: {same}", flush=True)
    startup, extra, ran = ray_overhead(settings, args.overhead_trials)
    rest = 1e3 * np.array(extra[1:])
    print(f"Ray start + stop: {startup:.1f} s; first trial on a fresh worker: {extra[0]:.2f} s beyond the trial "
          f"(worker start, imports), which ran {ran[0]:.1f} s (Taichi start-up) against a median "
          f"{np.median(ran[1:]):.1f} s; then per trial: median {np.median(rest):.0f} ms, max {rest.max():.0f} ms "
          f"beyond the trial ({len(rest)} trials); load {load()}", flush=True)

if __name__ == "__main__":
    main()
