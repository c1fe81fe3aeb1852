"""Checks of the arguments of the public dataset functions (``ValueError`` naming the argument)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["check_seed", "float_arg", "int_arg"]


def int_arg(name: str, value: Any, low: int) -> int:
    """``value`` as an ``int`` when it is an integer ``>= low`` (not a bool)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)


def float_arg(
    name: str, value: Any, low: float, high: float, *, high_open=False, infinite=False
) -> float:
    """``value`` as a ``float`` when it is finite and lies in ``[low, high]`` (``[low,
    high)``: ``high_open``, or ``high`` infinite; ``infinite``: ``inf`` too, where it
    means "off")."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    outside = not (low <= x <= high) or (high_open and x == high)
    if isinstance(value, bool) or outside or not (infinite or math.isfinite(x)):
        bracket = ")" if high_open or (math.isinf(high) and not infinite) else "]"
        kind = "a number" if infinite else "a finite number"
        raise ValueError(f"{name} must be {kind} in [{low:g}, {high:g}{bracket}, got {value!r}")
    return x


def check_seed(seed: Any) -> int:
    """A base seed: an integer >= 0 whose split seeds ``seed * 1000 + 2`` fit in int64."""
    seed = int_arg("seed", seed, 0)
    if seed * 1000 + 2 >= 2**63:
        raise ValueError(f"seed must be below {(2**63 - 3) // 1000}, got {seed}")
    return seed
