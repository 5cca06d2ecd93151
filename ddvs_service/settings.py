"""The base of every settings model of the configuration schema (engine, law, service): one pydantic definition per
setting, with its default, its range and its description (`Field(ge=, le=, description=)`), validated once, on
construction. The service's settings extend the engine's and the law's models, so a setting is defined once.
"""

from __future__ import annotations

from typing import Any, Self, TypeVar

from pydantic import BaseModel, ConfigDict

S = TypeVar("S", bound="Settings")


class Settings(BaseModel):
    """Immutable settings: unknown fields and non-finite numbers are refused."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    def replaced(self, **changes: Any) -> Self:
        """A copy with `changes` applied, validated as a whole (raises `ValueError` naming a bad value)."""
        return self.model_validate({**self.model_dump(), **changes})


def narrowed(settings: Settings, to: type[S], **changes: Any) -> S:
    """The values `settings` holds for the fields it shares with the model `to` (a base of its model: the same
    definitions, already validated, so not validated again), defaults for `to`'s other fields, and `changes`."""
    shared = {name: getattr(settings, name) for name in to.model_fields if name in type(settings).model_fields}
    return to.model_construct(**{**shared, **changes})
