"""Contact frames and extended-body material points.

Pure tensor functions, batched over any leading dims; device and dtype follow
the inputs.
"""

from __future__ import annotations

import torch
from torch import Tensor

from diffcontact.fastops import dot_last, spd_solve

__all__ = [
    "contact_frame",
    "material_point_weights",
    "safe_norm",
    "safe_normalize",
    "tangent_basis",
]


def _tiny(x: Tensor) -> float:
    """A length below which a vector counts as zero for ``x``'s dtype."""
    return float(torch.finfo(x.dtype).tiny) ** 0.5


def safe_norm(v: Tensor, eps: float | None = None) -> Tensor:
    """Euclidean norm over the last dim with a finite gradient at zero.

    Args:
        v: ``(..., dim)``.
        eps: lengths below ``eps`` are reported as ``eps`` (with zero gradient);
            default: the square root of the dtype's smallest normal number, so
            the value is exact for every vector that is not essentially zero.

    Returns:
        ``(...,)``.
    """
    eps = _tiny(v) if eps is None else eps
    return dot_last(v, v).clamp_min(eps * eps).sqrt()


def safe_normalize(
    v: Tensor, fallback: Tensor | None = None, eps: float | None = None
) -> tuple[Tensor, Tensor]:
    """Unit vector and length of ``v`` without NaN (value or gradient) at zero.

    Args:
        v: ``(..., dim)``.
        fallback: unit vector broadcastable to ``(..., dim)`` returned where
            ``|v| <= eps``; default the first coordinate axis.
        eps: degeneracy threshold (see :func:`safe_norm`).

    Returns:
        ``(unit (..., dim), norm (...,))``.
    """
    eps = _tiny(v) if eps is None else eps
    norm = safe_norm(v, eps)
    ok = (norm > eps).unsqueeze(-1)
    if fallback is None:
        fallback = torch.zeros_like(v)
        fallback[..., 0] = 1.0
    unit = torch.where(ok, v / norm.unsqueeze(-1), fallback)
    return unit, norm


def tangent_basis(n: Tensor) -> Tensor:
    """Deterministic orthonormal tangents of unit normals.

    2D: ``t = (-n_y, n_x)`` (the normal turned by +90 degrees).
    3D: the branch-free basis of Duff et al. (2017, "Building an orthonormal
    basis, revisited"), smooth except across ``n_z = 0`` sign flips, with
    ``t1 x t2 = n``.

    Args:
        n: unit normals ``(..., dim)``, dim 2 or 3.

    Returns:
        ``(..., dim - 1, dim)``: the tangent rows.
    """
    dim = n.shape[-1]
    if dim == 2:
        return torch.stack((-n[..., 1], n[..., 0]), dim=-1).unsqueeze(-2)
    if dim == 3:
        nx, ny, nz = n.unbind(-1)
        sign = torch.copysign(torch.ones_like(nz), nz)
        a = -1.0 / (sign + nz)
        b = nx * ny * a
        t1 = torch.stack((1.0 + sign * nx * nx * a, sign * b, -sign * nx), dim=-1)
        t2 = torch.stack((b, sign + ny * ny * a, -ny), dim=-1)
        return torch.stack((t1, t2), dim=-2)
    raise ValueError(f"tangent_basis: normals must be 2D or 3D, got last dim {dim}")


def contact_frame(n: Tensor) -> Tensor:
    """Contact frame rows ``(n, t...)`` of unit normals.

    Args:
        n: ``(..., dim)``.

    Returns:
        ``(..., dim, dim)``: row 0 is ``n``, rows 1.. are :func:`tangent_basis`.
    """
    return torch.cat((n.unsqueeze(-2), tangent_basis(n)), dim=-2)


def material_point_weights(body_points: Tensor, p: Tensor) -> Tensor:
    """Extended-body weights of the material point at world position ``p``.

    The body's points are ``x_0`` (centre of mass) and ``x_i = x_0 + e_i``.
    The body coordinates ``r`` solve ``p = x_0 + sum_i r_i e_i`` (least
    squares when ``k < dim``; the axes are orthonormal when the body's
    constraints hold), and the material point's velocity is
    ``sum_a c_a v_a`` with ``c = (1 - sum_i r_i, r_1, ..., r_k)``.

    Args:
        body_points: ``(..., k + 1, dim)``; ``k = 0`` is a point mass.
        p: ``(..., dim)``.

    Returns:
        ``c``: ``(..., k + 1)``; ``sum_a c_a x_a = p`` when ``p`` lies in the
        affine span of the body's points.
    """
    x0 = body_points[..., 0, :]
    axes = body_points[..., 1:, :] - x0.unsqueeze(-2)  # (..., k, dim)
    k = axes.shape[-2]
    if k == 0:
        return torch.ones_like(body_points[..., 0])
    gram = axes @ axes.transpose(-1, -2)  # (..., k, k)
    rhs = axes @ (p - x0).unsqueeze(-1)  # (..., k, 1)
    r = spd_solve(gram, rhs).squeeze(-1)  # (..., k); NaN for a degenerate body
    return torch.cat((1.0 - r.sum(-1, keepdim=True), r), dim=-1)
