"""One configuration schema: each setting defined once (one default, one range, one description), used by the
service, the engines and the experiments; every setting has a range enforced at start and at `set_config`, and the
settings read at start are refused at run time."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from pydantic import BaseModel
from test_service_node import service_config

from ddvs_service.control.law import ControlConfig, LawSettings
from ddvs_service.protocol import Command, dump
from ddvs_service.protocol.ros_settings import RosSettings
from ddvs_service.protocol.session import SessionConfig
from ddvs_service.registration.config import RegistrationConfig
from ddvs_service.registration.general_config import GeneralConfig
from ddvs_service.service.config import (
    START_ONLY,
    ControlSettings,
    IntrinsicsConfig,
    RegistrationSettings,
    ServiceConfig,
)
from ddvs_service.service.robot import RobotServo

SCHEMA: tuple[type[BaseModel], ...] = (ServiceConfig, IntrinsicsConfig, RegistrationSettings, RegistrationConfig,
                                       GeneralConfig, ControlSettings, LawSettings, ControlConfig, SessionConfig,
                                       RosSettings)
UNSAFE = {"frame_timeout_s": 1e300, "max_frame_bytes": 2**62, "registration": {"max_iterations": 10**9},
          "control": {"max_linear": 1e300}}


def _definition(model: type[BaseModel], name: str) -> str:
    info = model.model_fields[name]
    return repr((info.annotation, info.default, info.default_factory, info.metadata, info.description))


def test_each_setting_has_one_definition() -> None:
    """A setting that several models hold (the service's and the engine's registration settings, the service's and
    the law's control settings, the general engine's interpolation) has the same type, default, range and
    description in all of them: one definition, not copies that drift apart."""
    definitions: dict[str, set[str]] = {}
    for model in SCHEMA:
        for name in model.model_fields:
            definitions.setdefault(name, set()).add(_definition(model, name))
    twice = {name: found for name, found in definitions.items() if len(found) > 1}
    assert not twice, twice
    shared = set(RegistrationConfig.model_fields) & set(RegistrationSettings.model_fields)
    assert shared == set(RegistrationConfig.model_fields)  # the service holds every engine setting
    assert set(LawSettings.model_fields) <= set(ControlSettings.model_fields)
    assert ServiceConfig().registration.engine_config() == RegistrationConfig()  # the same defaults
    assert ServiceConfig().control.law_config() == ControlConfig(stop_threshold=0.0)


def _bounded(schema: dict[str, Any]) -> bool:
    return ("minimum" in schema or "exclusiveMinimum" in schema) and (
        "maximum" in schema or "exclusiveMaximum" in schema)


def _unbounded_numbers(schema: dict[str, Any], path: str) -> list[str]:
    """The numeric leaves of a JSON schema (fields, tuple items, union members) without a lower and an upper
    bound."""
    if schema.get("type") in ("integer", "number"):
        return [] if _bounded(schema) or "enum" in schema else [path]
    found = []
    for i, item in enumerate(schema.get("prefixItems", [])):
        found += _unbounded_numbers(item, f"{path}[{i}]")
    for option in schema.get("anyOf", []):
        found += _unbounded_numbers(option, path)
    return found


def _models(schema: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The top model of a JSON schema and every model it nests (`$defs`), by name."""
    return {schema["title"]: schema, **schema.get("$defs", {})}


@pytest.mark.parametrize("root", [ServiceConfig, GeneralConfig], ids=lambda m: m.__name__)
def test_every_setting_has_a_description_and_a_range(root: type[BaseModel]) -> None:
    """What the configuration reference is generated from: each field's description, and for every number its
    lowest and highest accepted value, in the service's configuration and every model it nests (and the general
    engine's settings, which the service does not expose)."""
    for model, schema in _models(root.model_json_schema()).items():
        for name, field in schema["properties"].items():
            assert field.get("description"), f"{model}.{name} has no description"
            assert not _unbounded_numbers(field, name), f"{model}.{name} has no range"


@pytest.mark.parametrize("patch", [{key: value} for key, value in UNSAFE.items()], ids=list(UNSAFE))
def test_values_that_switch_safety_off_are_refused_at_start_and_at_set_config(patch: dict[str, Any],
                                                                               tmp_path: Path) -> None:
    """A watchdog of 1e300 s, 10^9 iterations per level, 2^62-byte frames, an unbounded speed: refused by the
    configuration file at start, and by `set_config` at run time, naming the setting; nothing applied or
    persisted."""
    name = next(iter(patch.get("registration", patch.get("control", patch))))
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(patch))
    with pytest.raises(ValueError, match=name):
        ServiceConfig.from_file(bad)
    robot = RobotServo(service_config(0, tmp_path / "state"))
    try:
        before = robot.config
        reply = robot.handle_command(dump(Command(op="set_config", config=patch)))
        assert not reply.ok and name in (reply.error or ""), reply
        assert robot.config == before
        assert not (tmp_path / "state" / "state.json").exists()
    finally:
        robot.writer.close()


@pytest.mark.parametrize("patch", [
    {"state_dir": "elsewhere"},
    {"zenoh": {"listen": ["tcp/127.0.0.1:1"]}},
    {"ros": {"domain_id": 3}},
    {"intrinsics": {"fx": 300.0, "fy": 300.0, "cx": 10.0, "cy": 10.0, "width": 20, "height": 20}},
], ids=lambda p: next(iter(p)))
def test_settings_read_at_start_are_refused_at_run_time_with_that_reason(patch: dict[str, Any],
                                                                         tmp_path: Path) -> None:
    robot = RobotServo(service_config(0, tmp_path / "state"))
    try:
        before = robot.config
        reply = robot.handle_command(dump(Command(op="set_config", config=patch)))
        assert not reply.ok, reply
        assert f"{next(iter(patch))} cannot change while it is served: read when the robot starts" in (
            reply.error or "")
        assert robot.config == before
    finally:
        robot.writer.close()
    assert ServiceConfig.model_fields[next(iter(patch))].json_schema_extra == START_ONLY


def test_settings_within_their_ranges_change_at_run_time(tmp_path: Path) -> None:
    config = service_config(0, tmp_path / "state")
    new = config.merged({"frame_timeout_s": 0.5, "registration": {"max_iterations": 50},
                         "control": {"max_linear": 0.1}})
    assert (new.frame_timeout_s, new.registration.max_iterations, new.control.max_linear) == (0.5, 50, 0.1)
    assert config.start_only_changes(new) == []


def test_persisted_changes_out_of_range_are_dropped_at_start(tmp_path: Path) -> None:
    """A change persisted by an earlier version that accepted it is checked again at start and dropped."""
    state = tmp_path / "state"
    state.mkdir()
    (state / "state.json").write_text(json.dumps({"config_changes": {"frame_timeout_s": 1e300}}))
    robot = RobotServo(service_config(0, state))
    try:
        assert robot.config.frame_timeout_s == service_config(0, state).frame_timeout_s
    finally:
        robot.writer.close()
