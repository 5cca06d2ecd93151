"""`ddvs serve --config FILE`: run the servo service until SIGTERM/SIGINT (then zero twist, close, exit 0);
`--warmup-only`: compile the configuration's kernels into Taichi's offline cache and exit (`service.startup`).

One process serves the robot the configuration names, or every robot of its `robots` list (or of `--robots`),
and robots added at run time (`service.fleet_config`, `service.process`).
"""

from __future__ import annotations

import argparse
import os

# Imported before anything that loads numpy or OpenCV (`ddvs.cli` imports this module, then calls `add_arguments`):
# each bundles an OpenBLAS that otherwise starts one thread per core at import, and those threads spin
# (`sched_yield`) after the service's small solves — about 0.25 s of CPU taken from a 2-core host's start-up, for
# matrices of at most 18 × 18 that one thread solves anyway (docs/performance.md, Start-up). A value the user set
# is kept.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ddvs_service.protocol.ros_cli import add_ros_arguments
    from ddvs_service.protocol.session import add_zenoh_arguments

    parser.add_argument("--config", metavar="FILE", help="service configuration (JSON); defaults apply without it")
    parser.add_argument("--state-dir", metavar="DIR", help="where the reference, configuration and state persist")
    parser.add_argument("--robot", help="robot name in the key expressions (overrides the configuration)")
    parser.add_argument("--robots", nargs="+", metavar="NAME",
                        help="serve these robots in this process, each with the configuration's settings (replaces "
                             "the configuration's robots list; each persists in STATE_DIR/robots/NAME)")
    parser.add_argument("--process", metavar="NAME",
                        help="the process's name in its command key <prefix>/serve/NAME/command (add_robot, "
                             "remove_robot, list_robots; default: the first robot's name)")
    parser.add_argument("--fresh", action="store_true",
                        help="ignore (and delete) the persisted state instead of resuming it")
    parser.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    parser.add_argument("--no-warmup", dest="warmup", action="store_false",
                        help="skip compiling the configuration's kernels before serving (the first frame pays)")
    parser.add_argument("--warmup-only", action="store_true",
                        help="compile the configured robots' kernels into Taichi's offline cache and exit, without "
                             "serving or touching the state directory (set-up: the first start is then a warm one)")
    parser.add_argument("--arch", choices=["cpu", "cuda", "vulkan", "gpu"],
                        help="Taichi backend of the kernels (default: $DDVS_TAICHI_ARCH, else cpu; gpu: cuda or "
                             "vulkan, whichever Taichi finds); the service exits with status 3 when it cannot start "
                             "it, unless --cpu-fallback (docs/gpu.md)")
    parser.add_argument("--cpu-fallback", action="store_true",
                        help="serve on the CPU when the --arch backend cannot start (the log and the status say so)")
    parser.add_argument("--batched", choices=["auto", "on", "off"], default="auto",
                        help="serve the waiting frames of all robots of the process in lock-step, one planar step "
                             "launch per level and iteration for all (auto: when the backend is not the CPU, where it "
                             "was not faster; docs/performance.md)")
    parser.add_argument("--realtime-priority", type=int, metavar="1-99",
                        help="run under SCHED_FIFO at this priority (needs root or CAP_SYS_NICE)")
    add_zenoh_arguments(parser)
    add_ros_arguments(parser)


def use_realtime_scheduling(priority: int) -> None:
    """SCHED_FIFO at `priority` (1–99) for this process and every thread it creates afterwards (Taichi's, Zenoh's).

    With every core busy a servo at normal priority waits behind other processes (benchmarks/bench_service.py
    --hogs 2); under SCHED_FIFO it runs as soon as a frame arrives. Needs root or CAP_SYS_NICE (systemd:
    `CPUSchedulingPolicy=fifo`, or `AmbientCapabilities=CAP_SYS_NICE` with this flag); Linux keeps 5 % of each
    second for normal tasks (`sched_rt_runtime_us`), so a runaway loop cannot freeze the host."""
    if not 1 <= priority <= 99:
        raise SystemExit(f"--realtime-priority must be 1…99, got {priority}")
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError as exc:
        raise SystemExit(f"--realtime-priority {priority} refused ({exc}): run as root or with CAP_SYS_NICE") from exc


def run(args: argparse.Namespace) -> int:
    if args.realtime_priority is not None:  # first: every thread created from here on inherits it
        use_realtime_scheduling(args.realtime_priority)
    import gc

    # Start-up (imports, Taichi's front end over every kernel) makes some hundred thousand objects that mostly stay:
    # Python's cyclic collector would traverse them again and again (~5 % of a warm start's CPU time, perf). It is
    # off until the warm-up is done, and what start-up built is then frozen out of later collections (enabled
    # without that, the first collections would traverse it all, ~0.08 s each: pauses of the loop). Frozen objects
    # are never collected: the garbage cycles start-up left (a few thousand objects, a few hundred kB) and those of
    # a robot served from the start, should it be removed at run time, stay; robots added later are collected.
    gc.disable()
    import logging
    import shutil
    import signal
    import threading
    import time
    from pathlib import Path

    from ddvs_service.logs import fields, setup_logging
    from ddvs_service.protocol.ros_cli import ros_settings_from_args
    from ddvs_service.protocol.security import check_process_covered
    from ddvs_service.protocol.session import session_config_from_args
    from ddvs_service.service.config import ServiceConfig
    from ddvs_service.service.fleet_config import FleetConfig, read_file
    from ddvs_service.service.process import ServeProcess
    from ddvs_service.service.startup import start_general_steps, warm_up_configured
    from kernels.backend import BackendUnavailable, finish, init

    setup_logging(args.log_level)
    log = logging.getLogger("ddvs.serve")
    if args.warmup_only and not args.warmup:
        log.error("configuration refused", extra=fields(error="--warmup-only and --no-warmup contradict"))
        return 2
    try:
        base, robots, process = read_file(args.config) if args.config else (ServiceConfig(), None, None)
        update: dict[str, object] = {"zenoh": session_config_from_args(args, base=base.zenoh),
                                     "ros": ros_settings_from_args(args, base=base.ros)}
        if args.state_dir:
            update["state_dir"] = Path(args.state_dir)
        if args.robot:
            update["robot"] = args.robot
        if args.robots:
            robots = [{"robot": name} for name in args.robots]
        base = base.model_copy(update=update)
        base.check()
        fleet = FleetConfig(base, robots, args.process or process)
    except ValueError as exc:
        log.error("configuration refused", extra=fields(error=str(exc)))
        return 2
    # --warmup-only: the general engines' step kernels compile in a helper process beside this one (forked before
    # Taichi starts here; `service.startup`)
    general_steps = start_general_steps(fleet, args.arch, args.cpu_fallback) if args.warmup_only else None
    try:
        running = init(args.arch, fallback=args.cpu_fallback)
    except BackendUnavailable as exc:
        log.error("taichi backend unavailable", extra=fields(error=f"{exc}; --cpu-fallback serves on the CPU"))
        if general_steps is not None:
            general_steps.join()  # it fails to start the backend too
        return 3
    log.info("taichi backend", extra=fields(requested=args.arch or "default", running=running))
    if args.warmup_only:
        t0 = time.monotonic()
        per_robot = warm_up_configured(fleet, general_steps)
        for robot, robot_seconds in per_robot.items():
            log.info("kernels warmed up", extra=fields(robot=robot, seconds=round(robot_seconds, 3)))
        log.info("warm-up done", extra=fields(seconds=round(time.monotonic() - t0, 3), robots=len(per_robot)))
        return 0
    if args.fresh:
        shutil.rmtree(base.state_dir, ignore_errors=True)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    served = ServeProcess(fleet, warmup=args.warmup, batched={"auto": None, "on": True, "off": False}[args.batched])
    if served.uncovered() or not check_process_covered(fleet.command_key, base.zenoh.zenoh_config):
        return 2  # logged: the router configuration beside ours would silently drop those robots or process commands

    def prepare() -> None:  # with the session open and the cameras subscribed: their frames arrive meanwhile
        if args.warmup:
            seconds = served.warm_up()
            log.info("warm-up done", extra=fields(seconds=round(seconds, 3), robots=len(served.robots)))
        gc.freeze()
        gc.enable()

    try:
        served.run(stop, prepare)
    finally:  # what this process compiled (its warm-up, kernels first needed later) is kept for the next start
        finish()
    return 0
