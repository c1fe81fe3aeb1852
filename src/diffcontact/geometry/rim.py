"""Disk rim against a plane in 3D (the gyroscope with a wall).

A body is a free 3D extended body of 4 points: ``x0`` (centre of mass), then
``x0 + e1``, ``x0 + e2``, ``x0 + e3`` with ``e3`` the symmetry axis. Its rim is
the circle of radius ``R`` around ``x0`` in the plane normal to ``e3``. A plane
is ``n_w . p + c_w = 0`` with the allowed side ``> 0``.

The rim point closest to the plane is exact:
``p = x0 - R e / |e|`` with ``a = e3 / |e3|`` and ``e = n_w - (n_w . a) a``, so
``gap = n_w . p + c_w = n_w . x0 + c_w - R |e|``. When the disk is parallel to
the plane (``e ~ 0``) every rim point is closest; the body's ``e1`` direction
(made orthogonal to ``a``) is used then, so values and gradients stay finite.

Candidates are body-major, ``n_planes * i + j``. Contact space ``d = 3``:
``(n_w, t1, t2)`` with :func:`~diffcontact.geometry.frames.tangent_basis`
tangents (``t1 x t2 = n_w``). The normal row is ``D_x gap`` (on ``x0`` and
``x0 + e3``); the tangent rows are the tangential velocity of ``p`` as a
material point of the body (extended-body weights over its 4 points).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import ClassVar

import torch
from torch import Tensor

from diffcontact.fastops import dot_last

from .base import (
    GeometryBase,
    SparseJacobian,
    broadcast_batch,
    gather_points,
    unit_normal_planes,
)
from .frames import material_point_weights, safe_norm, safe_normalize, tangent_basis

__all__ = ["RimPlane", "closest_rim_point"]


def closest_rim_point(
    body_points: Tensor, radius: Tensor, normal: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Rim point of least ``normal . p`` and the pieces of its derivative.

    Args:
        body_points: ``(..., 4, 3)``: ``x0, x0 + e1, x0 + e2, x0 + e3``.
        radius: ``(...)`` rim radius ``R``.
        normal: ``(..., 3)`` unit plane normal ``n_w``.

    Returns:
        ``p (..., 3)``; ``u (..., 3)`` the unit direction with ``p = x0 - R u``;
        ``s (...)`` = ``n_w . a``; ``len_e3 (...)`` = ``|e3|``.
    """
    x0 = body_points[..., 0, :]
    e1 = body_points[..., 1, :] - x0
    e3 = body_points[..., 3, :] - x0
    a, len_e3 = safe_normalize(e3)
    s = dot_last(normal, a)
    e = normal - s.unsqueeze(-1) * a
    eps = 16.0 * float(torch.finfo(body_points.dtype).eps)
    len_e = safe_norm(e)
    regular = (len_e > eps).unsqueeze(-1)
    e1_perp = e1 - dot_last(e1, a).unsqueeze(-1) * a
    fallback, _ = safe_normalize(e1_perp)
    u = torch.where(regular, e / torch.where(regular, len_e.unsqueeze(-1), 1.0), fallback)
    p = x0 - radius.unsqueeze(-1) * u
    return p, u, s, len_e3


@dataclasses.dataclass(frozen=True, eq=False)
class RimPlane(GeometryBase):
    """Rim-plane candidates of 3D disks (body-major over planes).

    Attributes:
        body_points: ``(B, 4)`` long, each body's 4 points.
        radii: ``(B,)`` float64 rim radii.
        planes: ``(W, 4)`` float64 ``(n_w, c_w)`` with ``|n_w| = 1``.
    """

    body_points: Tensor
    radii: Tensor
    planes: Tensor

    d: ClassVar[int] = 3

    @classmethod
    def build(
        cls,
        first_points: Sequence[int] = (0,),
        radii: Sequence[float] = (0.3,),
        planes: Sequence[Sequence[float]] = ((0.0, 1.0, 0.0, 0.33),),
    ) -> RimPlane:
        """Candidates of every rim against every plane.

        Args:
            first_points: per body, the index of its centre point (its 4
                points are consecutive).
            radii: per body, the rim radius (gyroscope: 0.3).
            planes: ``[nx, ny, nz, c]`` with allowed side ``n . p + c > 0``
                (gyroscope: ``[0, 1, 0, 0.33]``, the wall ``y = -0.33``);
                normalised here.
        """
        starts = [int(s) for s in first_points]
        radii = [float(r) for r in radii]
        if len(starts) != len(radii):
            raise ValueError(f"got {len(starts)} bodies but {len(radii)} radii")
        if any(s < 0 for s in starts) or any(not r > 0 for r in radii):
            raise ValueError(f"need first points >= 0 and radii > 0, got {starts}, {radii}")
        w = torch.tensor([[float(v) for v in pl] for pl in planes], dtype=torch.float64)
        if w.ndim != 2 or w.shape[0] == 0 or w.shape[1] != 4:
            raise ValueError(f"planes must be [nx, ny, nz, c] rows, got shape {tuple(w.shape)}")
        if bool((w[:, :3] == 0).all(dim=-1).any()):
            raise ValueError(f"plane normals must be non-zero, got {w.tolist()}")
        w = unit_normal_planes(w, 3)
        body_points = torch.tensor(starts, dtype=torch.long)[:, None] + torch.arange(4)
        return cls(body_points, torch.tensor(radii, dtype=torch.float64), w)

    @property
    def n_planes(self) -> int:
        return int(self.planes.shape[0])

    @property
    def n_candidates(self) -> int:
        return int(self.radii.shape[0]) * self.n_planes

    def _closest(self, x: Tensor, body: Tensor, plane: Tensor):
        """Body points, plane rows and :func:`closest_rim_point` for candidate arrays."""
        pts = self.body_points.to(x.device)[body]  # (*B, Ka, 4)
        bpos = gather_points(x, pts)  # (*B, Ka, 4, 3)
        pl = self.planes.to(device=x.device, dtype=x.dtype)[plane]  # (*B, Ka, 4)
        r = self.radii.to(device=x.device, dtype=x.dtype)[body]
        return pts, bpos, pl, r, closest_rim_point(bpos, r, pl[..., :3])

    def gaps(self, x: Tensor) -> Tensor:
        """``n_w . p + c_w`` at the exact closest rim point.

        Args:
            x: ``(..., P, 3)``.

        Returns:
            ``(..., K)``, body-major.
        """
        k = torch.arange(self.n_candidates, device=x.device)
        idx = k.expand(*x.shape[:-2], -1)
        _, _, pl, _, (p, _, _, _) = self._closest(x, idx // self.n_planes, idx % self.n_planes)
        return dot_last(pl[..., :3], p) + pl[..., 3]

    def jacobian_sparse(self, x: Tensor, idx: Tensor) -> SparseJacobian:
        """Rows of candidates ``idx``.

        Args:
            x: ``(..., P, 3)``.
            idx: ``(..., Ka)`` long.

        Returns:
            ``points (..., Ka, 4)`` and ``values (..., Ka, 3, 4, 3)``.
        """
        x, idx = broadcast_batch(x, idx)
        pts, bpos, pl, r, (p, u, s, len_e3) = self._closest(
            x, idx // self.n_planes, idx % self.n_planes
        )
        n = pl[..., :3]
        # D gap / D x3 = R s u / |e3|, D gap / D x0 = n - that (x1, x2: none)
        g3 = (r * s / len_e3).unsqueeze(-1) * u
        zero = torch.zeros_like(g3)
        normal = torch.stack((n - g3, zero, zero, g3), dim=-2)  # (*B, Ka, 4, 3)
        w = material_point_weights(bpos, p)  # (*B, Ka, 4)
        tang = w[..., None, :, None] * tangent_basis(n).unsqueeze(-2)  # (*B, Ka, 2, 4, 3)
        return SparseJacobian(pts, torch.cat((normal.unsqueeze(-3), tang), dim=-3))
