"""Dataclass configs from YAML, with clear errors for unknown keys and wrong types (CleanRL style: one
dataclass per experiment kind, a docstring per field)."""

from __future__ import annotations

import dataclasses
import difflib
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")


def dataclass_from_dict(cls: type[T], data: dict, where: str = "config") -> T:
    """Build ``cls`` from a mapping, rejecting unknown keys (with a "did you mean") and wrong types."""
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected a mapping of settings, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    defaults = cls()
    values: dict[str, Any] = {}
    for key, value in data.items():
        if key not in fields:
            close = difflib.get_close_matches(str(key), list(fields), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ValueError(f"{where}: unknown key {key!r}{hint}; known keys: {', '.join(fields)}")
        expected = type(getattr(defaults, key))
        if expected is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, expected) or (expected is not bool and isinstance(value, bool)):
            raise ValueError(f"{where}: {key} must be a {expected.__name__}, got {value!r}")
        values[key] = value
    try:
        return cls(**values)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{where}: {err}") from None


def load_yaml_config(cls: type[T], path: str | Path, **overrides) -> T:
    """Read a YAML file into ``cls``; keyword ``overrides`` that are not None win over the file."""
    import yaml

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no config file at {path} (see experiments/*.yaml for examples)")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise ValueError(f"{path} is not valid YAML ({err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of settings at the top level")
    data.update({k: v for k, v in overrides.items() if v is not None})
    return dataclass_from_dict(cls, data, str(path))
