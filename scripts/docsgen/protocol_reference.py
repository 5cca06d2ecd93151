"""The protocol reference (`docs/reference/protocol.md`): the key table (`protocol.keys.TOPICS`) and every
control-plane message from its committed JSON schema (`ddvs_service/schemas/*.json`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ddvs_service.protocol.control import process_command_key
from ddvs_service.protocol.keys import TOPICS
from ddvs_service.protocol.schemas import SCHEMA_DIR
from scripts.docsgen.markdown import GENERATED, cell, code, table

_CONSTRAINTS = (
    ("minimum", "≥"), ("exclusiveMinimum", ">"), ("maximum", "≤"), ("exclusiveMaximum", "<"),
    ("minItems", "items ≥"), ("maxItems", "items ≤"), ("minLength", "length ≥"), ("maxLength", "length ≤"),
)


def schema_type(prop: dict[str, Any]) -> str:
    """A JSON schema property's type in words: `number`, `array of number`, `Roi`, `"a" | "b"`, `X | null`."""
    if "$ref" in prop:
        return str(prop["$ref"]).rsplit("/", 1)[-1]
    if "enum" in prop:
        return " | ".join(json.dumps(v) for v in prop["enum"])
    if "const" in prop:
        return json.dumps(prop["const"])
    if "anyOf" in prop:
        return " | ".join(schema_type(p) for p in prop["anyOf"])
    if prop.get("type") == "array":
        items = prop.get("items") or prop.get("prefixItems") or {}
        inner = " , ".join(schema_type(i) for i in items) if isinstance(items, list) else schema_type(items)
        return f"array of {inner}" if inner else "array"
    if prop.get("type") == "object" and "additionalProperties" in prop:
        extra = prop["additionalProperties"]
        return f"object of {schema_type(extra)}" if isinstance(extra, dict) else "object"
    return str(prop.get("type", "any"))


def constraints(prop: dict[str, Any]) -> str:
    """The property's bounds, and its default when it has one."""
    parts = [f"{symbol} {prop[key]}" for key, symbol in _CONSTRAINTS if key in prop]
    for alternative in prop.get("anyOf", []):
        parts += [f"{symbol} {alternative[key]}" for key, symbol in _CONSTRAINTS if key in alternative]
    if "default" in prop:
        parts.append(f"default {json.dumps(prop['default'])}")
    return ", ".join(parts)


def _object(title: str, schema: dict[str, Any], level: int) -> str:
    out = [f"{'#' * level} {title}\n"]
    if schema.get("description"):
        out.append(schema["description"].strip() + "\n")
    required = set(schema.get("required", []))
    props = schema.get("properties", {})
    out.append(table(
        ["field", "type", "required", "constraints", "meaning"],
        [[code(name), cell(schema_type(p)), "yes" if name in required else "", cell(constraints(p)),
          cell(p.get("description", ""))] for name, p in props.items()],
    ))
    return "\n".join(out)


def _message(name: str, schema: dict[str, Any]) -> str:
    out = [_object(f"`{schema.get('title', name)}` (`schemas/{name}.json`)", schema, 3)]
    for def_name, definition in schema.get("$defs", {}).items():
        out.append(_object(f"`{schema.get('title', name)}` › `{def_name}`", definition, 4))
    return "\n".join(out)


def render(schema_dir: Path = SCHEMA_DIR) -> str:
    """The whole page: keys, then each JSON message with its nested definitions."""
    keys = table(
        ["key (under `<prefix>/<robot>/`)", "payload", "published by", "received by", "delivery"],
        [[code(t.suffix), cell(t.payload), cell(t.publisher), cell(t.subscribers), cell(t.delivery)]
         for t in TOPICS.values()],
    )
    messages = [_message(p.stem, json.loads(p.read_text(encoding="utf-8"))) for p in sorted(schema_dir.glob("*.json"))]
    return "\n".join([
        GENERATED.format(source="ddvs_service/protocol/keys.py and ddvs_service/schemas/*.json"),
        "# Protocol reference\n",
        "The keys a robot's servo system uses and the JSON messages of its control plane. The ROS-typed payloads "
        "are CDR-encoded ROS 2 messages; [ROS 2](../ros2.md) says how they map to ROS topics, and "
        "[the protocol page](../protocol.md) explains their use, QoS and bad-input handling.\n",
        "## Keys\n",
        f"Every key is `<prefix>/<robot>/<key>` (default prefix `ddvs`). A process serving several robots also "
        f"answers process commands on `{process_command_key('<prefix>', '<process>')}`.\n",
        keys,
        "## Control-plane messages (JSON)\n",
        "Each message is a JSON object validated against its schema; unknown fields are refused.\n",
        *messages,
    ])
