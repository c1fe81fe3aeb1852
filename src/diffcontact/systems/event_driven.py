"""An exact event-driven simulator of one point mass among walls, with Coulomb friction.

Reference data for contact models (``docs/results.md``, "Exact Coulomb friction"): a
``bouncing_masses`` system with **one** body and any number of walls, under its
gravity. Between impacts the motion is the closed-form parabola (a straight line
without gravity); impact times are the roots of each wall's quadratic gap, found
exactly; at an impact with wall normal ``n``

    v_n -> -e v_n,        v_t -> v_t * max(0, 1 - mu (1 + e) |v_n| / |v_t|),

the textbook result of Coulomb friction with Poisson's (for a point mass also
Newton's) restitution, integrated over the impact. Nothing is discretised: states are
sampled every ``dt``, and the impacts fall between samples where they happen.

It is not a ``System.simulate`` (that one is time-stepping: an impact is resolved at
the end of the step in which the gap became negative); the two differ by where the
positions are after an impact within a step, not by the velocities' rule.

Limits: one body (no body-body impacts); a resting contact (a ball that comes to rest
on a wall under gravity: infinitely many impacts in finite time) is not modelled and
raises ``ValueError``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from diffcontact.geometry.base import unit_normal_planes
from diffcontact.systems.system import System

__all__ = ["simulate_event_driven"]

MAX_EVENTS_PER_STEP = 64


def _first_impact(
    x: Tensor, v: Tensor, g: Tensor, walls: Tensor, r: float
) -> tuple[Tensor, Tensor]:
    """Earliest time ``t >= 0`` (inf: none) at which the point hits a wall approaching it,
    and which wall. ``x, v: (N, 2)``, ``g: (2,)``, ``walls: (W, 3)`` unit normals."""
    n, c = walls[:, :2], walls[:, 2]
    gap = x @ n.T + c - r  # (N, W)
    vn = v @ n.T
    a = 0.5 * (n @ g)  # (W,)
    a = a.expand_as(gap)
    inf = torch.full_like(gap, torch.inf)
    # linear case
    t_lin = torch.where(vn < 0, -gap / torch.where(vn < 0, vn, -1.0), inf)
    # quadratic a t^2 + vn t + gap = 0, stable roots
    disc = vn * vn - 4 * a * gap
    sq = torch.sqrt(disc.clamp_min(0))
    q = -0.5 * (vn + torch.where(vn >= 0, sq, -sq))
    q_safe = torch.where(q == 0, 1.0, q)
    a_safe = torch.where(a == 0, 1.0, a)
    r1, r2 = q / a_safe, gap / q_safe
    roots = torch.stack([r1, r2], -1)
    approaching = (vn.unsqueeze(-1) + 2 * a.unsqueeze(-1) * roots) < 0
    ok = (disc.unsqueeze(-1) >= 0) & (roots >= 0) & approaching & (q != 0).unsqueeze(-1)
    t_quad = torch.where(ok, roots, torch.inf).amin(-1)
    t = torch.where(a.abs() > 0, t_quad, t_lin)
    t = torch.where(gap < 0, torch.where(vn < 0, 0.0, inf), t)  # inside a wall: hit now
    t_min, wall = t.min(-1)
    return t_min, wall


def simulate_event_driven(system: System, z0: Tensor, steps: int | None = None) -> Tensor:
    """Roll out one point mass among walls exactly (Coulomb friction, restitution e).

    Args:
        system: a ``bouncing_masses`` :class:`~diffcontact.systems.System` with one body;
            its walls, radius, gravity and the per-wall ``mu`` and ``cor`` are used.
        z0: ``(N, 2, 1, 2)`` initial states (positions then velocities).
        steps: number of ``dt`` intervals (default: ``system.default_steps``).

    Returns:
        ``(N, steps + 1, 2, 1, 2)`` float64 (on ``z0``'s device), sampled every ``dt``;
        the layout of ``System.simulate`` (and of ``dataset_from_arrays``).

    Raises:
        ValueError: a system that is not one point mass among walls, a bad ``z0``, or
            more than :data:`MAX_EVENTS_PER_STEP` impacts within one step (a resting
            contact).
    """
    if system.type != "bouncing_masses" or system.n_points != 1:
        raise ValueError(
            "simulate_event_driven needs a bouncing_masses system with one body, got "
            f"{system.type} with {system.n_points} points"
        )
    walls_l = system.config.walls
    if not walls_l:
        raise ValueError("simulate_event_driven: the system has no walls")
    if not isinstance(z0, Tensor) or z0.dim() != 4 or tuple(z0.shape[1:]) != (2, 1, 2):
        raise ValueError(f"z0 must have shape (N, 2, 1, 2), got {getattr(z0, 'shape', z0)}")
    steps = system.default_steps if steps is None else steps
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 0:
        raise ValueError(f"steps must be a non-negative integer, got {steps!r}")
    dev = z0.device
    f64 = torch.float64
    walls = torch.tensor(walls_l, dtype=f64, device=dev)
    walls = unit_normal_planes(walls, 2)  # unit normals, as the geometry
    mu = system.mu.to(dev, f64)
    cor = system.cor.to(dev, f64)
    r = float(system.config.radii[0])
    g = torch.tensor([0.0, -float(system.config.gravity)], dtype=f64, device=dev)
    dt = float(system.dt)
    x, v = z0[:, 0, 0].to(f64).clone(), z0[:, 1, 0].to(f64).clone()
    out = [torch.stack([x, v], 1)]
    for _ in range(steps):
        left = torch.full_like(x[:, 0], dt)  # time left in this interval
        for _event in range(MAX_EVENTS_PER_STEP + 1):
            t, w = _first_impact(x, v, g, walls, r)
            hit = t <= left
            tau = torch.where(hit, t, left)[:, None]
            x = x + v * tau + 0.5 * g * tau * tau
            v = v + g * tau
            left = left - tau[:, 0]
            if not bool(hit.any()):
                break
            if _event == MAX_EVENTS_PER_STEP:
                raise ValueError(
                    f"simulate_event_driven: more than {MAX_EVENTS_PER_STEP} impacts within one "
                    "step (a ball coming to rest on a wall): resting contact is not modelled"
                )
            n = walls[w, :2]
            vn = (v * n).sum(-1, keepdim=True)
            vt = v - vn * n
            speed = vt.norm(dim=-1, keepdim=True)
            e, m = cor[w][:, None], mu[w][:, None]
            slip = (speed - m * (1 + e) * vn.abs()).clamp_min(0)
            vt_new = torch.where(speed > 0, vt * slip / torch.where(speed > 0, speed, 1), vt)
            v = torch.where((hit[:, None]) & (vn < 0), -e * vn * n + vt_new, v)
        gap = x @ walls[:, :2].T + walls[:, 2] - r
        if bool((gap < -1e-9 * max(r, 1.0)).any()):
            raise ValueError(
                "simulate_event_driven: a body ended inside a wall (a ball coming to rest on "
                "a wall under gravity): resting contact is not modelled"
            )
        out.append(torch.stack([x, v], 1))
    return torch.stack(out, 1).unsqueeze(-2)
