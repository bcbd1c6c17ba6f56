"""Library settings made from a stage's declared params: a library function that takes a settings dataclass
gets the values of the stage's params of the same names."""

from __future__ import annotations

from dataclasses import fields
from typing import Any, TypeVar

Settings = TypeVar("Settings")


def settings_from(settings_type: type[Settings], params: Any) -> Settings:
    """A `settings_type` instance whose every field takes the value of the same-named field of `params`
    (a stage's params dataclass, which declares each of them)."""
    return settings_type(**{spec.name: getattr(params, spec.name) for spec in fields(settings_type)})
