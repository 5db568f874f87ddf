"""Shared pieces of the config schemas: :class:`ConfigError`, the value validators and YAML reading.

Every validator takes the dotted key path of the value it checks and raises :class:`ConfigError`
whose message starts with that path, says what was found and how to fix it. PyYAML reads ``1e-3``
(no dot, no sign in the exponent) as a string; float fields therefore accept any string that
``float()`` parses. This module imports no workflow (and nothing of adseismic at all).
"""
from __future__ import annotations

import math
import pathlib
from pathlib import Path

import numpy as np

__all__ = ["ConfigError"]


class ConfigError(ValueError):
    """An invalid config; the message starts with the dotted key path and names the fix."""


# ------------------------------------------------------------------------------ primitives

def _mapping(value, key: str, what: str) -> dict:
    if not isinstance(value, dict):
        raise ConfigError(f"{key}: {value!r} is not a mapping; write it as '{key.split('.')[-1]}: "
                          f"{{...}}' with {what}")
    return value


def _check_keys(section: dict, key: str, allowed) -> None:
    for k in section:
        if k not in allowed:
            name = f"{key}.{k}" if key else str(k)
            raise ConfigError(f"{name}: unknown key; allowed: {', '.join(allowed)}")


def _number(value, key: str, unit: str = "") -> float:
    """A finite float; numeric strings (PyYAML reads 1e-3 as text) are accepted."""
    u = f" {unit}" if unit else ""
    if isinstance(value, bool) or value is None:
        x = None
    elif isinstance(value, (int, float, np.number)):
        x = float(value)
    elif isinstance(value, str):
        try:
            x = float(value.strip())
        except ValueError:
            x = None
    else:
        x = None
    if x is None or not math.isfinite(x):
        raise ConfigError(f"{key}: {value!r} is not a finite number; give a number{u}")
    return x


def _positive(value, key: str, unit: str = "") -> float:
    x = _number(value, key, unit)
    if x <= 0:
        raise ConfigError(f"{key}: {value!r} is not > 0; give a positive number" +
                          (f" of {unit}" if unit else ""))
    return x


def _integer(value, key: str) -> int:
    """An int; integral floats and integer strings are accepted, bools are not."""
    if isinstance(value, bool):
        ok = False
    elif isinstance(value, (int, np.integer)):
        return int(value)
    else:
        try:
            x = _number(value, key)
            ok = x == int(x)
        except ConfigError:
            ok = False
    if not ok:
        raise ConfigError(f"{key}: {value!r} is not an integer; give a whole number")
    return int(x)


def _boolean(value, key: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{key}: {value!r} is not true or false; write true or false")
    return value


def _choice(value, key: str, choices) -> object:
    if value not in choices:
        raise ConfigError(f"{key}: {value!r} is not one of {', '.join(map(str, choices))}; "
                          f"pick one of them")
    return value


def _optional(section: dict, name: str, fn, *args):
    value = section.get(name)
    return None if value is None else fn(value, *args)


def _read_yaml(path) -> tuple[dict, Path]:
    import yaml

    path = pathlib.Path(path).expanduser()
    if not path.is_file():
        raise ConfigError(f"config: {str(path)!r} does not exist; give the path of a YAML file")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ConfigError(f"config: {path} is not valid YAML: {e}") from None
    return raw, path

