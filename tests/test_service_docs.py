"""docs/protocol.md names what an outside client needs: every configuration field and the reply of every command."""

from __future__ import annotations

import re
from pathlib import Path
from typing import get_args

from pydantic import BaseModel

from ddvs_service.protocol.control import Command, Counters
from ddvs_service.service.config import ServiceConfig

DOC = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"


def field_paths(model: type[BaseModel], prefix: str = "") -> list[str]:
    """Dotted names of every field of `model`, nested models included (`registration.gain_grid`)."""
    paths = []
    for name, info in model.model_fields.items():
        paths.append(prefix + name)
        for kind in (info.annotation, *get_args(info.annotation)):
            nested = isinstance(kind, type) and issubclass(kind, BaseModel) and kind.__module__.startswith("ddvs_")
            if nested and name not in ("zenoh", "ros"):  # settings documented in sections of their own
                paths += field_paths(kind, f"{prefix}{name}.")
    return paths


def test_protocol_doc_names_every_configuration_field() -> None:
    text = DOC.read_text()
    def named(path: str) -> bool:  # `control.law`, or a JSON key of an object's format: "fx"
        return f"`{path}`" in text or f'"{path.rsplit(".", 1)[-1]}"' in text

    missing = [p for p in field_paths(ServiceConfig) if not named(p)]
    assert not missing, f"docs/protocol.md does not name these configuration fields: {missing}"


def test_protocol_doc_gives_each_commands_reply_data() -> None:
    text = DOC.read_text()
    section = text.split("**Reply data**", 1)
    assert len(section) == 2, "docs/protocol.md has no 'Reply data' table"
    ops = get_args(Command.model_fields["op"].annotation)
    rows = {m.group(1) for m in re.finditer(r"^\| `([a-z_]+)`[^|]*\|", section[1], re.MULTILINE)}
    assert set(ops) <= rows, f"no reply data row for {sorted(set(ops) - rows)}"
    assert all(f"`{name}`" in text for name in Counters.model_fields)
