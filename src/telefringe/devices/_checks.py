"""Validation shared by the device models: intrinsics fields, a frozen pose, world
points and the image size."""

from __future__ import annotations

import numpy as np

__all__ = ["check_intrinsics", "freeze_pose", "points_array", "image_size_of"]


def _number(val) -> bool:
    return (isinstance(val, int | float | np.integer | np.floating)
            and not isinstance(val, bool) and bool(np.isfinite(val)))


def check_intrinsics(obj, numbers, positive) -> None:
    """Check the frozen intrinsics dataclass ``obj``: the fields ``numbers`` finite numbers,
    those in ``positive`` > 0, ``width`` and ``height`` integers >= 0 (stored as int).
    Raises ValueError naming the class and the field."""
    cls = type(obj).__name__
    for name in numbers:
        if not _number(getattr(obj, name)):
            raise ValueError(f"{cls}.{name} must be a finite number, got "
                             f"{getattr(obj, name)!r}")
    for name in positive:
        if getattr(obj, name) <= 0:
            raise ValueError(f"{cls}.{name} must be > 0, got {getattr(obj, name)!r}")
    for name in ("width", "height"):
        val = getattr(obj, name)
        if not (_number(val) and float(val) == int(val) and int(val) >= 0):
            raise ValueError(f"{cls}.{name} must be an integer >= 0 (pixels), got {val!r}")
        object.__setattr__(obj, name, int(val))


def freeze_pose(obj, t_names: str) -> None:
    """Replace ``obj.R_dev_world`` and ``obj.t_dev`` of a frozen device by validated,
    read-only float copies: R a proper (3, 3) rotation, t finite with one entry per name
    in ``t_names`` (e.g. "tx, ty"). Raises ValueError."""
    R = np.array(obj.R_dev_world, dtype=float)
    t = np.array(obj.t_dev, dtype=float).reshape(-1)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError("R_dev_world must be a finite (3, 3) array")
    if not np.allclose(R @ R.T, np.eye(3), rtol=0.0, atol=1e-9) or np.linalg.det(R) < 0:
        raise ValueError("R_dev_world must be a proper rotation")
    n = len(t_names.split(","))
    if t.shape != (n,) or not np.all(np.isfinite(t)):
        raise ValueError(f"t_dev must be a finite ({n},) array ({t_names}) in mm")
    R.setflags(write=False)
    t.setflags(write=False)
    object.__setattr__(obj, "R_dev_world", R)
    object.__setattr__(obj, "t_dev", t)


def points_array(points_world, *, flat: bool = False) -> np.ndarray:
    """``points_world`` as a float array of shape (..., 3) mm, or (n, 3) with ``flat``.
    Raises ValueError naming the shape expected and the one given."""
    X = np.asarray(points_world, dtype=float)
    if flat and (X.ndim != 2 or X.shape[1] != 3):
        raise ValueError(f"points_world must have shape (n, 3), got {X.shape}")
    if X.shape[-1:] != (3,):
        raise ValueError(f"points_world must have shape (..., 3), got {X.shape}")
    return X


def image_size_of(intrinsics) -> tuple[int, int] | None:
    """(width, height) px of an intrinsics dataclass, or None where it does not give it."""
    k = intrinsics
    return (k.width, k.height) if k.width > 0 and k.height > 0 else None
