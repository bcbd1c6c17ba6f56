"""Build parameters: each stage declares its typed params in its own module (`nuplan_occ/stages/<stage>.py`),
one line per param with `param(default, meaning, unit=..., range or choices)`; a config file (TOML / JSON)
and `--set stage.param=value` override them, and every value is checked against its declaration when it is
read, so a bad value fails the build before any work starts, with one line naming where it came from.
"""

from __future__ import annotations

import json
import math
import types
import typing
from dataclasses import MISSING, Field, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Any

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    tomllib = None  # type: ignore[assignment]


class ConfigError(ValueError):
    """A config file or override names an unknown stage or field, or has a value of the wrong type or range."""


def param(default: Any, meaning: str, *, unit: str = "", low: float | None = None, high: float | None = None,
          low_open: bool = False, choices: tuple[str, ...] | None = None) -> Any:
    """A declared stage param: its default, what it means and its unit ("" for counts, ratios and flags);
    numbers must lie in [low, high] (low excluded when low_open; None: unbounded; NaN and infinities never
    pass); a str param, or each element of a tuple-of-str param, must be one of `choices` when given."""
    return field(default=default, metadata={"meaning": meaning, "unit": unit, "low": low, "high": high,
                                            "low_open": low_open, "choices": choices})


def default_params(stages: list) -> dict[str, Any]:
    """params section -> default params instance, for the stages that declare params."""
    return {stage.params_name: stage.params_type() for stage in stages if stage.params_type is not None}


def _annotation(owner: type, name: str) -> Any:
    return typing.get_type_hints(owner)[name]


def _element_type(annotation: Any) -> Any:
    args = typing.get_args(annotation)
    return args[0] if args else str


def _is_tuple(annotation: Any) -> bool:
    return typing.get_origin(annotation) is tuple


def _coerce_scalar(value: Any, kind: Any, where: str) -> Any:
    """`value` as `kind` (bool, int, float or str); strings (from --set) are parsed, other types must match."""
    if kind is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("1", "true", "yes", "on", "0", "false", "no", "off"):
            return value.lower() in ("1", "true", "yes", "on")
        raise ConfigError(f"{where}: expected true or false, got {value!r}")
    if kind is int:
        if isinstance(value, bool):
            raise ConfigError(f"{where}: expected a whole number, got {value!r}")
        if isinstance(value, int):
            return value
        if isinstance(value, str):
            try:
                return int(value.strip())
            except ValueError:
                pass
        raise ConfigError(f"{where}: expected a whole number, got {value!r}")
    if kind is float:
        if isinstance(value, bool):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        if isinstance(value, (int, float)):
            return float(value)
        if isinstance(value, str):
            try:
                return float(value.strip())
            except ValueError:
                pass
        raise ConfigError(f"{where}: expected a number, got {value!r}")
    if kind is str:
        if isinstance(value, str):
            return value.strip()
        raise ConfigError(f"{where}: expected text, got {value!r}")
    raise ConfigError(f"{where}: params of type {kind!r} cannot be set")


def _check(value: Any, spec: Field, annotation: Any, where: str) -> None:
    """Raise ConfigError when `value` breaks its declaration (finite, range, choices)."""
    meta = spec.metadata
    items = value if _is_tuple(annotation) else (value,)
    for item in items:
        if isinstance(item, float) and not math.isfinite(item):
            raise ConfigError(f"{where}: {item!r} is not a finite number")
        if isinstance(item, (int, float)) and not isinstance(item, bool):
            low, high = meta.get("low"), meta.get("high")
            if low is not None and (item < low or (meta.get("low_open") and item == low)):
                raise ConfigError(f"{where}: {item!r} is below the allowed range ({_range_text(meta)})")
            if high is not None and item > high:
                raise ConfigError(f"{where}: {item!r} is above the allowed range ({_range_text(meta)})")
        choices = meta.get("choices")
        if choices is not None and isinstance(item, str) and item not in choices:
            raise ConfigError(f"{where}: {item!r} is not one of {', '.join(choices)}")


def _range_text(meta: Any) -> str:
    low, high = meta.get("low"), meta.get("high")
    left = "-inf" if low is None else f"{low:g}"
    right = "inf" if high is None else f"{high:g}"
    return f"{'(' if meta.get('low_open') or low is None else '['}{left}, {right}]"


def coerce_value(owner: type, spec: Field, value: Any, where: str) -> Any:
    """`value` (from a config file or --set) as the declared type of field `spec` of `owner`, checked."""
    annotation = _annotation(owner, spec.name)
    if _is_tuple(annotation):
        items = [v for v in value.split(",") if v.strip()] if isinstance(value, str) else value
        if not isinstance(items, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        coerced: Any = tuple(_coerce_scalar(v, _element_type(annotation), where) for v in items)
    else:
        kind = annotation
        if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
            raise ConfigError(f"{where}: optional params cannot be set")
        coerced = _coerce_scalar(value, kind, where)
    _check(coerced, spec, annotation, where)
    return coerced


def check_params(instance: Any, where: str) -> None:
    """Check every field of a params instance against its declaration (ConfigError naming `where`)."""
    owner = type(instance)
    for spec in fields(instance):
        _check(getattr(instance, spec.name), spec, _annotation(owner, spec.name), f"{where}.{spec.name}")


def apply_overrides(params: dict[str, Any], overrides: dict[str, dict[str, Any]], source: str) -> dict[str, Any]:
    """New params with `overrides` ({section: {field: value}}) applied and checked; `source` names where they
    came from (a file, --set, a dataset.json)."""
    out = dict(params)
    for section, values in overrides.items():
        if section not in out:
            raise ConfigError(f"{source}: unknown stage {section!r} (stages: {', '.join(out)})")
        current = out[section]
        specs = {spec.name: spec for spec in fields(current)} if is_dataclass(current) else {}
        if not isinstance(values, dict):
            raise ConfigError(f"{source}: {section} must be a table of params, got {values!r}")
        changes = {}
        for key, value in values.items():
            if key not in specs:
                raise ConfigError(f"{source}: stage {section!r} has no param {key!r} (params: {', '.join(sorted(specs))})")
            changes[key] = coerce_value(type(current), specs[key], value, f"{source}: {section}.{key}")
        try:
            out[section] = replace(current, **changes)
        except ValueError as exc:  # a rule between params of one section (__post_init__)
            raise ConfigError(f"{source}: {section}: {exc}") from exc
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


def param_rows(params_type: type) -> list[dict[str, Any]]:
    """One row per declared param of a params dataclass: name, type, default, unit, meaning, range / choices
    (what `nuplan-occ params` prints and the docs list)."""
    rows = []
    for spec in fields(params_type):
        meta = spec.metadata
        default = spec.default if spec.default is not MISSING else None
        allowed = f"one of {', '.join(meta['choices'])}" if meta.get("choices") else (
            _range_text(meta) if meta.get("low") is not None or meta.get("high") is not None else "")
        annotation = _annotation(params_type, spec.name)
        rows.append({"name": spec.name, "type": getattr(annotation, "__name__", str(annotation)), "default": default,
                     "unit": meta.get("unit", ""), "meaning": meta.get("meaning", ""), "allowed": allowed})
    return rows
