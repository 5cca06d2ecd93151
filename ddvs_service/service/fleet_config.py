"""Which robots one `ddvs serve` process serves, their configurations and where each persists.

The configuration file is a service configuration (`ServiceConfig`, every robot's settings) with two optional
process fields:
- `robots`: a list of objects, each a robot's `robot` name and any settings of its own over the file's (`prefix`,
  `intrinsics`, `registration`, `control`, …; not `zenoh` or `state_dir`, which are the process's). Without it the
  process serves the one robot the file names: the single-robot service, unchanged.
- `process`: the process's name in its command key `<prefix>/serve/<process>/command` (`add_robot`,
  `remove_robot`, `list_robots`); default: the first robot's name.

State directories: the robot of a single-robot configuration persists in `state_dir` as before; every robot of a
`robots` list or added at run time in `state_dir/robots/<robot>`. Robots added and removed at run time are recorded
in `state_dir/robots.json` (`{"added": {robot: settings}, "removed": [robot, …]}`), so a restarted process serves
the same robots: the configured ones, less those removed, plus those added.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ddvs_service.protocol.control import process_command_key
from ddvs_service.protocol.keys import Keys
from ddvs_service.service.config import ServiceConfig
from ddvs_service.service.persistence import BackgroundWriter

PROCESS_FIELDS = ("zenoh", "state_dir")  # one per process: not in a robot's own settings
CHANGES_FILE = "robots.json"


class FleetConfig:
    """The process's configuration: `base` (every robot's settings, the process's session and state directory),
    the configured robots (name → own settings; None: the single robot `base` names) and the process name."""

    def __init__(self, base: ServiceConfig, robots: list[dict[str, Any]] | None = None,
                 process: str | None = None) -> None:
        self.base = base
        self.robots: dict[str, dict[str, Any]] | None = None
        if robots is not None:
            self.robots = {}
            for entry in robots:
                name = entry.get("robot") if isinstance(entry, dict) else None
                if not isinstance(name, str):
                    raise ValueError(f"robots: each entry needs a 'robot' name, got {entry!r}")
                if name in self.robots:
                    raise ValueError(f"robots: {name!r} is listed twice")
                self.robots[name] = {k: v for k, v in entry.items() if k != "robot"}
                self.robot_config(name, self.robots[name])  # every entry checked now, not when it is served
        first = base.robot if not self.robots else next(iter(self.robots))
        self.process = process or first
        Keys(base.prefix, self.process)  # the same rules as a robot name

    @property
    def single(self) -> bool:
        """True for a configuration without `robots`: the one robot it names persists in `state_dir` itself."""
        return self.robots is None

    @property
    def command_key(self) -> str:
        return process_command_key(self.base.prefix, self.process)

    def state_dir_of(self, robot: str) -> Path:
        if self.single and robot == self.base.robot:
            return self.base.state_dir
        return self.base.state_dir / "robots" / robot

    def robot_config(self, robot: str, settings: dict[str, Any]) -> ServiceConfig:
        """Robot `robot`'s configuration: `base` with its own `settings` (raises `ValueError` naming the problem)."""
        own = [key for key in PROCESS_FIELDS if key in settings]
        if own:
            raise ValueError(f"robot {robot!r}: {', '.join(own)} belong to the process, not to one robot")
        if "robot" in settings and settings["robot"] != robot:
            raise ValueError(f"robot {robot!r}: its settings name another robot, {settings['robot']!r}")
        if any(chunk in (".", "..") for chunk in robot.split("/")):
            raise ValueError(f"robot name {robot!r}: '.' and '..' chunks are not allowed (it names a directory)")
        try:
            config = self.base.merged({**settings, "robot": robot})
            Keys(config.prefix, config.robot, config.ros)
        except ValueError as exc:
            raise ValueError(f"robot {robot!r}: {exc}") from exc
        return config.model_copy(update={"state_dir": self.state_dir_of(robot), "zenoh": self.base.zenoh})

    @property
    def configured(self) -> dict[str, dict[str, Any]]:
        """The configured robots, name → own settings (the one robot `base` names when there is no list)."""
        return {self.base.robot: {}} if self.robots is None else self.robots

    def is_configured(self, robot: str) -> bool:
        return robot == self.base.robot if self.robots is None else robot in self.robots

    def to_serve(self, changes: FleetChanges) -> tuple[dict[str, ServiceConfig], dict[str, str]]:
        """The robots to serve, name → configuration: the configured ones less those removed at run time, plus
        those added; and name → error for added robots whose persisted settings no longer apply (left out)."""
        wanted = {name: s for name, s in self.configured.items() if name not in changes.removed} | changes.added
        configs, errors = {}, {}
        for name, settings in wanted.items():
            try:
                configs[name] = self.robot_config(name, settings)
            except ValueError as exc:
                errors[name] = str(exc)
        return configs, errors


def read_file(path: str | Path) -> tuple[ServiceConfig, list[dict[str, Any]] | None, str | None]:
    """The configuration file's parts: every robot's settings, its `robots` list and its `process` name (each None
    when absent); raises `ValueError` naming the file and the problem."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
        if not isinstance(data, dict):
            raise ValueError(f"a JSON {type(data).__name__}; expected an object")
        robots, process = data.pop("robots", None), data.pop("process", None)
        if robots is not None and not isinstance(robots, list):
            raise ValueError("'robots' must be a list of objects")
        if process is not None and not isinstance(process, str):
            raise ValueError(f"'process' must be a name, got {process!r}")
        return ServiceConfig().merged(data), robots, process
    except (OSError, ValueError) as exc:  # json.JSONDecodeError is a ValueError
        raise ValueError(f"service configuration {path}: {exc}") from exc


class FleetChanges:
    """Robots added (with their settings) and removed at run time, persisted in `state_dir/robots.json` by
    `writer` (off the loop thread)."""

    def __init__(self, writer: BackgroundWriter) -> None:
        self.writer = writer
        data = writer.store.load_json(CHANGES_FILE) or {}
        self.added: dict[str, dict[str, Any]] = dict(data.get("added") or {})
        self.removed: set[str] = set(data.get("removed") or [])

    def add(self, robot: str, settings: dict[str, Any]) -> None:
        self.added[robot] = settings
        self.removed.discard(robot)
        self._save()

    def remove(self, robot: str, configured: bool) -> None:
        self.added.pop(robot, None)
        if configured:
            self.removed.add(robot)
        self._save()

    def _save(self) -> None:
        self.writer.put_json(CHANGES_FILE, {"added": dict(self.added), "removed": sorted(self.removed)})
