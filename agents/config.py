"""Dataclass configs from YAML, with clear errors for unknown keys and wrong types (CleanRL style: one
dataclass per experiment kind, a docstring per field)."""

from __future__ import annotations

import dataclasses
import difflib
import json
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
    path = Path(path)
    data = read_yaml_settings(path)
    data.update({k: v for k, v in overrides.items() if v is not None})
    return dataclass_from_dict(cls, data, str(path))


def read_yaml_settings(path: Path, _chain: tuple[Path, ...] = ()) -> dict:
    """A YAML config's settings. A config with ``base: OTHER.yaml`` (a path relative to its own folder) holds
    only what it changes: its settings are merged into the base's, mapping by mapping (``ddpo: {clip_range: 1e-3}``
    changes one DDPO setting), and a setting given as ``null`` is removed (its default applies)."""
    import yaml

    if not path.exists():
        raise FileNotFoundError(f"no config file at {path} (see experiments/*.yaml for examples)")
    if path.resolve() in _chain:
        raise ValueError(f"{path}: its base configs form a loop ({' -> '.join(p.name for p in _chain)} -> {path.name})")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise ValueError(f"{path} is not valid YAML ({err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of settings at the top level")
    base = data.pop("base", None)
    if base is None:
        return data
    if not isinstance(base, str):
        raise ValueError(f"{path}: base must be the path of another config, got {base!r}")
    return merge_settings(read_yaml_settings(path.parent / base, _chain + (path.resolve(),)), data)


def merge_settings(base: dict, changes: dict) -> dict:
    """``base`` with ``changes`` applied: mappings merged key by key, ``None`` removing a key."""
    merged = dict(base)
    for key, value in changes.items():
        if value is None:
            merged.pop(key, None)
        elif isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = merge_settings(merged[key], value)
        else:
            merged[key] = value
    return merged


DEVICE_CHOICES = "auto, cpu, cuda or cuda:N"


def read_jsonl(path: str | Path, warn=print) -> list[dict]:
    """The rows of a JSON-lines log. A torn last line (the run stopped while writing it) is dropped with a warning
    through ``warn``; a bad line before the last is a ValueError naming the file and the line."""
    lines = [(n, line) for n, line in enumerate(Path(path).read_text().splitlines(), 1) if line.strip()]
    rows = []
    for k, (n, line) in enumerate(lines):
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError as err:
            if k < len(lines) - 1:
                raise ValueError(f"{path} line {n} is not JSON ({err}); fix or remove that line") from None
            warn(f"warning: dropped the torn last line {n} of {path} (the run stopped while writing it)")
    return rows


def check_device(name: str) -> str:
    """``name`` if it spells a device iARCS runs on (:data:`DEVICE_CHOICES`), else a ValueError saying so."""
    text = str(name).strip().lower()
    if text in ("auto", "cpu", "cuda") or (text.startswith("cuda:") and text[5:].isdigit()):
        return text
    raise ValueError(f"device {name!r} is not one iARCS runs on; use {DEVICE_CHOICES}")


def resolve_device(name: str = "auto"):
    """The ``torch.device`` of a device setting: ``auto`` is the first CUDA GPU when torch sees one, else the
    CPU. Asking for a GPU that torch does not see is an error that says why, not a crash inside a layer."""
    import torch

    text = check_device(name)
    if text == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(text)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device {name!r} asked for, but torch {torch.__version__} sees no CUDA GPU (a CPU-only "
                             "build of torch, or no GPU driver); use device auto or cpu, or install a CUDA build "
                             "of torch")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"device {name!r} asked for, but torch sees {torch.cuda.device_count()} CUDA GPU(s) "
                             f"(cuda:0 to cuda:{torch.cuda.device_count() - 1})")
    return device
