"""Fixed-step integration of second-order dynamics: two fourth-order Runge-Kutta rules.

- ``rk4``: the classic rule (weights 1/6, 1/3, 1/3, 1/6, nodes 0, 1/2, 1/2, 1);
- ``rk4_38``: Kutta's 3/8 rule (weights 1/8, 3/8, 3/8, 1/8, nodes 0, 1/3, 2/3, 1), which
  is what torchdiffeq's ``method="rk4"`` computes (and so the paper's released
  simulator); its stages are written in torchdiffeq's order of operations so that
  trajectories agree with it to rounding.

Both are fourth order; they differ in the error constant, so trajectories differ at
the level of the truncation error (and chaotic systems amplify that).
"""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor

__all__ = ["INTEGRATORS", "VectorField", "rk4_38_step", "rk4_step"]

VectorField = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]
"""``(x, v) -> (x_dot, v_dot)``, all ``(..., P, dim)``."""


def _step_size(dt: float | Tensor) -> float | Tensor:
    if isinstance(dt, Tensor) and dt.dim() > 0:
        return dt[..., None, None]
    return dt


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
    dt = _step_size(dt)
    half = 0.5 * dt
    k1x, k1v = vector_field(x, v)
    k2x, k2v = vector_field(x + half * k1x, v + half * k1v)
    k3x, k3v = vector_field(x + half * k2x, v + half * k2v)
    k4x, k4v = vector_field(x + dt * k3x, v + dt * k3v)
    sixth = dt / 6.0
    x_next = x + sixth * (k1x + 2.0 * k2x + 2.0 * k3x + k4x)
    v_next = v + sixth * (k1v + 2.0 * k2v + 2.0 * k3v + k4v)
    return x_next, v_next


def rk4_38_step(
    vector_field: VectorField, x: Tensor, v: Tensor, dt: float | Tensor
) -> tuple[Tensor, Tensor]:
    """One step of Kutta's 3/8-rule fourth-order Runge-Kutta method (torchdiffeq's "rk4").

    Stages ``k1 = F(y)``, ``k2 = F(y + dt k1 / 3)``, ``k3 = F(y + dt (k2 - k1 / 3))``,
    ``k4 = F(y + dt (k1 - k2 + k3))``; ``y+ = y + (k1 + 3 (k2 + k3) + k4) dt / 8``.
    Arguments and result as :func:`rk4_step`.
    """
    dt = _step_size(dt)
    third = 1.0 / 3.0
    k1x, k1v = vector_field(x, v)
    k2x, k2v = vector_field(x + dt * k1x * third, v + dt * k1v * third)
    k3x, k3v = vector_field(x + dt * (k2x - k1x * third), v + dt * (k2v - k1v * third))
    k4x, k4v = vector_field(x + dt * (k1x - k2x + k3x), v + dt * (k1v - k2v + k3v))
    x_next = x + (k1x + 3 * (k2x + k3x) + k4x) * dt * 0.125
    v_next = v + (k1v + 3 * (k2v + k3v) + k4v) * dt * 0.125
    return x_next, v_next


INTEGRATORS: dict[str, Callable[..., tuple[Tensor, Tensor]]] = {
    "rk4": rk4_step,
    "rk4_38": rk4_38_step,
}
"""The config key ``integrator``'s choices: name -> step function."""
