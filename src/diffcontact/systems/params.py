"""``PhysicalParams``: the physical parameters of a system, as an immutable argument.

``System.simulate(z0, steps, params=p)`` is a pure function of ``z0`` and
``p``: nothing is written into the system. A learned model builds its
``PhysicalParams`` from its modules on every call; a robustness sweep or a
controller builds them with :meth:`PhysicalParams.replace`.

Every tensor field has an *unbatched* shape (one set for all trajectories)
and may carry one extra leading dimension ``N`` equal to the batch size of
``z0`` (one set per trajectory):

============== ================= =====================
field          unbatched         batched
============== ================= =====================
mass           ``(B,)``          ``(N, B)``
second_moments ``(B, k)``        ``(N, B, k)``
mu, cor        ``(K,)`` or ``()`` ``(N, K)`` or ``(N, 1)``
gravity        ``()``            ``(N,)``
stiffness      ``()``            ``(N,)``
rest_length    ``()``            ``(N,)``
eps            ``()``            ``(N,)``
============== ================= =====================

(B bodies, k axes per rigid body, K candidate contacts.) Shared values are
broadcast with ``expand``, so the gradient of a parameter shared across the
batch is the sum over trajectories.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

__all__ = ["PhysicalParams"]

_UNBATCHED_DIMS = {
    "mass": 1,
    "second_moments": 2,
    "mu": 1,
    "cor": 1,
    "gravity": 0,
    "stiffness": 0,
    "rest_length": 0,
    "eps": 0,
}


@dataclass(frozen=True)
class PhysicalParams:
    """Physical parameters of a :class:`~diffcontact.systems.System` (see the module doc).

    Attributes:
        mass: masses of the bodies.
        second_moments: second moments per unit mass along the body axes
            (rigid bodies), or ``None`` (point masses).
        mu: friction coefficients, one per candidate contact (or one shared).
        cor: Poisson's coefficients of restitution e_P in [0, 1], likewise.
        gravity: magnitude of gravity, >= 0 (along -y in 2D, -z in 3D).
        stiffness: the rope's segment-spring stiffness, or ``None``.
        rest_length: the rope's segment rest length, or ``None``.
        eps: CMr's regulariser (used by contact models that have one).
        potential: an extra potential ``V(x): (..., P, dim) -> (...)`` added
            to the built-in terms (e.g. a learned network), or ``None``.
    """

    mass: Tensor
    second_moments: Tensor | None
    mu: Tensor
    cor: Tensor
    gravity: Tensor
    stiffness: Tensor | None = None
    rest_length: Tensor | None = None
    eps: Tensor | float = 0.01
    potential: Callable[[Tensor], Tensor] | None = None

    def replace(self, **changes: Any) -> PhysicalParams:
        """A copy with some fields changed (numbers become float64 tensors)."""
        unknown = set(changes) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise ValueError(
                f"PhysicalParams has no field(s) {sorted(unknown)}; fields: "
                f"{', '.join(f.name for f in dataclasses.fields(self))}"
            )
        for name, value in changes.items():
            if name in _UNBATCHED_DIMS and isinstance(value, bool):  # (True had become 1.0)
                raise ValueError(f"{name} must be a number or a tensor, got {value!r}")
            if name in _UNBATCHED_DIMS and isinstance(value, (int, float)) and name != "eps":
                changes[name] = torch.tensor(float(value), dtype=torch.float64)
        return dataclasses.replace(self, **changes)

    def tensors(self) -> dict[str, Tensor]:
        """The tensor fields by name (``None`` ones and ``potential`` left out)."""
        out = {}
        for name in _UNBATCHED_DIMS:
            value = getattr(self, name)
            if isinstance(value, Tensor):
                out[name] = value
        return out

    def batch_size(self) -> int | None:
        """``N`` when some field carries a batch dimension, else ``None``.

        Raises:
            ValueError: batched fields with different ``N``.
        """
        sizes = {
            name: int(t.shape[0])
            for name, t in self.tensors().items()
            if t.dim() == _UNBATCHED_DIMS[name] + 1 and not (name in ("mu", "cor") and t.dim() == 1)
        }
        if len(set(sizes.values())) > 1:
            raise ValueError(f"batched parameters disagree on the batch size: {sizes}")
        return next(iter(sizes.values()), None)

    def validate(
        self,
        *,
        n_bodies: int,
        n_contacts: int,
        axes: int | None,
        rope: bool,
        n_states: int | None = None,
    ) -> None:
        """Check shapes, finiteness and ranges; a ``ValueError`` names the problem.

        Args:
            n_bodies: B.
            n_contacts: K.
            axes: k for rigid bodies, ``None`` for point masses.
            rope: whether ``stiffness`` and ``rest_length`` are required.
            n_states: the batch size ``N`` of the states simulated (batched
                fields must match it).
        """
        B, K = n_bodies, n_contacts
        shapes: dict[str, list[tuple[int, ...]]] = {
            "mass": [(B,)],
            "second_moments": [(B, axes)] if axes is not None else [],
            "mu": [(K,), (), (1,)],
            "cor": [(K,), (), (1,)],
            "gravity": [()],
            "stiffness": [()] if rope else [],
            "rest_length": [()] if rope else [],
            "eps": [()],
        }
        meaning = {"mass": "one per body", "second_moments": "one per body and axis"}
        checks: list[tuple[str, Tensor, Tensor, str]] = []  # name, value, bad entries, range
        for name, allowed in shapes.items():
            value = getattr(self, name)
            if not allowed:
                if value is not None:
                    raise ValueError(f"{name} does not apply to this system; pass None")
                continue
            if name == "eps" and isinstance(value, (int, float)):
                value = torch.tensor(float(value), dtype=torch.float64)
            if not isinstance(value, Tensor) or not value.is_floating_point():
                raise ValueError(
                    f"{name} must be a floating-point tensor, got {type(value).__name__}"
                    + (f" of {value.dtype}" if isinstance(value, Tensor) else "")
                )
            if value.is_meta or value.layout != torch.strided:  # (.item() failed on meta)
                raise ValueError(
                    f"{name} must be a dense tensor with values, got a "
                    f"{'meta' if value.is_meta else str(value.layout)} tensor"
                )
            shape = tuple(value.shape)
            batched_ok = [(n_states, *s) for s in allowed if n_states is not None]
            if name in ("mu", "cor") and n_states is not None:
                batched_ok = [(n_states, K), (n_states, 1)]
            if shape not in allowed and shape not in batched_ok:
                batch = f", or {batched_ok[0]} (one set per trajectory)" if batched_ok else ""
                if name in ("mu", "cor"):
                    want = f"be one number or have shape ({K},) (one per contact)"
                else:
                    want = f"have shape {allowed[0]}"
                    want += f" ({meaning[name]})" if name in meaning else ""
                raise ValueError(f"{name} must {want}{batch}; got shape {shape}")
            t = value.detach()
            low, high, rng = {
                "mass": (0.0, math.inf, "positive"),
                "second_moments": (0.0, math.inf, "positive"),
                "rest_length": (0.0, math.inf, "positive"),
                "eps": (0.0, math.inf, "positive"),
                "mu": (0.0, math.inf, ">= 0"),
                "stiffness": (0.0, math.inf, ">= 0"),
                # a magnitude along the fixed direction -y (-z in 3D), as in the config
                "gravity": (0.0, math.inf, ">= 0"),
                "cor": (0.0, 1.0, "in [0, 1]"),
            }[name]
            strict = rng == "positive"
            bad = (t <= low) if strict else (t < low)
            bad = bad | (t > high) | ~torch.isfinite(t)
            checks.append((name, t, bad, rng))
        # one read of the device per device (a training step validates its parameters in
        # every rollout; on CUDA each read waits for the queued work), the messages only
        # when a check fails
        flags: dict[torch.device, list[Tensor]] = {}
        for _, t, bad, _ in checks:
            flags.setdefault(t.device, []).append(bad.any())
        if not any(bool(torch.stack(f).any()) for f in flags.values()):
            checks = []
        for name, t, bad, rng in checks:
            if not bool(torch.isfinite(t).all()):
                raise ValueError(f"{name} contains NaN or infinite values: {_short(t)}")
            if bool(bad.any()):
                raise ValueError(f"{name} must be {rng}, got {_short(t)}")
        if self.potential is not None and not callable(self.potential):
            raise ValueError(f"potential must be callable, got {type(self.potential).__name__}")


def _short(t: Tensor) -> str:
    values = t.flatten().tolist()
    text = ", ".join(f"{v:.6g}" for v in values[:8])
    return f"[{text}{', ...' if len(values) > 8 else ''}]" if t.dim() else text
