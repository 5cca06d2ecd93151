"""The configuration reference (`docs/reference/configuration.md`) from the service's pydantic schema.

Every field of `ServiceConfig`, nested models included, becomes one row: its dotted name, type, its one default,
its range (the schema's bounds and choices) and its description. Nothing is written by hand: a setting added to the
schema appears here at the next `make docs`, and the freshness test fails until then.
"""

from __future__ import annotations

import json
import types
import typing
from typing import Any, Literal, get_args, get_origin

import annotated_types as at
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from ddvs_service.service.config import ServiceConfig
from scripts.docsgen.markdown import GENERATED, cell, code, table

_BOUNDS = ((at.Gt, "gt", ">"), (at.Ge, "ge", "≥"), (at.Lt, "lt", "<"), (at.Le, "le", "≤"))


def _models(annotation: Any) -> list[type[BaseModel]]:
    """The pydantic models an annotation refers to (`X`, `X | None`)."""
    kinds = (annotation, *get_args(annotation))
    return [k for k in kinds if isinstance(k, type) and issubclass(k, BaseModel)]


def type_name(annotation: Any) -> str:
    """A short readable name of a type annotation: `int`, `float | tuple[float, float]`, `"a" | "b"`."""
    origin = get_origin(annotation)
    if origin is Literal:
        return " | ".join(json.dumps(v) for v in get_args(annotation))
    if origin in (typing.Union, types.UnionType):
        return " | ".join(type_name(a) for a in get_args(annotation))
    if origin is typing.Annotated:
        return type_name(get_args(annotation)[0])
    if origin is not None:
        args = ", ".join("..." if a is Ellipsis else type_name(a) for a in get_args(annotation))
        return f"{getattr(origin, '__name__', str(origin))}[{args}]"
    if annotation is type(None):
        return "null"
    return getattr(annotation, "__name__", str(annotation))


def _bounds(metadata: list[Any]) -> list[str]:
    """The bounds among a field's or a type's metadata: `> 0`, `≤ 8`, `length ≥ 1`."""
    parts = []
    for meta in metadata:
        for kind, attr, symbol in _BOUNDS:
            if isinstance(meta, kind):
                parts.append(f"{symbol} {getattr(meta, attr)}")
        if isinstance(meta, at.MinLen):
            parts.append(f"length ≥ {meta.min_length}")
        if isinstance(meta, at.MaxLen):
            parts.append(f"length ≤ {meta.max_length}")
        if isinstance(meta, FieldInfo):
            parts += _bounds(meta.metadata)
    return parts


def _element_bounds(annotation: Any) -> str:
    """The bounds of the elements of a tuple or list type: `each ≥ 1, ≤ 4`, or per run of equal entries
    (`entries 1–2: ≥ 0; entries 3–4: ≥ 1`); empty when the elements have none."""
    origin = get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        return next((b for arg in get_args(annotation) if (b := _element_bounds(arg))), "")
    if origin not in (tuple, list):
        return ""
    per_entry = [", ".join(_bounds(list(get_args(arg)[1:]))) if get_origin(arg) is typing.Annotated else ""
                 for arg in get_args(annotation) if arg is not Ellipsis]
    if not any(per_entry):
        return ""
    if len(set(per_entry)) == 1:
        return f"each {per_entry[0]}"
    runs: list[tuple[int, int, str]] = []
    for i, bounds in enumerate(per_entry, 1):
        if runs and runs[-1][2] == bounds:
            runs[-1] = (runs[-1][0], i, bounds)
        else:
            runs.append((i, i, bounds))
    return "; ".join(f"entries {a}–{b}: {bounds}" if a != b else f"entry {a}: {bounds}" for a, b, bounds in runs)


def value_range(info: FieldInfo) -> str:
    """The field's bounds (`> 0`, `≥ 1, ≤ 232`), its elements' (`each ≥ 1, ≤ 4`), its choices, or empty."""
    parts = _bounds(info.metadata)
    elements = _element_bounds(info.annotation)
    if elements:
        parts.append(elements)
    for kind in (info.annotation, *get_args(info.annotation)):
        if get_origin(kind) is Literal:
            parts.append("one of " + ", ".join(str(v) for v in get_args(kind)))
    return ", ".join(parts)


def default_value(info: FieldInfo) -> Any:
    """The field's default, its factory called; PydanticUndefined when it is required."""
    if info.default_factory is not None:
        return info.default_factory()  # type: ignore[call-arg]
    return info.default


def _default_text(info: FieldInfo) -> str:
    value = default_value(info)
    if value is PydanticUndefined:
        return "required"
    if isinstance(value, BaseModel):
        return "see below"
    return code(json.dumps(value, default=str, ensure_ascii=False))


def rows(model: type[BaseModel], prefix: str = "") -> list[tuple[str, FieldInfo, type[BaseModel]]]:
    """(dotted name, field, the model that declares it) of every setting, nested models' fields after their row."""
    out = []
    for name, info in model.model_fields.items():
        out.append((prefix + name, info, model))
        for nested in _models(info.annotation):
            out += rows(nested, f"{prefix}{name}.")
    return out


def start_only(info: FieldInfo) -> bool:
    """Whether the schema marks the setting as read at start only (`set_config` refuses to change it)."""
    extra = info.json_schema_extra
    return isinstance(extra, dict) and extra.get("start_only") is True


def _meaning(info: FieldInfo) -> str:
    text = info.description or ""
    if start_only(info):
        text += " *Read at start: a run-time change is refused.*"
    return cell(text.strip())


def _section(model: type[BaseModel], title: str, prefix: str) -> str:
    body = [f"## {title}\n"]
    if model.__doc__:
        body.append(" ".join(model.__doc__.split()) + "\n")
    body.append(table(
        ["setting", "type", "default", "range", "meaning"],
        [[code(prefix + name), cell(type_name(info.annotation)), _default_text(info), cell(value_range(info)),
          _meaning(info)] for name, info in model.model_fields.items()],
    ))
    for name, info in model.model_fields.items():
        for nested in _models(info.annotation):
            body.append(_section(nested, f"`{prefix}{name}`", f"{prefix}{name}."))
    return "\n".join(body)


def render() -> str:
    """The whole page: the top-level settings, then one section per nested model, each with its own table."""
    return "\n".join([
        GENERATED.format(source="the pydantic models of ddvs_service/service/config.py"),
        "# Configuration reference\n",
        "The service's configuration is one JSON object (`ddvs serve --config FILE`; examples in `configs/serve/`). "
        "Every setting has one default, below; unknown settings are refused; a whole configuration is validated "
        "at once, at start and on every run-time change (`ddvs ctl config set --set control.gains=0.6`), and a "
        "rejected change changes nothing. Dotted names (`control.law`) are the paths used by `ddvs ctl config "
        "set --set` and by a robot's own settings in a fleet file ([Configuration](../guide/configuration.md)).\n",
        _section(ServiceConfig, "Top level", ""),
    ])
