"""Initial-condition distributions of the built-in system types (paper-facts.md).

Each ``draw_*`` function draws ``n`` candidate states ``(n, 2, P, dim)``
float64 on the CPU from a ``torch.Generator``; :func:`rejection_sample` keeps
drawing fixed-size chunks, keeps the valid ones (vectorised) and stops at
``n``. The draws depend only on the generator, so the same seed gives the
same bytes, and a request for ``n`` states returns the first ``n`` of any
larger request.

Layouts (point order of the state):

- ``bouncing_masses``: one point per body (its centre).
- ``bouncing_disks``: three points per body: centre, centre + body x axis,
  centre + body y axis (body x axis at the drawn angle).
- ``chain_pendulum``: one point per joint, joint i at the end of link i;
  absolute link angles q from straight down, ``x_i = x_{i-1} + l_i (sin q_i, -cos q_i)``.
- ``gyroscope``: 4 points ``[c, c + R e1, c + R e2, c + R e3]`` with the pivot
  at the origin, ``R = Rz(a) Rx(b) Rz(c)`` (intrinsic Z-X-Z Euler angles),
  the centre of mass ``c = R (0, 0, com_distance)`` and ``e3`` the symmetry
  axis; the world angular velocity is
  ``w = a' z + b' Rz(a) x + c' Rz(a) Rx(b) z`` and every point moves with ``w x p``.
- ``rope``: one point per mass, point k at the end of segment k (segment 0
  starts at the anchor); absolute segment angles from straight down are the
  first angle plus the cumulative sums of the relative angles; each
  segment's absolute angular velocity is drawn independently (as for the
  chain pendulum; rates of the relative angles would add up along the rope
  and whip the tip of a 100-point rope at ~50 m/s); segments start at their
  rest length.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from diffcontact.mechanics import chain_points_2d, disk_points_2d, rigid_body_points_3d
from diffcontact.systems.config import (
    BouncingDisksConfig,
    BouncingMassesConfig,
    ChainPendulumConfig,
    GyroscopeConfig,
    RopeConfig,
)

__all__ = [
    "draw_bouncing_disks",
    "draw_bouncing_masses",
    "draw_chain_pendulum",
    "draw_gyroscope",
    "draw_rope",
    "euler_zxz",
    "rejection_sample",
]

_F = torch.float64


def _uniform(shape: tuple[int, ...], low: float, high: float, gen: torch.Generator) -> Tensor:
    return low + (high - low) * torch.rand(shape, generator=gen, dtype=_F)


def _normal(shape: tuple[int, ...], std: float, gen: torch.Generator) -> Tensor:
    return std * torch.randn(shape, generator=gen, dtype=_F)


def draw_bouncing_masses(cfg: BouncingMassesConfig, n: int, gen: torch.Generator) -> Tensor:
    """Centres uniform in the box, velocities ``N(0, velocity_std^2)``: ``(n, 2, B, 2)``."""
    ic = cfg.initial_conditions
    B = cfg.n_bodies
    low = torch.tensor(ic.position_low, dtype=_F)
    high = torch.tensor(ic.position_high, dtype=_F)
    x = low + (high - low) * torch.rand((n, B, 2), generator=gen, dtype=_F)
    v = _normal((n, B, 2), ic.velocity_std, gen)
    return torch.stack([x, v], dim=1)


def draw_bouncing_disks(cfg: BouncingDisksConfig, n: int, gen: torch.Generator) -> Tensor:
    """As point masses plus angle ``U[0, 2 pi)`` and ``N(0, std^2)`` spin: ``(n, 2, 3B, 2)``."""
    ic = cfg.initial_conditions
    B = cfg.n_bodies
    centre, velocity = draw_bouncing_masses(cfg, n, gen).unbind(1)  # same draws, same order
    angle = _uniform((n, B), 0.0, 2 * math.pi, gen)
    omega = _normal((n, B), ic.angular_velocity_std, gen)
    z = disk_points_2d(centre, angle, velocity, omega)  # (n, B, 2, 3, 2)
    return z.transpose(1, 2).reshape(n, 2, 3 * B, 2)


def draw_chain_pendulum(cfg: ChainPendulumConfig, n: int, gen: torch.Generator) -> Tensor:
    """Absolute link angles uniform, rates ``N(0, std^2)``: ``(n, 2, L, 2)``."""
    ic = cfg.initial_conditions
    L = len(cfg.masses)
    q = _uniform((n, L), ic.angle_low, ic.angle_high, gen)
    qd = _normal((n, L), ic.angular_velocity_std, gen)
    lengths = torch.tensor(cfg.link_lengths, dtype=_F)
    pivot = torch.tensor(cfg.pivot, dtype=_F)
    return chain_points_2d(q, qd, lengths, pivot)


def _rot_z(a: Tensor) -> Tensor:
    c, s = torch.cos(a), torch.sin(a)
    o, z = torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([c, -s, z, s, c, z, z, z, o], dim=-1).unflatten(-1, (3, 3))


def _rot_x(a: Tensor) -> Tensor:
    c, s = torch.cos(a), torch.sin(a)
    o, z = torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([o, z, z, z, c, -s, z, s, c], dim=-1).unflatten(-1, (3, 3))


def euler_zxz(angles: Tensor, rates: Tensor) -> tuple[Tensor, Tensor]:
    """Rotation and world angular velocity from intrinsic Z-X-Z Euler angles.

    Args:
        angles: ``(..., 3)`` ``(a, b, c)``: ``R = Rz(a) Rx(b) Rz(c)``.
        rates: ``(..., 3)`` their time derivatives.

    Returns:
        ``R (..., 3, 3)`` (columns are the body axes in world coordinates) and
        ``omega (..., 3)`` ``= a' z + b' Rz(a) x + c' Rz(a) Rx(b) z``.
    """
    Rz1 = _rot_z(angles[..., 0])
    Rzx = Rz1 @ _rot_x(angles[..., 1])
    R = Rzx @ _rot_z(angles[..., 2])
    omega = (
        rates[..., 0:1] * torch.tensor([0.0, 0.0, 1.0], dtype=angles.dtype)
        + rates[..., 1:2] * Rz1[..., :, 0]
        + rates[..., 2:3] * Rzx[..., :, 2]
    )
    return R, omega


def draw_gyroscope(cfg: GyroscopeConfig, n: int, gen: torch.Generator) -> Tensor:
    """Euler angles and rates as in paper-facts.md: ``(n, 2, 4, 3)``.

    Angles uniform in ``(euler_low, euler_high)``; precession rate and nutation
    rate uniform in their ranges; spin ``+-spin_scale (spin_mean + N(0, spin_std^2))``
    with a random sign.
    """
    ic = cfg.initial_conditions
    angles = _uniform((n, 3), ic.euler_low, ic.euler_high, gen)
    precession = _uniform((n,), *ic.precession_rate_range, gen)
    nutation = _uniform((n,), *ic.nutation_rate_range, gen)
    sign = torch.where(torch.rand((n,), generator=gen, dtype=_F) < 0.5, -1.0, 1.0).to(_F)
    spin = sign * ic.spin_scale * (ic.spin_mean + _normal((n,), ic.spin_std, gen))
    R, omega = euler_zxz(angles, torch.stack([precession, nutation, spin], dim=-1))
    com = R[..., :, 2] * cfg.com_distance
    velocity = torch.linalg.cross(omega, com, dim=-1)
    return rigid_body_points_3d(com, R, velocity, omega)


def draw_rope(cfg: RopeConfig, n: int, gen: torch.Generator) -> Tensor:
    """Segment angles from the anchor: ``(n, 2, n_points, 2)``."""
    ic = cfg.initial_conditions
    P = cfg.n_points
    first = _uniform((n, 1), ic.first_angle_low, ic.first_angle_high, gen)
    rel = _uniform((n, P - 1), -cfg.max_angle, cfg.max_angle, gen)
    qd = _normal((n, P), ic.angular_velocity_std, gen)  # absolute segment rates
    q = torch.cumsum(torch.cat([first, rel], dim=-1), dim=-1)
    lengths = torch.full((P,), cfg.rest_length, dtype=_F)
    return chain_points_2d(q, qd, lengths, torch.tensor(cfg.anchor, dtype=_F))


DRAWERS: dict[str, Callable[..., Tensor]] = {
    "bouncing_masses": draw_bouncing_masses,
    "bouncing_disks": draw_bouncing_disks,
    "chain_pendulum": draw_chain_pendulum,
    "gyroscope": draw_gyroscope,
    "rope": draw_rope,
}


def rejection_sample(
    draw: Callable[[int, torch.Generator], Tensor],
    valid: Callable[[Tensor], Tensor],
    n: int,
    gen: torch.Generator,
    *,
    chunk: int = 1024,
    max_draws: int | None = None,
) -> Tensor:
    """Draw fixed-size chunks, keep the valid samples, repeat until ``n`` are kept.

    The chunk size does not depend on ``n``, so the candidate sequence is a
    function of the generator's seed alone: ``n`` samples are the first ``n``
    of any larger request with the same seed.

    Args:
        draw: ``(m, gen) -> (m, ...)`` candidate samples.
        valid: ``(m, ...) -> (m,)`` bool.
        n: number of samples wanted.
        gen: the generator.
        chunk: candidates per draw.
        max_draws: give up after this many candidates (default
            ``1_000_000 + 1000 n``); also give up after 100,000 without one valid.

    Returns:
        ``(n, ...)`` the first ``n`` valid samples in draw order.

    Raises:
        ValueError: when fewer than ``n`` valid samples were found in ``max_draws``.
    """
    max_draws = 1_000_000 + 1000 * n if max_draws is None else max_draws
    kept: list[Tensor] = []
    have, drawn = 0, 0
    while have < n:
        if drawn >= max_draws or (have == 0 and drawn >= 100_000):
            raise ValueError(
                f"could only draw {have} of {n} valid initial conditions in {drawn} tries "
                f"(acceptance rate {have / drawn:.2g}); widen the initial_conditions box "
                "or make the bodies smaller"
            )
        z = draw(chunk, gen)
        good = z[valid(z)]
        kept.append(good)
        have += good.shape[0]
        drawn += chunk
    return torch.cat(kept)[:n]
