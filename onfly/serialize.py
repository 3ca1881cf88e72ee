"""One way to turn runtime values into JSON and TOML tables into configs.

- :func:`to_jsonable`: enums to their values, dataclasses to dicts, numpy to lists and
  numbers, non-finite floats to ``None`` (strict JSON), paths to strings.
- :func:`config_from_tables`: a frozen config dataclass from a plain dict (a TOML table) whose
  nested tables fill nested config dataclasses; unknown keys raise the caller's error class
  listing the valid ones.
"""

from __future__ import annotations

import math
from dataclasses import fields, is_dataclass
from enum import Enum
from pathlib import Path
from typing import Any, Mapping, TypeVar

import numpy as np

__all__ = ["to_jsonable", "config_from_tables", "ConfigFileError", "read_toml", "resolve_config_path"]

T = TypeVar("T")


def to_jsonable(x: Any) -> Any:
    """A value made of dicts, lists, strings, numbers, booleans and None only."""
    if isinstance(x, Enum):
        return to_jsonable(x.value)
    if is_dataclass(x) and not isinstance(x, type):
        return {f.name: to_jsonable(getattr(x, f.name)) for f in fields(x)}
    if isinstance(x, Mapping):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return to_jsonable(x.tolist())
    if isinstance(x, np.generic):
        return to_jsonable(x.item())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    return x


def config_from_tables(
    cls: type[T],
    data: Mapping[str, Any],
    nested: Mapping[str, type],
    error: type[Exception],
    what: str,
    convert: Mapping[str, Any] | None = None,
) -> T:
    """Build ``cls`` from ``data``.

    Parameters
    ----------
    cls : the config dataclass
    data : plain values; keys in ``nested`` hold dicts for the nested config classes
    nested : field name -> config class of that field
    error : exception class raised for unknown keys (message names ``what`` and the valid keys)
    what : how the user calls these options, e.g. ``"pilot"``
    convert : optional field name -> callable applied to that (non-nested) value
    """
    known = {f.name for f in fields(cls)}
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        if key not in known:
            raise error(f"unknown {what} option {key!r}; valid: {sorted(known)}")
        if key in nested:
            sub = nested[key]
            valid = {f.name for f in fields(sub)}
            bad = sorted(set(value) - valid)
            if bad:
                raise error(f"unknown {key} option(s) {bad}; valid: {sorted(valid)}")
            value = sub(**{k: tuple(v) if isinstance(v, list) else v for k, v in value.items()})
        elif convert and key in convert and value is not None:
            value = convert[key](value)
        kwargs[key] = value
    return cls(**kwargs)


class ConfigFileError(ValueError):
    """A config file that cannot be used: the message names the file and the table or key."""


def read_toml(path: str | Path, *, allowed: tuple[str, ...] | None = None, what: str = "config") -> dict:
    """The tables of a TOML config file.

    Raises ConfigFileError naming the file when it is missing, is not valid TOML, or (with
    ``allowed``) has a top-level table or key outside ``allowed``.
    """
    import tomllib

    p = Path(path)
    if not p.is_file():
        raise ConfigFileError(f"{p}: {what} file not found" if not p.exists() else f"{p}: not a file")
    try:
        data = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigFileError(f"{p}: not valid TOML: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigFileError(f"{p}: cannot read: {exc}") from None
    if allowed is not None:
        bad = sorted(set(data) - set(allowed))
        if bad:
            raise ConfigFileError(f"{p}: unknown table(s) or key(s) {bad}; valid tables: {list(allowed)}")
        for k in allowed:
            if k in data and not isinstance(data[k], dict):
                raise ConfigFileError(f"{p}: {k!r} must be a table ([{k}]), got {type(data[k]).__name__}")
    return data


def resolve_config_path(value: str | Path, config_file: str | Path) -> Path:
    """A path written inside a config file: ``~`` expanded; relative paths resolve against the
    folder of the config file that holds them (not the working directory), so a config and the
    files next to it can be moved together."""
    p = Path(value).expanduser()
    return p if p.is_absolute() else (Path(config_file).resolve().parent / p).resolve()
