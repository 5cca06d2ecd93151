"""JSON schemas of the control-plane messages, committed under `ddvs_service/schemas/<name>.json`.

Regenerate after changing a model: `python -m ddvs_service.protocol.schemas` (a test fails while they differ).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from ddvs_service.protocol.control import Command, GroundTruth, Reply, StateSnapshot, Status

SCHEMA_DIR = Path(__file__).resolve().parent.parent / "schemas"
SCHEMA_MODELS: dict[str, type[BaseModel]] = {
    "command": Command,
    "reply": Reply,
    "status": Status,
    "state_snapshot": StateSnapshot,
    "ground_truth": GroundTruth,
}


def schema_documents() -> dict[str, dict[str, Any]]:
    """`{name: JSON schema}` of every control-plane message model."""
    return {name: model.model_json_schema() for name, model in SCHEMA_MODELS.items()}


def schema_text(schema: dict[str, Any]) -> str:
    """The committed file form of a schema: sorted keys, two-space indent, trailing newline."""
    return json.dumps(schema, indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def write_schemas(directory: Path = SCHEMA_DIR) -> list[Path]:
    """Write every schema to `directory/<name>.json`; returns the paths written."""
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, schema in schema_documents().items():
        path = directory / f"{name}.json"
        path.write_text(schema_text(schema), encoding="utf-8")
        paths.append(path)
    return paths


if __name__ == "__main__":
    for p in write_schemas():
        print(p)
