"""Checks of the arguments of the public dataset functions (``ValueError`` naming the argument)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = [
    "CONSTRAINT_TOL",
    "DT_RTOL",
    "check_seed",
    "check_stride",
    "constraint_violation",
    "float_arg",
    "int_arg",
]

DT_RTOL = 1e-6
"""A recording's time step and a config's agree within this relative difference."""


def int_arg(name: str, value: Any, low: int) -> int:
    """``value`` as an ``int`` when it is an integer ``>= low`` (not a bool)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)


def float_arg(
    name: str,
    value: Any,
    low: float,
    high: float,
    *,
    high_open: bool = False,
    infinite: bool = False,
    low_open: bool = False,
) -> float:
    """``value`` as a ``float`` when it is a finite number (not a string or a bool) in
    ``[low, high]`` (``(low, ...``: ``low_open``; ``..., high)``: ``high_open``, or
    ``high`` infinite; ``infinite``: ``inf`` too, where it means "off")."""
    if isinstance(value, (str, bytes)):
        raise ValueError(f"{name} must be a number, not a string: got {value!r}")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    outside = not (low <= x <= high) or (high_open and x == high) or (low_open and x == low)
    if isinstance(value, bool) or outside or not (infinite or math.isfinite(x)):
        kind = "a number" if infinite else "a finite number"
        if low_open and math.isinf(high):
            raise ValueError(f"{name} must be {kind} > {low:g}, got {value!r}")
        bracket = ")" if high_open or (math.isinf(high) and not infinite) else "]"
        start = "(" if low_open else "["
        raise ValueError(
            f"{name} must be {kind} in {start}{low:g}, {high:g}{bracket}, got {value!r}"
        )
    return x


def check_seed(seed: Any) -> int:
    """A base seed: an integer >= 0 whose split seeds ``seed * 1000 + 2`` fit in int64."""
    seed = int_arg("seed", seed, 0)
    if seed * 1000 + 2 >= 2**63:
        raise ValueError(f"seed must be below {(2**63 - 3) // 1000}, got {seed}")
    return seed


def check_stride(stride: Any, n_states: int, chunk_length: int) -> int:
    """A stride of windows: an integer >= 1, returned as given.

    The windows start at ``0, stride, 2 stride, ...`` up to state ``T - L``; a stride of
    ``T - L + 1`` or more takes only the window at state 0 (one window per trajectory).
    The functions that take the starts use ``min(stride, T - L + 1)``, so a stride beyond
    int64 (``--stride 99999999999999999999``, which broke numpy's indexing after the
    output folder was made) works as the largest one does. ``n_states`` and
    ``chunk_length`` are those the stride will be applied to (kept for the callers'
    symmetry with the other checks).
    """
    del n_states, chunk_length
    return int_arg("stride", stride, 1)


CONSTRAINT_TOL = 0.25  # = systems.system.CONSTRAINT_DRIFT_TOL (not imported: no torch here)
"""Recorded positions whose equality constraints are off by more than this (relative,
:meth:`~diffcontact.mechanics.EqualityConstraints.relative_residual`) do not belong to the
config: its link lengths, pivot, rigid bodies' axis points or units differ from the data
(a wrong origin, or axis points at the rim, are off by more than 0.5). A simulation's
drift stays far below it (``tests/learning/data/test_constraint_check.py`` checks every
built-in task with equality constraints over its horizon), and ``simulate`` warns where it
does not (:data:`~diffcontact.systems.system.CONSTRAINT_DRIFT_TOL`, the same number)."""


def constraint_violation(system: Any, x: np.ndarray) -> str | None:
    """Where positions ``x: (N, T, P, d)`` break ``system``'s equality constraints by more
    than :data:`CONSTRAINT_TOL`: one line naming the worst trajectory and state and the
    count, or ``None`` (also for a system without equality constraints)."""
    import torch

    constraints = system.constraints
    if constraints is None or constraints.num_equations == 0:
        return None
    rel = constraints.relative_residual(torch.as_tensor(x, dtype=torch.float64))
    worst = rel.amax(-1)  # (N, T)
    above = int((worst > CONSTRAINT_TOL).sum())
    if above == 0:
        return None
    n, t = divmod(int(worst.argmax()), worst.shape[1])
    return (
        f"the positions break the config's equality constraints (link lengths, pivot, rigid "
        f"bodies' unit axis points) by up to {float(worst.max()):.3g} relative (trajectory "
        f"{n}, state {t}; {above} of {worst.numel()} states above {CONSTRAINT_TOL:g}): the "
        "config does not describe the data, or its origin or units differ "
        "(docs/own-data.md, 'What to check')"
    )
