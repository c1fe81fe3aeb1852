"""Projection onto one contact's feasible set, with its derivatives.

Each contact k owns the block ``f_k = (f_n, f_t)`` (``d`` numbers, ``f_t`` has
``d - 1``) and the closed convex set

    C_k = { f_n >= l_k,  ||f_t|| <= mu_k f_n }          (l_k >= 0, mu_k >= 0)

the friction cone of paper eq. (3) cut by the lower bound of eqs. (4)/(7).
The solution of the cone QP is the fixed point ``f = Pi_C(f - rho (A f + b))``
(the natural map); :mod:`diffcontact.contact.cone_qp` polishes and
differentiates through that equation, and needs ``Pi_C`` together with its
Jacobians with respect to ``z``, ``mu`` and ``l``, which this module provides
in closed form, region by region.

Regions (z = (z_n, z_t), s = ||z_t||, u = z_t / s):

- inside the cone (``s <= mu z_n``, mu > 0): ``Pi = z`` (a sticking contact);
- polar cone (``mu s <= -z_n``): ``Pi_K = 0`` (a separating contact);
- otherwise the cone surface: ``Pi = c (1, mu u)`` with
  ``c = (z_n + mu s) / (1 + mu^2)`` (a sliding contact);
- if the cone projection has ``f_n < l`` (or is the tip while ``l = 0``), the
  projection lies on the disk ``f_n = l, ||f_t|| <= mu l``: ``Pi = (l, z_t)``
  when ``s <= mu l``, else ``(l, mu l u)``.

One-sided choices where Pi is not differentiable (they define the gradients
at degenerate points; the values are continuous):

- the tip with ``l = 0`` takes the disk branch, so ``dPi/dl`` is the right
  derivative ``(1, mu u)`` (a separating contact pushed by a lower bound);
- ``mu = 0`` is never "inside": a pressing contact is sliding, and
  ``dPi/dmu`` is the right derivative ``(s, z_n u)``; with no slip (``s = 0``)
  the direction is undefined and the mu-gradient is taken as zero;
- ``z = 0`` exactly (zero impulse, zero velocity) counts as inside (sticking).
"""

from __future__ import annotations

import torch
from torch import Tensor


def project_contact_set(
    z: Tensor, mu: Tensor, lower: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Project every contact block onto its feasible set, with derivatives.

    Args:
        z: (..., K, d) points to project, blocks ``(z_n, z_t)``.
        mu: (..., K) friction coefficients, >= 0 (ignored when d == 1).
        lower: (..., K) lower bounds on the normal component, >= 0.

    Returns:
        proj: (..., K, d) the projections ``Pi(z)``.
        P: (..., K, d, d) Jacobians ``dPi/dz`` (symmetric).
        dmu: (..., K, d) ``dPi/dmu_k``.
        dl: (..., K, d) ``dPi/dl_k``.
    """
    d = z.shape[-1]
    zn = z[..., 0]
    zero = torch.zeros_like(zn)
    one = torch.ones_like(zn)
    eye = torch.eye(d, dtype=z.dtype, device=z.device).expand(*z.shape[:-1], d, d)

    if d == 1:
        use_disk = zn < lower
        proj = torch.where(use_disk, lower, zn).unsqueeze(-1)
        P = torch.where(use_disk, zero, one)[..., None, None]
        dl = torch.where(use_disk, one, zero).unsqueeze(-1)
        return proj, P, torch.zeros_like(dl), dl

    zt = z[..., 1:]
    s = torch.linalg.vector_norm(zt, dim=-1)
    positive = s > 0
    s_safe = torch.where(positive, s, one)
    u = torch.where(positive.unsqueeze(-1), zt / s_safe.unsqueeze(-1), torch.zeros_like(zt))
    uuT = u.unsqueeze(-1) * u.unsqueeze(-2)
    eye_t = eye[..., 1:, 1:]
    mu2 = mu * mu

    inside = (mu > 0) & (s <= mu * zn)
    polar = ~inside & (mu * s <= -zn)
    surface = ~inside & ~polar

    # cone surface branch (sliding)
    c = (zn + mu * s) / (1 + mu2)
    surf_proj = torch.cat([c.unsqueeze(-1), (c * mu).unsqueeze(-1) * u], dim=-1)
    P_surf = torch.empty_like(eye)
    P_surf[..., 0, 0] = 1 / (1 + mu2)
    P_surf[..., 0, 1:] = (mu / (1 + mu2)).unsqueeze(-1) * u
    P_surf[..., 1:, 0] = P_surf[..., 0, 1:]
    P_surf[..., 1:, 1:] = (mu2 / (1 + mu2))[..., None, None] * uuT + (c * mu / s_safe)[
        ..., None, None
    ] * (eye_t - uuT)
    dc_dmu = (s - 2 * mu * c) / (1 + mu2)
    dmu_surf = torch.cat([dc_dmu.unsqueeze(-1), (dc_dmu * mu + c).unsqueeze(-1) * u], dim=-1)

    cone_n = torch.where(inside, zn, torch.where(polar, zero, c))
    use_disk = (cone_n < lower) | (polar & (cone_n <= lower))

    # cone branches combined
    m_in = inside[..., None]
    m_pol = polar[..., None]
    cone_proj = torch.where(m_in, z, torch.where(m_pol, torch.zeros_like(z), surf_proj))
    cone_P = torch.where(m_in[..., None], eye, torch.where(m_pol[..., None], 0 * eye, P_surf))
    cone_dmu = torch.where(surface[..., None], dmu_surf, torch.zeros_like(z))

    # disk branch: f_n = l, f_t clipped to radius mu * l
    radius = mu * lower
    clipped = (s > radius) | (radius <= 0)
    disk_t = torch.where(clipped.unsqueeze(-1), radius.unsqueeze(-1) * u, zt)
    disk_proj = torch.cat([lower.unsqueeze(-1), disk_t], dim=-1)
    disk_P = torch.zeros_like(eye)
    disk_P[..., 1:, 1:] = torch.where(
        clipped[..., None, None], (radius / s_safe)[..., None, None] * (eye_t - uuT), eye_t
    )
    m_clip = clipped.unsqueeze(-1)
    disk_dl = torch.cat(
        [one.unsqueeze(-1), torch.where(m_clip, mu.unsqueeze(-1) * u, torch.zeros_like(zt))], -1
    )
    disk_dmu = torch.cat(
        [zero.unsqueeze(-1), torch.where(m_clip, lower.unsqueeze(-1) * u, torch.zeros_like(zt))],
        -1,
    )

    m_disk = use_disk.unsqueeze(-1)
    proj = torch.where(m_disk, disk_proj, cone_proj)
    P = torch.where(m_disk.unsqueeze(-1), disk_P, cone_P)
    dmu = torch.where(m_disk, disk_dmu, cone_dmu)
    dl = torch.where(m_disk, disk_dl, torch.zeros_like(z))
    return proj, P, dmu, dl
