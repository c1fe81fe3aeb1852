"""Extended bodies: point sets with a constant mass matrix over points.

A body is a set of consecutive Cartesian points (see ``docs/conventions.md``):
a point mass is 1 point; a 2D rigid body is 3 points (centre of mass, centre +
body x axis, centre + body y axis); a free 3D rigid body is 4 points (centre
of mass, then centre + each unit body axis). Its mass matrix over points,
acting identically on every spatial coordinate, is

    M_body = m * [[1 + sum(s), -s^T], [-s, diag(s)]]

with ``s`` the second moments of the mass distribution along the body axes
per unit mass (a uniform disk of radius r has s = (r^2/4, r^2/4)). Full
matrices over flattened point-major coordinates (index ``p * dim + c``) are
``kron(M, I_dim)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "assemble_mass_matrix",
    "block_diagonal",
    "body_inverse_mass_matrix",
    "body_mass_matrix",
    "chain_points_2d",
    "disk_points_2d",
    "kinetic_energy",
    "kron_identity",
    "quaternion_to_matrix",
    "rigid_body_points_3d",
]


def _check_body_args(mass: Tensor, second_moments: Tensor) -> None:
    if second_moments.dim() < 1:
        raise ValueError(
            "second_moments must have shape (..., k) with k = number of body axes "
            f"(0 for a point mass); got a tensor of shape {tuple(second_moments.shape)}"
        )


def body_mass_matrix(mass: Tensor, second_moments: Tensor) -> Tensor:
    """Mass matrix over the k + 1 points of one extended body.

    Args:
        mass: ``(...)`` total mass m of the body.
        second_moments: ``(..., k)`` second moments s of the mass distribution
            along the body axes, per unit mass (k = 0 for a point mass, 2 for a
            2D rigid body, 3 for a 3D rigid body).

    Returns:
        ``(..., k+1, k+1)``: ``m * [[1 + sum(s), -s^T], [-s, diag(s)]]``; ``[[m]]``
        when k = 0. Batch dims of ``mass`` and ``second_moments`` broadcast.
    """
    _check_body_args(mass, second_moments)
    s = second_moments
    top_left = (1.0 + s.sum(-1))[..., None, None]
    top = torch.cat([top_left, -s[..., None, :]], dim=-1)
    bottom = torch.cat([-s[..., :, None], torch.diag_embed(s)], dim=-1)
    return mass[..., None, None] * torch.cat([top, bottom], dim=-2)


def body_inverse_mass_matrix(mass: Tensor, second_moments: Tensor) -> Tensor:
    """Closed-form inverse of :func:`body_mass_matrix`.

    ``M_body = m B^T diag(1, s) B`` with ``B = [[1, 0], [-1, I]]`` (the rows give
    the centre velocity and the axis velocities relative to it), so

        M_body^-1 = (1 / m) * [[1, 1^T], [1, 1 1^T + diag(1 / s)]].

    Args:
        mass: ``(...)`` total mass (positive).
        second_moments: ``(..., k)`` second moments per unit mass (positive).

    Returns:
        ``(..., k+1, k+1)`` inverse mass matrix of the body.
    """
    _check_body_args(mass, second_moments)
    s = second_moments
    k = s.shape[-1]
    ones = torch.ones((*s.shape[:-1], k + 1, k + 1), dtype=s.dtype, device=s.device)
    inv_s = F.pad(torch.diag_embed(1.0 / s), (1, 0, 1, 0))
    return (ones + inv_s) / mass[..., None, None]


def assemble_mass_matrix(blocks: Sequence[Tensor]) -> Tensor:
    """Block-diagonal mass matrix over all points from per-body blocks.

    Args:
        blocks: per-body ``(..., n_i, n_i)`` matrices in body order (batch dims
            broadcast against each other).

    Returns:
        ``(..., P, P)`` with ``P = sum(n_i)``; differentiable in every block.
    """
    if len(blocks) == 0:
        raise ValueError("assemble_mass_matrix needs at least one body block")
    for i, b in enumerate(blocks):
        if b.dim() < 2 or b.shape[-1] != b.shape[-2]:
            raise ValueError(f"block {i} must be square (..., n, n); got {tuple(b.shape)}")
    batch = torch.broadcast_shapes(*(b.shape[:-2] for b in blocks))
    total = sum(b.shape[-1] for b in blocks)
    rows = []
    offset = 0
    for b in blocks:
        n = b.shape[-1]
        b = b.expand(*batch, n, n)
        rows.append(F.pad(b, (offset, total - offset - n)))
        offset += n
    return torch.cat(rows, dim=-2)


def block_diagonal(blocks: Tensor) -> Tensor:
    """The block-diagonal matrix of a stack of equal blocks.

    Args:
        blocks: ``(..., B, m, k)``, block ``b`` at rows ``b m .. (b + 1) m`` and columns
            ``b k .. (b + 1) k``.

    Returns:
        ``(..., B m, B k)``; differentiable (one broadcast product with the identity).
    """
    B, m, k = blocks.shape[-3:]
    eye = torch.eye(B, dtype=blocks.dtype, device=blocks.device).view(B, 1, B, 1)
    return (blocks.unsqueeze(-2) * eye).reshape(*blocks.shape[:-3], B * m, B * k)


def kron_identity(M: Tensor, dim: int) -> Tensor:
    """Lift a matrix over points to flattened point-major coordinates.

    Args:
        M: ``(..., P, Q)`` matrix over points.
        dim: spatial dimension.

    Returns:
        ``(..., P*dim, Q*dim)`` equal to ``kron(M, I_dim)``: entry
        ``[p*dim + c, q*dim + c'] = M[p, q] * delta(c, c')``.
    """
    eye = torch.eye(dim, dtype=M.dtype, device=M.device)
    P, Q = M.shape[-2:]
    full = M[..., :, None, :, None] * eye[:, None, :]
    return full.reshape(*M.shape[:-2], P * dim, Q * dim)


def kinetic_energy(v: Tensor, M: Tensor) -> Tensor:
    """Kinetic energy ``0.5 * sum_c v[:, c]^T M v[:, c]``.

    Args:
        v: ``(..., P, dim)`` point velocities.
        M: ``(P, P)`` or ``(..., P, P)`` mass matrix over points.

    Returns:
        ``(...)`` kinetic energy.
    """
    return 0.5 * (v * (M @ v)).sum(dim=(-2, -1))


def disk_points_2d(
    centre: Tensor, angle: Tensor, velocity: Tensor, angular_velocity: Tensor
) -> Tensor:
    """State of a 2D rigid body as 3 points (centre, centre + e_x, centre + e_y).

    Args:
        centre: ``(..., 2)`` centre of mass.
        angle: ``(...)`` orientation; body x axis ``e_x = (cos a, sin a)``,
            body y axis ``e_y = (-sin a, cos a)``.
        velocity: ``(..., 2)`` centre-of-mass velocity.
        angular_velocity: ``(...)`` counter-clockwise angular velocity w.

    Returns:
        ``(..., 2, 3, 2)``: positions then velocities of the 3 points; axis
        point i moves with ``velocity + w x e_i`` (``v + w e_y`` and ``v - w e_x``).
    """
    batch = torch.broadcast_shapes(
        centre.shape[:-1], angle.shape, velocity.shape[:-1], angular_velocity.shape
    )
    centre = centre.expand(*batch, 2)
    velocity = velocity.expand(*batch, 2)
    angle = angle.expand(batch)
    w = angular_velocity.expand(batch)[..., None]
    cos, sin = torch.cos(angle), torch.sin(angle)
    e_x = torch.stack([cos, sin], dim=-1)
    e_y = torch.stack([-sin, cos], dim=-1)
    x = torch.stack([centre, centre + e_x, centre + e_y], dim=-2)
    v = torch.stack([velocity, velocity + w * e_y, velocity - w * e_x], dim=-2)
    return torch.stack([x, v], dim=-3)


def quaternion_to_matrix(quaternion: Tensor) -> Tensor:
    """Rotation matrix of a unit quaternion ``(w, x, y, z)`` (scalar first, as MuJoCo).

    Args:
        quaternion: ``(..., 4)`` unit quaternions (normalised here; ``q`` and ``-q`` give
            the same rotation).

    Returns:
        ``(..., 3, 3)`` rotation matrices whose columns are the body axes in world
        coordinates (``R @ r`` maps body coordinates ``r`` to the world).
    """
    q = quaternion / torch.linalg.vector_norm(quaternion, dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).unflatten(-1, (3, 3))


def rigid_body_points_3d(centre: Tensor, R: Tensor, velocity: Tensor, omega: Tensor) -> Tensor:
    """State of a free 3D rigid body as 4 points (centre, centre + each body axis).

    Args:
        centre: ``(..., 3)`` centre of mass.
        R: ``(..., 3, 3)`` rotation matrix whose columns are the body axes in
            world coordinates.
        velocity: ``(..., 3)`` centre-of-mass velocity.
        omega: ``(..., 3)`` angular velocity in world coordinates.

    Returns:
        ``(..., 2, 4, 3)``: positions then velocities; axis point i has position
        ``centre + R[:, i]`` and velocity ``velocity + omega x R[:, i]``.
    """
    batch = torch.broadcast_shapes(
        centre.shape[:-1], R.shape[:-2], velocity.shape[:-1], omega.shape[:-1]
    )
    axes = R.expand(*batch, 3, 3).transpose(-1, -2)  # rows are body axes
    centre = centre.expand(*batch, 3)[..., None, :]
    velocity = velocity.expand(*batch, 3)[..., None, :]
    omega = omega.expand(*batch, 3)[..., None, :].expand_as(axes)
    x = torch.cat([centre, centre + axes], dim=-2)
    v = torch.cat([velocity, velocity + torch.linalg.cross(omega, axes, dim=-1)], dim=-2)
    return torch.stack([x, v], dim=-3)


def chain_points_2d(
    angles: Tensor,
    angular_velocities: Tensor,
    link_lengths: Tensor,
    pivot: Tensor | None = None,
) -> Tensor:
    """State of a planar chain pendulum with point masses at the joints.

    Link i runs from joint i-1 (the pivot for i = 0) to joint i, at the
    absolute angle ``q_i`` measured from straight down:
    ``x_i = x_{i-1} + l_i * (sin q_i, -cos q_i)``.

    Args:
        angles: ``(..., n)`` absolute link angles q.
        angular_velocities: ``(..., n)`` their rates.
        link_lengths: ``(n,)`` or ``(..., n)`` link lengths.
        pivot: ``(2,)`` or ``(..., 2)`` fixed pivot; the origin when ``None``.

    Returns:
        ``(..., 2, n, 2)``: positions then velocities of the n joints.
    """
    sin, cos = torch.sin(angles), torch.cos(angles)
    offsets = link_lengths[..., None] * torch.stack([sin, -cos], dim=-1)
    rates = (link_lengths * angular_velocities)[..., None] * torch.stack([cos, sin], dim=-1)
    x = torch.cumsum(offsets, dim=-2)
    if pivot is not None:
        x = x + pivot[..., None, :]
    v = torch.cumsum(rates, dim=-2)
    x, v = torch.broadcast_tensors(x, v)
    return torch.stack([x, v], dim=-3)
