"""What :func:`~diffcontact.control.optimize` may change: parts of the initial state, parameters.

A variable reads its current value from ``(z0, params)`` and writes a batch of
new values back into them, differentiably. Four kinds:

- :class:`Velocity`: a body's centre-of-mass velocity (``dim`` values); a
  rigid body translates (its spin is kept).
- :class:`Spin`: a rigid body's angular velocity about its centre (one value
  in 2D, three in 3D); its centre velocity is kept.
- :class:`Position`: a body's centre position (``dim`` values); the whole body
  moves (orientation and velocities kept).
- :class:`Parameter`: a field of :class:`~diffcontact.systems.PhysicalParams`
  (``"mass"``, ``"mu"``, ``"cor"``, ...), all of it or the entries at ``index``.

Every variable has a ``name`` (default e.g. ``"velocity[0]"``) and box
``bounds``: ``(low, high)``, each a number or one number per value, ``None``
for unbounded. Writes happen in the order given; the kinds commute.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

__all__ = ["Parameter", "Position", "Spin", "Variable", "Velocity", "as_bounds"]

Bound = float | Sequence[float] | None
PARAMETER_FIELDS = (
    "mass", "second_moments", "mu", "cor", "gravity", "stiffness", "rest_length", "eps",
)  # fmt: skip
# valid values of each field (PhysicalParams.validate); positive ones stay 1e-9 away from 0
PHYSICAL_RANGE = {
    "mass": (1e-9, float("inf")),
    "second_moments": (1e-9, float("inf")),
    "eps": (1e-9, float("inf")),
    "rest_length": (1e-9, float("inf")),
    "cor": (0.0, 1.0),
}


def as_bounds(bounds: Any, size: int, name: str) -> tuple[Tensor, Tensor]:
    """``(low, high)`` as two float64 ``(size,)`` tensors (``-inf``/``inf`` where open).

    Raises:
        ValueError: not a pair, a wrong number of values, NaN, or ``low > high``.
    """
    if bounds is None:
        bounds = (None, None)
    if not isinstance(bounds, Sequence) or isinstance(bounds, str) or len(bounds) != 2:
        raise ValueError(f"{name}: bounds must be (low, high), got {bounds!r}")
    out = []
    for side, fill in zip(bounds, (-float("inf"), float("inf")), strict=True):
        if side is None:
            out.append(torch.full((size,), fill, dtype=torch.float64))
            continue
        t = torch.as_tensor(side, dtype=torch.float64).reshape(-1)
        if t.numel() == 1:
            t = t.expand(size).clone()
        if t.numel() != size:
            raise ValueError(f"{name}: a bound needs 1 or {size} values, got {t.numel()}")
        if torch.isnan(t).any():
            raise ValueError(f"{name}: a bound is NaN")
        out.append(t)
    low, high = out
    if (low > high).any():
        raise ValueError(f"{name}: low bound above high bound ({low.tolist()} > {high.tolist()})")
    return low, high


class Variable:
    """Base of the variable kinds: a name, bounds and the read/write pair.

    Subclasses implement :meth:`size`, :meth:`read` and :meth:`write`;
    :meth:`bind` checks the variable against a simulator before use.
    """

    name: str
    bounds: Any

    def bind(self, sim: Any) -> None:
        """Check that the variable exists in ``sim`` (a :class:`~.planner.Planner`)."""

    def size(self, sim: Any) -> int:
        raise NotImplementedError

    def read(self, z0: Tensor, params: Any, sim: Any) -> Tensor:
        """The current value ``(size,)`` from one unbatched state ``(2, P, dim)``."""
        raise NotImplementedError

    def write(self, z0: Tensor, params: Any, value: Tensor, sim: Any) -> tuple[Tensor, Any]:
        """``z0: (S, 2, P, dim)``, ``value: (S, size)`` -> the new ``(z0, params)``."""
        raise NotImplementedError


def _body(sim: Any, body: int, name: str) -> Any:
    bodies = sim.bodies
    if isinstance(body, bool) or not isinstance(body, int) or not 0 <= body < len(bodies):
        raise ValueError(f"{name}: body must be one of 0..{len(bodies) - 1}, got {body!r}")
    return bodies[body]


@dataclass(frozen=True)
class Velocity(Variable):
    """A body's centre-of-mass velocity; the other points of a rigid body follow (spin kept)."""

    body: int
    bounds: Any = None
    name: str = ""

    def __post_init__(self) -> None:
        if not self.name:
            object.__setattr__(self, "name", f"velocity[{self.body}]")

    def bind(self, sim: Any) -> None:
        _body(sim, self.body, self.name)

    def size(self, sim: Any) -> int:
        return sim.dim

    def read(self, z0: Tensor, params: Any, sim: Any) -> Tensor:
        return z0[1, sim.bodies[self.body].points[0]]

    def write(self, z0: Tensor, params: Any, value: Tensor, sim: Any) -> tuple[Tensor, Any]:
        pts = list(sim.bodies[self.body].points)
        old = z0[:, 1, pts[0]]  # (S, dim)
        z = z0.clone()
        z[:, 1, pts] = z0[:, 1, pts] + (value - old).unsqueeze(1)
        return z, params


@dataclass(frozen=True)
class Position(Variable):
    """A body's centre position; the whole body is translated."""

    body: int
    bounds: Any = None
    name: str = ""

    def __post_init__(self) -> None:
        if not self.name:
            object.__setattr__(self, "name", f"position[{self.body}]")

    def bind(self, sim: Any) -> None:
        _body(sim, self.body, self.name)

    def size(self, sim: Any) -> int:
        return sim.dim

    def read(self, z0: Tensor, params: Any, sim: Any) -> Tensor:
        return z0[0, sim.bodies[self.body].points[0]]

    def write(self, z0: Tensor, params: Any, value: Tensor, sim: Any) -> tuple[Tensor, Any]:
        pts = list(sim.bodies[self.body].points)
        old = z0[:, 0, pts[0]]
        z = z0.clone()
        z[:, 0, pts] = z0[:, 0, pts] + (value - old).unsqueeze(1)
        return z, params


def _cross(w: Tensor, r: Tensor) -> Tensor:
    """``w x r``: 2D (``w: (..., 1)``, ``r: (..., n, 2)``) or 3D (``w: (..., 3)``)."""
    if r.shape[-1] == 2:
        return w.unsqueeze(-2) * torch.stack([-r[..., 1], r[..., 0]], dim=-1)
    return torch.linalg.cross(w.unsqueeze(-2).expand_as(r), r, dim=-1)


@dataclass(frozen=True)
class Spin(Variable):
    """A rigid body's angular velocity about its centre (2D: one value, rad/s; 3D: three)."""

    body: int
    bounds: Any = None
    name: str = ""

    def __post_init__(self) -> None:
        if not self.name:
            object.__setattr__(self, "name", f"spin[{self.body}]")

    def bind(self, sim: Any) -> None:
        body = _body(sim, self.body, self.name)
        if len(body.points) < 2:
            raise ValueError(
                f"{self.name}: body {self.body} is a {body.kind} (one point) and has no spin"
            )

    def size(self, sim: Any) -> int:
        return 1 if sim.dim == 2 else 3

    def read(self, z0: Tensor, params: Any, sim: Any) -> Tensor:
        pts = list(sim.bodies[self.body].points)
        r = z0[0, pts[1:]] - z0[0, pts[0]]  # (n, dim)
        u = z0[1, pts[1:]] - z0[1, pts[0]]
        if sim.dim == 2:  # w = (r x u) / |r|^2, averaged over the axis points
            w = (r[:, 0] * u[:, 1] - r[:, 1] * u[:, 0]) / (r * r).sum(-1)
            return w.mean().reshape(1)
        # least squares: u_i = w x r_i = -[r_i]_x w
        rx = torch.zeros(r.shape[0], 3, 3, dtype=r.dtype, device=r.device)
        rx[:, 0, 1], rx[:, 0, 2], rx[:, 1, 2] = -r[:, 2], r[:, 1], -r[:, 0]
        rx = rx - rx.transpose(-1, -2)
        return torch.linalg.lstsq(-rx.reshape(-1, 3), u.reshape(-1, 1)).solution.reshape(3)

    def write(self, z0: Tensor, params: Any, value: Tensor, sim: Any) -> tuple[Tensor, Any]:
        pts = list(sim.bodies[self.body].points)
        r = z0[:, 0, pts[1:]] - z0[:, 0, pts[0]].unsqueeze(1)  # (S, n, dim)
        z = z0.clone()
        z[:, 1, pts[1:]] = z0[:, 1, pts[0]].unsqueeze(1) + _cross(value, r)
        return z, params


@dataclass(frozen=True)
class Parameter(Variable):
    """A physical parameter: a field of ``PhysicalParams``, all of it or the entries at ``index``.

    Args:
        field: ``"mass"``, ``"second_moments"``, ``"mu"``, ``"cor"``, ``"gravity"``,
            ``"stiffness"``, ``"rest_length"`` or ``"eps"``.
        index: ``None`` (the whole field, flattened), an int or a tuple of ints
            indexing the field's (unbatched) tensor.
    """

    field: str
    index: int | tuple[int, ...] | None = None
    bounds: Any = None
    name: str = ""

    def __post_init__(self) -> None:
        if not self.name:
            suffix = "" if self.index is None else f"[{self.index}]"
            object.__setattr__(self, "name", f"{self.field}{suffix}")

    def _value(self, params: Any) -> Tensor:
        value = getattr(params, self.field)  # a number (eps) read as float64, not float32
        return value if isinstance(value, Tensor) else torch.tensor(value, dtype=torch.float64)

    def bind(self, sim: Any) -> None:
        if self.field not in PARAMETER_FIELDS:
            raise ValueError(
                f"{self.name}: unknown parameter {self.field!r}; fields: "
                f"{', '.join(PARAMETER_FIELDS)}"
            )
        params = sim.parameters()
        if params is None:
            raise ValueError(
                f"{self.name}: {sim.name} has no physical parameters to optimise "
                "(only initial-state variables)"
            )
        if getattr(params, self.field) is None:
            raise ValueError(f"{self.name}: {sim.name} has no {self.field}")
        value = self._value(params)
        if self.index is not None:
            try:
                value[self.index]
            except (IndexError, TypeError):
                raise ValueError(
                    f"{self.name}: index {self.index!r} does not fit {self.field} of shape "
                    f"{tuple(value.shape)}"
                ) from None

    def size(self, sim: Any) -> int:
        value = self._value(sim.parameters())
        return (value if self.index is None else value[self.index]).numel()

    def read(self, z0: Tensor, params: Any, sim: Any) -> Tensor:
        value = self._value(params)
        return (value if self.index is None else value[self.index]).reshape(-1)

    def physical_bounds(self) -> tuple[float, float]:
        """The field's valid range; :func:`optimize` intersects it with ``bounds``."""
        return PHYSICAL_RANGE.get(self.field, (0.0, float("inf")))

    def write(self, z0: Tensor, params: Any, value: Tensor, sim: Any) -> tuple[Tensor, Any]:
        shape = self._value(sim.parameters()).shape  # the unbatched field
        S = value.shape[0]
        if self.index is None:
            if self.field in ("mu", "cor") and len(shape) == 0:
                shape = torch.Size([1])  # batched shared mu/cor is (S, 1); 1-D means per contact
            full = value.reshape(S, *shape)
        else:  # an indexed field is at least 1-D (bind checks the index)
            current = self._value(params).to(value)
            batched = current.shape == (S, *shape) and current.dim() > len(shape)
            full = (current if batched else current.expand(S, *shape)).clone()
            full[(slice(None), *_as_tuple(self.index))] = value.reshape(
                S, *torch.empty(shape)[self.index].shape
            )
        return z0, params.replace(**{self.field: full})


def _as_tuple(index: int | tuple[int, ...]) -> tuple[int, ...]:
    return index if isinstance(index, tuple) else (index,)
