"""Result objects as plain JSON values: the one converter every JSON writer uses."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from telefringe.io.atomic import write_json_atomic

__all__ = ["to_jsonable", "number_or_none", "write_json"]


def number_or_none(x) -> float | None:
    """``float(x)``, or None when it is NaN or infinite (JSON has no such numbers)."""
    x = float(x)
    return x if np.isfinite(x) else None


def to_jsonable(obj):
    """Convert results (dataclasses, dicts, numpy arrays and scalars, tuples) to JSON values.

    Dataclasses become objects of their fields, arrays (nested) lists, tuples lists, dict
    keys strings; NaN and infinities become ``null``. Anything else is returned as is.

    >>> to_jsonable({"a": np.array([1.0, np.nan]), 2: (np.int64(3), np.bool_(True))})
    {'a': [1.0, None], '2': [3, True]}
    """
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        # tolist gives Python bools, ints and floats (float32 widened exactly)
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.bool_ | bool):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        return number_or_none(obj)
    return obj


def write_json(path, obj, *, force: bool = True) -> Path:
    """Write ``to_jsonable(obj)`` as indented JSON, atomically."""
    write_json_atomic(path, to_jsonable(obj), force=force)
    return Path(path)
