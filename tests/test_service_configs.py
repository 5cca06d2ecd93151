"""The shipped service and Zenoh configurations load and validate."""

from __future__ import annotations

from pathlib import Path

import pytest
import zenoh

from ddvs_service.service.config import ServiceConfig

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("path", sorted((ROOT / "configs" / "serve").glob("*.json")), ids=lambda p: p.name)
def test_service_configs_validate(path: Path) -> None:
    config = ServiceConfig.from_file(path)
    config.check()


@pytest.mark.parametrize("path", sorted((ROOT / "configs" / "zenoh").glob("*.json5")), ids=lambda p: p.name)
def test_zenoh_configs_parse(path: Path) -> None:
    zenoh.Config.from_file(str(path))


def test_bad_service_config_is_named(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text('{"control": {"law": "pid"}}')
    with pytest.raises(ValueError, match=r"(?s)bad\.json.*law"):
        ServiceConfig.from_file(bad)


def test_unknown_interpolation_is_refused() -> None:
    with pytest.raises(ValueError, match="interpolation"):
        ServiceConfig().merged({"registration": {"interpolation": "linear"}})


def test_camera_response_and_defocus_reach_the_engine() -> None:
    config = ServiceConfig().merged({"registration": {"gamma": 2.2, "defocus_px": 3.5}})
    engine = config.registration.engine_config()
    assert (engine.gamma, engine.defocus_px) == (2.2, 3.5)
    for bad in ({"gamma": 9.0}, {"defocus_px": -1.0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            ServiceConfig().merged({"registration": bad}).check()
