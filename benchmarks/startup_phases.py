"""Where a restart of `ddvs serve` spends its time before the service is alive, phase by phase, in one process
(`bench_startup.py --phases N` runs it; issue 21).

The phases are those of `ddvs serve --config FILE` (`service.serve_cli.run`) up to the end of the warm-up, done the
same way in the same order; opening the Zenoh session and answering frames are left to `bench_startup.py`'s rows.
Each phase gives wall and process CPU time (all threads); the first phase counts from the moment the parent spawned
this process (`CLOCK_MONOTONIC`, passed as an argument): the interpreter and its `site` start, including what the
virtual environment's `.pth` files do. The warm-up is split into Taichi's Python front end (`Kernel.materialize`:
each kernel's AST walked, every `ti.func` inlined, the IR built to key the offline cache) and the rest (offline
cache loads, machine code generated from the cached IR on each kernel's first launch, the synthetic frames' own work).

    .venv/bin/python -m benchmarks.startup_phases SPAWNED_AT CONFIG   # prints one JSON object
"""

from __future__ import annotations

import gc
import os
import sys
import time

SPAWNED_AT = float(sys.argv[1])
PHASES: list[tuple[str, float, float]] = []  # name, wall s, CPU s
_last = [SPAWNED_AT, 0.0]


def cpu() -> float:
    t = os.times()
    return t.user + t.system


def phase(name: str) -> None:
    now, used = time.monotonic(), cpu()
    PHASES.append((name, now - _last[0], used - _last[1]))
    _last[:] = [now, used]


def main() -> None:
    phase("interpreter and site (spawn → first line)")
    import argparse
    import json

    from ddvs_service.service import serve_cli  # first, as `ddvs serve` imports it: its environment defaults

    # isort: split
    from ddvs_service.logs import setup_logging
    from ddvs_service.protocol.ros_cli import ros_settings_from_args
    from ddvs_service.protocol.session import session_config_from_args
    from ddvs_service.service.config import ServiceConfig
    from ddvs_service.service.fleet_config import FleetConfig, read_file
    phase("imports: protocol, configuration (numpy, pydantic, zenoh, cv2)")
    gc.disable()  # as `serve_cli.run` does from here to the end of the warm-up
    from ddvs_service.service.process import ServeProcess
    phase("imports: service, registration, kernels (taichi)")
    from kernels.backend import init
    init(None)
    phase("ti.init")
    parser = argparse.ArgumentParser()
    serve_cli.add_arguments(parser)
    args = parser.parse_args(["--config", sys.argv[2], "--log-level", "WARNING"])
    setup_logging(args.log_level)
    base, robots, process = read_file(args.config) if args.config else (ServiceConfig(), None, None)
    base = base.model_copy(update={"zenoh": session_config_from_args(args, base=base.zenoh),
                                   "ros": ros_settings_from_args(args, base=base.ros)})
    base.check()
    served = ServeProcess(FleetConfig(base, robots, process))
    served.uncovered()
    phase("configuration, robots (persisted reference read and prepared)")
    from taichi.lang import kernel_impl

    front_end = [0.0, 0.0]  # wall, CPU
    materialize = kernel_impl.Kernel.materialize

    def timed(self, *a, **k):  # type: ignore[no-untyped-def]
        t0, c0 = time.monotonic(), cpu()
        try:
            return materialize(self, *a, **k)
        finally:
            front_end[0] += time.monotonic() - t0
            front_end[1] += cpu() - c0

    kernel_impl.Kernel.materialize = timed
    served.warm_up()
    kernel_impl.Kernel.materialize = materialize
    now, used = time.monotonic(), cpu()
    wall, cpu_s = now - _last[0], used - _last[1]
    PHASES.append(("warm-up: Taichi front end", front_end[0], front_end[1]))
    PHASES.append(("warm-up: cache loads, machine code, frames", wall - front_end[0], cpu_s - front_end[1]))
    _last[:] = [now, used]
    gc.freeze()
    gc.enable()
    print(json.dumps({"phases": [{"phase": n, "wall_s": w, "cpu_s": c} for n, w, c in PHASES]}))
    for robot in served.robots.values():
        robot.writer.close()
    served.writer.close()


if __name__ == "__main__":
    main()
