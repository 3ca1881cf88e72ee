import json
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

import numpy as np
import pytest

from onfly.serialize import config_from_tables, to_jsonable


class Color(str, Enum):
    RED = "red"


@dataclass(frozen=True)
class Inner:
    a: float = 1.0
    b: tuple = (1, 2)


@dataclass(frozen=True)
class Outer:
    inner: Inner = Inner()
    name: str = "x"
    goal: tuple | None = None


class Bad(ValueError):
    pass


def test_to_jsonable_gives_strict_json():
    value = {
        "enum": Color.RED,
        "arr": np.arange(3, dtype=np.int64),
        "f32": np.float32(0.5),
        "nan": float("nan"),
        "inf": np.float64("inf"),
        "dc": Inner(),
        "path": Path("/tmp/x"),
        1: (np.bool_(True), None),
    }
    out = to_jsonable(value)
    text = json.dumps(out, allow_nan=False)  # raises if anything non-strict is left
    assert json.loads(text) == {
        "enum": "red", "arr": [0, 1, 2], "f32": 0.5, "nan": None, "inf": None,
        "dc": {"a": 1.0, "b": [1, 2]}, "path": "/tmp/x", "1": [True, None],
    }


def test_config_from_tables_nested_and_errors():
    cfg = config_from_tables(Outer, {"inner": {"b": [3, 4]}, "goal": [1, 2, 3]}, {"inner": Inner}, Bad, "outer", convert={"goal": tuple})
    assert cfg == Outer(Inner(1.0, (3, 4)), "x", (1, 2, 3))
    with pytest.raises(Bad, match=r"unknown outer option 'nmae'; valid: \['goal', 'inner', 'name'\]"):
        config_from_tables(Outer, {"nmae": "y"}, {"inner": Inner}, Bad, "outer")
    with pytest.raises(Bad, match=r"unknown inner option\(s\) \['c'\]; valid: \['a', 'b'\]"):
        config_from_tables(Outer, {"inner": {"c": 1}}, {"inner": Inner}, Bad, "outer")
