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

__all__ = ["to_jsonable", "config_from_tables"]

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
