"""Build parameters: each stage's typed params (defaults live in the stage's Params dataclass),
overridable from a JSON/TOML config file and from `--set stage.field=value` on the CLI."""

from __future__ import annotations

import json
from dataclasses import fields, is_dataclass, replace
from pathlib import Path
from typing import Any

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    tomllib = None  # type: ignore[assignment]


class ConfigError(ValueError):
    """A config file or override names an unknown stage or field, or has a value of the wrong type."""


def default_params(stages: list) -> dict[str, Any]:
    """stage name -> default params instance."""
    return {stage.params_name: stage.params_type() for stage in stages}


def _coerce(value: Any, current: Any, where: str) -> Any:
    if isinstance(current, bool):
        if isinstance(value, str):
            if value.lower() in ("1", "true", "yes", "on"):
                return True
            if value.lower() in ("0", "false", "no", "off"):
                return False
            raise ConfigError(f"{where}: expected a boolean, got {value!r}")
        return bool(value)
    if isinstance(current, (int, float)) and not isinstance(current, bool):
        try:
            return type(current)(value)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{where}: expected {type(current).__name__}, got {value!r}") from exc
    if isinstance(current, tuple):
        items = value.split(",") if isinstance(value, str) else list(value)
        return tuple(items)
    return value


def apply_overrides(params: dict[str, Any], overrides: dict[str, dict[str, Any]], source: str) -> dict[str, Any]:
    """New params with `overrides` ({stage: {field: value}}) applied; `source` names where they came from."""
    out = dict(params)
    for stage_name, values in overrides.items():
        if stage_name not in out:
            raise ConfigError(f"{source}: unknown stage {stage_name!r} (stages: {', '.join(out)})")
        current = out[stage_name]
        names = {f.name for f in fields(current)} if is_dataclass(current) else set()
        changes = {}
        for key, value in values.items():
            if key not in names:
                raise ConfigError(f"{source}: stage {stage_name!r} has no param {key!r} (params: {', '.join(sorted(names))})")
            changes[key] = _coerce(value, getattr(current, key), f"{source}: {stage_name}.{key}")
        out[stage_name] = replace(current, **changes)
    return out


def load_config_file(path: Path) -> dict[str, dict[str, Any]]:
    """Read {stage: {field: value}} from a .json or .toml file."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config file ({exc})") from exc
    try:
        if path.suffix == ".toml":
            if tomllib is None:
                raise ConfigError(f"{path}: TOML configs need Python >= 3.11; use JSON")
            data = tomllib.loads(text)
        else:
            data = json.loads(text)
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{path}: not valid {path.suffix.lstrip('.') or 'JSON'} ({exc})") from exc
    if not isinstance(data, dict) or not all(isinstance(v, dict) for v in data.values()):
        raise ConfigError(f"{path}: expected a table of stages, each a table of params")
    return data


def parse_set_options(options: list[str]) -> dict[str, dict[str, Any]]:
    """`["split.box_margin=1.2", ...]` -> {"split": {"box_margin": "1.2"}} (values coerced later)."""
    out: dict[str, dict[str, Any]] = {}
    for option in options:
        key, sep, value = option.partition("=")
        stage, dot, field_name = key.partition(".")
        if not sep or not dot:
            raise ConfigError(f"--set {option!r}: expected STAGE.PARAM=VALUE")
        out.setdefault(stage.strip(), {})[field_name.strip()] = value.strip()
    return out
