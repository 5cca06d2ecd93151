"""One `ddvs serve` process: its Zenoh session, its loop thread, the robots it serves and its process commands.

All robots share the process's Taichi runtime and its compiled kernels, and one loop thread (Taichi launches and
compiles on the thread that runs it). Each turn the loop runs: the oldest pending process command
(`<prefix>/serve/<process>/command`: `add_robot`, `remove_robot`, `list_robots`), each robot's oldest pending
command and newest camera info, one frame — the newest of the robot that has waited longest for a turn
(`scheduler.Scheduler`: a robot's frame waits behind at most one frame of each other robot) — then every robot's
watchdog. Between turns it sleeps until something arrives for the process or any robot, or a watchdog is due.
Batched (`batched`; by default when Taichi runs on a device, not on the CPU, where it was not faster:
docs/performance.md), a turn takes the newest frame of every robot that has one, in the same order, and serves them
in lock-step (`registration.lockstep`: one planar step launch per level and iteration for all of them).
A robot's bad frame or command is answered for that robot alone; the others go on.

`add_robot` builds the robot (its persisted state resumed from `state_dir/robots/<robot>`, or deleted first with
`fresh`), compiles its kernels on this thread when its registration settings are new to the process (the other
robots wait that long), declares its keys and records it in `robots.json`; `remove_robot` publishes its zero twist,
undeclares its keys, flushes its state and records the removal. Shutdown (`stop` set): every robot's zero twist
and last state, then every Zenoh object undeclared and the session closed.
"""

from __future__ import annotations

import functools
import logging
import shutil
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import zenoh

from ddvs_service.logs import fields
from ddvs_service.protocol import Command, InvalidMessage, Keys, ProtocolError, Reply, dump, open_session, parse_command
from ddvs_service.protocol.control import PROCESS_OPS
from ddvs_service.protocol.security import check_robot_covered, warn_if_insecure
from ddvs_service.registration.lockstep import Lockstep
from ddvs_service.service.fleet_config import FleetChanges, FleetConfig
from ddvs_service.service.inbox import Arrival, Inbox, Wakeup
from ddvs_service.service.persistence import BackgroundWriter, StateStore
from ddvs_service.service.robot import CheckedFrame, RobotServo
from ddvs_service.service.scheduler import Scheduler

log = logging.getLogger("ddvs.serve")
MAX_WAIT_S = 0.05  # longest sleep between turns: how soon a set `stop` is noticed


class ServeProcess:
    """Serves `fleet`'s robots (or the given `robots`, built on `wakeup`) until `run`'s `stop` is set.
    `warmup`: compile each new registration configuration's kernels before its robot is served. `batched`: serve
    every robot's waiting frame of a turn in lock-step (module docstring); None: when Taichi does not run on the
    CPU."""

    def __init__(self, fleet: FleetConfig, robots: Iterable[RobotServo] | None = None, wakeup: Wakeup | None = None,
                 warmup: bool = True, batched: bool | None = None) -> None:
        self.fleet = fleet
        self.warmup = warmup
        self.batched = batched
        self._lockstep: Lockstep | None = None
        self.wakeup = wakeup or Wakeup()
        self.inbox: Inbox[None] = Inbox(wakeup=self.wakeup)  # the process's commands (no frames)
        self.writer = BackgroundWriter(StateStore(fleet.base.state_dir))
        self.changes = FleetChanges(self.writer)
        self.robots: dict[str, RobotServo] = {}
        self.scheduler = Scheduler()
        self._warmed: set[tuple[str, bool]] = set()
        self._session: zenoh.Session | None = None
        if robots is None:
            configs, errors = fleet.to_serve(self.changes)
            for name, error in errors.items():
                log.error("a robot added at run time is not served: its settings no longer apply",
                          extra=fields(robot=name, error=error))
            robots = [RobotServo(config, self.wakeup) for config in configs.values()]
        for robot in robots:
            self._schedule(robot)

    def _schedule(self, robot: RobotServo) -> None:
        if robot.inbox.wakeup is not self.wakeup:
            raise ValueError(f"robot {robot.name!r} was built on another loop's wake-up")
        self.scheduler.add(robot.name)
        self.robots[robot.name] = robot

    def uncovered(self) -> list[str]:
        """Robots a router configuration beside the process's Zenoh configuration would cut off (logged)."""
        return [name for name, robot in self.robots.items()
                if not check_robot_covered(robot.keys, self.fleet.base.zenoh.zenoh_config)]

    def warm_up(self) -> float:
        """Compile the kernels of every robot's registration settings not compiled yet; the seconds it took."""
        return sum(self._warm_up(robot) for robot in self.robots.values())

    def _warm_up(self, robot: RobotServo) -> float:
        from ddvs_service.service.startup import needs_initialiser, warm_up

        alone = all(other is robot for other in self.robots.values())
        initialiser = needs_initialiser(robot.config, robot.pipeline.last_good, alone, robot.pipeline.rho_coeffs)
        key = robot.config.registration.model_dump_json()
        if (key, True) in self._warmed or (key, initialiser) in self._warmed:  # with the initialiser covers without
            return 0.0
        seconds = warm_up(robot.config, robot.pipeline.intrinsics, initialiser)
        self._warmed.add((key, initialiser))
        log.info("kernels warmed up", extra=fields(robot=robot.name, seconds=round(seconds, 3),
                                                   initialiser=initialiser))
        return seconds

    # --- the loop -----------------------------------------------------------------------------------------------
    def run(self, stop: threading.Event, prepare: Callable[[], None] | None = None) -> None:
        """Serve until `stop` is set. Every robot publishes a zero twist; every Zenoh object is closed. `prepare`
        (the warm-up) runs once the session is open and the robots subscribed to their cameras, before anything
        else is declared: nothing is answered and no robot announced before it ends, and the newest frame that
        arrived meanwhile waits in its robot's inbox for the first turn."""
        warn_if_insecure(self.fleet.base.zenoh, log)
        session = open_session(self.fleet.base.zenoh)
        try:
            for robot in self.robots.values():
                robot.listen(session)
            if prepare is not None:
                prepare()
            self._serve(session, stop)
        finally:
            session.close()
            for robot in self.robots.values():
                robot.writer.close()
            self.writer.close()

    def _serve(self, session: zenoh.Session, stop: threading.Event) -> None:
        self._session = session
        commands = session.declare_queryable(self.fleet.command_key, self.inbox.on_query)
        try:
            for robot in self.robots.values():
                robot.open(session)
            log.info("process serving", extra=fields(process=self.fleet.process, command_key=self.fleet.command_key,
                                                     robots=list(self.robots)))
            while not stop.is_set():
                self._turn()
        finally:
            if self._lockstep is not None:
                self._lockstep.close()
            for robot in self.robots.values():
                robot.close("service shutting down")
            commands.undeclare()
            log.info("service stopped", extra=fields(process=self.fleet.process, robots=list(self.robots)))

    def _turn(self) -> None:
        robots = list(self.robots.values())
        timeout = min((robot.wait_timeout(MAX_WAIT_S) for robot in robots), default=MAX_WAIT_S)
        self.inbox.wait(timeout, [robot.inbox for robot in robots])
        self._handle_query(self.inbox.take_query())
        for robot in self.robots.values():
            robot.handle_inputs()
        taken = self._take_frames(self._batching())
        if len(taken) == 1:
            robot, arrival = taken[0]
            robot.handle_frame(arrival)
        elif taken:
            if self._lockstep is None:
                self._lockstep = Lockstep()
            self._lockstep.run([functools.partial(robot.handle_frame, arrival) for robot, arrival in taken])
        for robot in self.robots.values():
            robot.watchdog()

    def _batching(self) -> bool:
        """Whether this turn takes every waiting robot's frame (`batched`, by default off the CPU)."""
        if self.batched is not None:
            return self.batched
        from kernels.backend import current

        return current() not in ("", "cpu")

    def _take_frames(self, every: bool) -> list[tuple[RobotServo, Arrival[CheckedFrame]]]:
        """The frame of the robot waiting longest (`scheduler.Scheduler`), or with `every` the frames of every robot
        with one, in that order (one per robot: a frame arriving meanwhile waits for the next turn)."""
        taken: list[tuple[RobotServo, Arrival[CheckedFrame]]] = []
        names: set[str] = set()
        while (name := self.scheduler.pick(
                lambda n: None if n in names else self.robots[n].inbox.waiting_since)) is not None:
            names.add(name)
            robot = self.robots[name]
            arrival = robot.inbox.take_frame()
            if arrival is not None:
                self.scheduler.take(name, arrival.turn, self.wakeup.turns)
                taken.append((robot, arrival))
            if not every:
                break
        return taken

    # --- process commands ---------------------------------------------------------------------------------------
    def _handle_query(self, query: zenoh.Query | None) -> None:
        if query is None:
            return
        try:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            query.reply(query.key_expr, dump(self.handle_command(payload)))
        finally:
            query.drop()

    def handle_command(self, payload: bytes) -> Reply:
        """Execute one process command; any failure is a `Reply.failure` naming the problem, nothing changed."""
        try:
            command = parse_command(payload)
        except (InvalidMessage, ProtocolError) as exc:
            log.warning("process command rejected", extra=fields(error=str(exc)))
            return Reply.failure(str(exc))
        if command.op not in PROCESS_OPS:
            return Reply.failure(f"{command.op} is a robot's command: send it to <prefix>/<robot>/servo/command "
                                 f"(this process's key takes {', '.join(PROCESS_OPS)})")
        try:
            data = self._execute(command)
        except (ValueError, OSError) as exc:
            log.warning("process command refused", extra=fields(op=command.op, robot=command.robot, error=str(exc)))
            return Reply.failure(f"{command.op}: {exc}")
        log.info("process command executed", extra=fields(op=command.op, robot=command.robot))
        return Reply.success(data)

    def _execute(self, command: Command) -> dict[str, Any]:
        if command.op == "list_robots":
            return {"process": self.fleet.process, "robots": [self._summary(r) for r in self.robots.values()]}
        assert command.robot is not None
        if command.op == "add_robot":
            return self._add(command.robot, command.config or {}, command.fresh)
        return self._remove(command.robot)

    def _add(self, name: str, settings: dict[str, Any], fresh: bool) -> dict[str, Any]:
        if name in self.robots:
            raise ValueError(f"robot {name!r} is already served by this process")
        config = self.fleet.robot_config(name, settings)
        keys = Keys(config.prefix, config.robot, config.ros)
        clash = [r.name for r in self.robots.values() if r.keys.base == keys.base]
        if clash:
            raise ValueError(f"robot {clash[0]!r} already uses the keys {keys.base}/**")
        if not check_robot_covered(keys, self.fleet.base.zenoh.zenoh_config, log):
            raise ValueError(f"{keys.base} is not covered by the router's access control beside "
                             f"{self.fleet.base.zenoh.zenoh_config} (logged): its messages would be dropped")
        if fresh:
            if config.state_dir == self.fleet.base.state_dir:
                raise ValueError("fresh would delete the process's state directory: restart with --fresh instead")
            shutil.rmtree(config.state_dir, ignore_errors=True)
        robot = RobotServo(config, self.wakeup)
        t0 = time.monotonic()
        warmed = self._warm_up(robot) if self.warmup else 0.0
        if self._session is not None:
            robot.open(self._session)
        self._schedule(robot)
        self.changes.add(name, settings)
        return {**self._summary(robot), "warmup_s": round(warmed, 3), "seconds": round(time.monotonic() - t0, 3)}

    def _remove(self, name: str) -> dict[str, Any]:
        robot = self.robots.get(name)
        if robot is None:
            raise ValueError(f"robot {name!r} is not served by this process; it serves {sorted(self.robots)}")
        summary = self._summary(robot)
        del self.robots[name]
        self.scheduler.remove(name)
        robot.close("removed from the process")
        self.changes.remove(name, self.fleet.is_configured(name))
        return summary

    def _summary(self, robot: RobotServo) -> dict[str, Any]:
        fair = self.scheduler.fairness[robot.name]
        return {"robot": robot.name, "prefix": robot.config.prefix, "state": robot.pipeline.machine.state.value,
                "state_dir": str(robot.store.dir), "received": robot.inbox.frames_received,
                "counters": robot.current_counters().model_dump(),
                "fairness": {"frames": fair.frames, "max_waited": fair.max_waited,
                             "max_waited_one_robot": fair.max_waited_one_robot}}
