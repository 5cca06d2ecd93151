"""`ddvs sim <plant>`: the simulated plants, one sub-subcommand each (table `PLANTS`).

A plant module defines `add_arguments(parser)` and `run(args) -> int`, with light top-level imports (as
`ddvs_service/cli.py` asks of subcommands).
"""

from __future__ import annotations

import argparse
import importlib

# name -> (module implementing it, one-line help). Add a line for a new plant.
PLANTS: dict[str, tuple[str, str]] = {
    "arm": ("sim.arm_cli", "SAPIEN arm (UR5 by default) with a flange camera, over Zenoh"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="plant", metavar="PLANT", required=True)
    for name, (module_name, help_text) in PLANTS.items():
        plant = sub.add_parser(name, help=help_text, description=help_text)
        plant.set_defaults(_plant_module=module_name)
        importlib.import_module(module_name).add_arguments(plant)


def run(args: argparse.Namespace) -> int:
    return int(importlib.import_module(args._plant_module).run(args) or 0)
