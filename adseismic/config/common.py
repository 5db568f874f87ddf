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
        raise ConfigError(f"{key}: {_short(value)} is not a mapping; write it as '{key.split('.')[-1]}: "
                          f"{{...}}' with {what}")
    return value


def _check_keys(section: dict, key: str, allowed) -> None:
    for k in section:
        if k not in allowed:
            name = f"{key}.{k}" if key else str(k)
            raise ConfigError(f"{name}: unknown key; allowed: {', '.join(allowed)}")


def _number(value, key: str, unit: str = "") -> float:
    """A finite float; numeric strings (PyYAML reads 1e-3 as text) are accepted."""
    u = f" in {unit}" if unit else ""
    x = None
    if isinstance(value, (bool, np.bool_, complex, np.complexfloating)) or value is None:
        x = None
    elif isinstance(value, (int, float, np.number, str)):
        try:
            x = float(value.strip() if isinstance(value, str) else value)
        except (ValueError, OverflowError):
            x = None
    if x is None or not math.isfinite(x):
        hint = " (true/false are not numbers)" if isinstance(value, (bool, np.bool_)) else ""
        raise ConfigError(f"{key}: {_short(value)} is not a finite number{hint}; give a number{u}")
    return x


def _short(value, limit: int = 80) -> str:
    """repr(value), cut to ``limit`` characters (a fuzzed or pasted value can be huge)."""
    r = repr(value)
    return r if len(r) <= limit else r[: limit - 3] + "..."


def _positive(value, key: str, unit: str = "") -> float:
    x = _number(value, key, unit)
    if x <= 0:
        raise ConfigError(f"{key}: {_short(value)} is not > 0; give a positive number" +
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
        raise ConfigError(f"{key}: {_short(value)} is not an integer; give a whole number")
    return int(x)


def _boolean(value, key: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{key}: {_short(value)} is not true or false; write true or false")
    return value


def _choice(value, key: str, choices) -> object:
    if value not in choices:
        raise ConfigError(f"{key}: {_short(value)} is not one of {', '.join(map(str, choices))}; "
                          f"pick one of them")
    return value


class _DuplicateKey(Exception):
    """A key given twice in one YAML mapping (raised by the loader, turned into a ConfigError)."""


def _loader():
    """A yaml.SafeLoader that refuses a key given twice in one mapping (PyYAML keeps the last one
    silently); merge keys (``<<``) may still be overridden."""
    import yaml

    class UniqueKeyLoader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            if isinstance(node, yaml.MappingNode):
                seen = {}
                for key_node, _ in node.value:
                    if key_node.tag == "tag:yaml.org,2002:merge":
                        continue
                    key = self.construct_object(key_node, deep=True)
                    try:
                        first = seen.get(key)
                    except TypeError:  # unhashable: the base class raises its own error below
                        continue
                    line = key_node.start_mark.line + 1
                    if first is not None:
                        raise _DuplicateKey(f"key {key!r} appears twice in one mapping (line {first} and line {line})")
                    seen[key] = line
            return super().construct_mapping(node, deep)

    return UniqueKeyLoader


MAX_CONFIG_BYTES = 10 * 2**20  # a config is a few kB; anything above 10 MiB is not one


def _read_yaml(path) -> tuple[dict, Path]:
    """(parsed YAML, path) of a config file. Refuses (ConfigError naming the file and the place):
    a missing file, one that is not UTF-8 (byte offset and line), invalid YAML, a key given twice
    in one mapping, and YAML nested too deeply to parse."""
    import yaml

    path = pathlib.Path(path).expanduser()
    if not path.is_file():
        raise ConfigError(f"config: {str(path)!r} does not exist; give the path of a YAML file")
    try:
        size = path.stat().st_size
        if size > MAX_CONFIG_BYTES:
            raise ConfigError(f"config: {path} is {size / 2**20:.1f} MiB; a config is a small YAML file "
                              f"(< {MAX_CONFIG_BYTES / 2**20:.0f} MiB): give the YAML config, not a data file")
        data = path.read_bytes()
    except OSError as e:
        raise ConfigError(f"config: {path} cannot be read ({e.strerror or e}); check its permissions") from None
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data[:e.start].count(b"\n") + 1
        col = e.start - (data.rfind(b"\n", 0, e.start) + 1) + 1
        raise ConfigError(f"config: {path} is not UTF-8 text: byte {e.start} (line {line}, column {col}) is "
                          f"{data[e.start:e.start + 1]!r} ({e.reason}); save the file as UTF-8 (e.g. "
                          f"'iconv -f latin1 -t utf-8 {path.name}'), or give the YAML config, not a binary file") from None
    try:
        raw = yaml.load(text, Loader=_loader())  # a SafeLoader subclass
    except _DuplicateKey as e:
        raise ConfigError(f"config: {path}: {e}; keep one of them (YAML would silently use the last)") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"config: {path} is not valid YAML: {e}") from None
    except RecursionError:
        raise ConfigError(f"config: {path} is nested too deeply to parse; a config has at most a few levels") from None
    except (ValueError, TypeError, OverflowError) as e:  # e.g. a timestamp like 2001-02-30
        raise ConfigError(f"config: {path} could not be parsed as YAML ({type(e).__name__}: {e}); "
                          f"quote the value (write it as a string) or fix it") from None
    return raw, path
