"""The single-robot servo service: one robot served by a process of its own (the N = 1 case of `ServeProcess`).

`ServoNode(config)` is that robot (`RobotServo`: keys, pipeline, state, persistence in `config.state_dir`);
`run(stop)` serves it, with the process's command key named after it, until `stop` is set. `ddvs serve` builds a
`ServeProcess` from its configuration file instead, which also serves robot lists (`service.fleet_config`).
"""

from __future__ import annotations

import threading

from ddvs_service.service.fleet_config import FleetConfig
from ddvs_service.service.process import ServeProcess
from ddvs_service.service.robot import RobotServo


class ServoNode(RobotServo):
    """One robot, served by `run(stop)` until `stop` is set (then a zero twist, every Zenoh object closed)."""

    def run(self, stop: threading.Event) -> None:
        ServeProcess(FleetConfig(self.config), [self], self.inbox.wakeup, warmup=False).run(stop)
