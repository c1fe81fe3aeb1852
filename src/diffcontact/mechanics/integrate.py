"""Fixed-step integration of second-order dynamics."""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor

__all__ = ["VectorField", "rk4_step"]

VectorField = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]
"""``(x, v) -> (x_dot, v_dot)``, all ``(..., P, dim)``."""


def rk4_step(
    vector_field: VectorField, x: Tensor, v: Tensor, dt: float | Tensor
) -> tuple[Tensor, Tensor]:
    """One classic fourth-order Runge-Kutta step of ``(x, v)``.

    Args:
        vector_field: ``(x, v) -> (x_dot, v_dot)``.
        x: ``(..., P, dim)`` positions.
        v: ``(..., P, dim)`` velocities.
        dt: step, a number or a tensor of shape ``()`` or ``(...)`` (one step
            per batch element).

    Returns:
        ``(x_next, v_next)``, each ``(..., P, dim)``.
    """
    if isinstance(dt, Tensor) and dt.dim() > 0:
        dt = dt[..., None, None]
    half = 0.5 * dt
    k1x, k1v = vector_field(x, v)
    k2x, k2v = vector_field(x + half * k1x, v + half * k1v)
    k3x, k3v = vector_field(x + half * k2x, v + half * k2v)
    k4x, k4v = vector_field(x + dt * k3x, v + dt * k3v)
    sixth = dt / 6.0
    x_next = x + sixth * (k1x + 2.0 * k2x + 2.0 * k3x + k4x)
    v_next = v + sixth * (k1v + 2.0 * k2v + 2.0 * k3v + k4v)
    return x_next, v_next
