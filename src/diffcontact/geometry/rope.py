"""Rope limits in 2D as one-row contacts (``d = 1``).

A rope of ``P`` points hangs from a fixed anchor (not a state point): segment
``k`` runs from point ``k - 1`` to point ``k``, segment 0 from the anchor to
point 0. Limits, numbered as in paper-facts.md (bending first):

- bending at joint ``k = 0 .. P-2`` (point ``k``, between segments ``k`` and
  ``k + 1``): ``gap = max_angle - |theta|`` with ``theta`` the signed angle
  from segment ``k`` to segment ``k + 1``;
- stretch of segment ``k = 0 .. P-1``:
  ``gap = min(len - min_ratio l0, max_ratio l0 - len)``.

The single ``J_C`` row is ``D_x gap`` of the active side (``theta >= 0`` counts
as the positive side; a stretch tie counts as the lower limit).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from typing import ClassVar

import torch
from torch import Tensor

from diffcontact.fastops import dot_last

from .base import ContactGeometry, GeometryBase, SparseJacobian, broadcast_batch, gather_points
from .frames import safe_norm, safe_normalize

__all__ = ["RopeBending", "RopeStretch", "rope_limits"]


def _rope_points(x: Tensor, first: int, n: int, anchor: Tensor) -> tuple[Tensor, Tensor]:
    """Rope points ``(..., n, 2)`` and segment vectors ``(..., n, 2)`` (anchor first)."""
    pts = x[..., first : first + n, :]
    prev = torch.cat((anchor.to(pts).expand(*pts.shape[:-2], 1, 2), pts[..., :-1, :]), dim=-2)
    return pts, pts - prev


def _cross(a: Tensor, b: Tensor) -> Tensor:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _perp(a: Tensor) -> Tensor:
    return torch.stack((-a[..., 1], a[..., 0]), dim=-1)


def _point_before(x: Tensor, k: Tensor, first: int, anchor: Tensor) -> Tensor:
    """Position of point ``k - 1`` (the anchor for ``k = 0``): ``(..., Ka, 2)``."""
    before = gather_points(x, first + (k - 1).clamp_min(0))
    return torch.where((k > 0).unsqueeze(-1), before, anchor.to(before))


@functools.lru_cache(maxsize=64)
def _inner_mask_on(n: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    mask = torch.ones(n, 1, dtype=dtype, device=device)
    mask[0] = 0.0
    return mask


def _inner_mask(n: int, x: Tensor) -> Tensor:
    """``(n, 1)``: 0 for row 0 (whose point before is the fixed anchor), else 1 (cached:
    the projection asks for it in every iteration)."""
    return _inner_mask_on(n, x.dtype, x.device)


@functools.lru_cache(maxsize=64)
def _row_points_on(n: int, m: int, first: int, device: torch.device) -> Tensor:
    k = torch.arange(n, device=device)
    return torch.stack([(k - 1).clamp_min(0), *(k + j for j in range(m - 1))], -1) + first


def _row_points(n: int, m: int, first: int, x: Tensor) -> Tensor:
    """``(..., n, m)`` points ``k - 1, k[, k + 1]`` of rows ``k = 0 .. n-1`` (the anchor's
    entry, row 0's first, points at ``first``; its value is zero). Cached per device."""
    return _row_points_on(n, m, first, x.device).expand(*x.shape[:-2], n, m)


@dataclasses.dataclass(frozen=True, eq=False)
class RopeBending(GeometryBase):
    """Bending limits at the ``n_points - 1`` inner joints.

    Attributes:
        n_points: number of rope points ``P``.
        max_angle: the limit on ``|theta|`` (radians).
        anchor: ``(2,)`` float64 fixed anchor.
        first_point: index of the rope's first point in the state.
    """

    n_points: int
    max_angle: float
    anchor: Tensor
    first_point: int = 0

    d: ClassVar[int] = 1

    @property
    def n_candidates(self) -> int:
        return self.n_points - 1

    def gap_widths(self) -> Tensor:
        """``(n_points - 1,)``: ``2 max_angle`` (``gap`` on the other side is ``width - gap``),
        on the anchor's device (made there: a CUDA graph's capture cannot copy from the host)."""
        return torch.full(
            (self.n_candidates,),
            2.0 * self.max_angle,
            dtype=torch.float64,
            device=self.anchor.device,
        )

    def gaps(self, x: Tensor) -> Tensor:
        """``max_angle - |theta|`` per joint.

        Args:
            x: ``(..., P_total, 2)``.

        Returns:
            ``(..., n_points - 1)``.
        """
        _, seg = _rope_points(x, self.first_point, self.n_points, self.anchor)
        a, b = seg[..., :-1, :], seg[..., 1:, :]
        theta = torch.atan2(_cross(a, b), dot_last(a, b))
        return self.max_angle - theta.abs()

    def jacobian_sparse(self, x: Tensor, idx: Tensor) -> SparseJacobian:
        """Rows of joints ``idx``.

        Args:
            x: ``(..., P_total, 2)``.
            idx: ``(..., Ka)`` long, joint indices.

        Returns:
            ``points (..., Ka, 3)`` (points ``k-1, k, k+1``; the anchor's entry
            is zero) and ``values (..., Ka, 1, 3, 2)``.
        """
        x, idx = broadcast_batch(x, idx)
        f = self.first_point
        p_prev = _point_before(x, idx, f, self.anchor)
        p_mid = gather_points(x, f + idx)
        p_next = gather_points(x, f + idx + 1)
        a, b = p_mid - p_prev, p_next - p_mid
        theta = torch.atan2(_cross(a, b), dot_last(a, b))
        # theta = phi_b - phi_a, d phi / d s = perp(s) / |s|^2
        g_a = -_perp(a) / dot_last(a, a).unsqueeze(-1)
        g_b = _perp(b) / dot_last(b, b).unsqueeze(-1)
        sign = torch.where(theta >= 0, -1.0, 1.0).to(x).unsqueeze(-1)  # gap = max - |theta|
        g_prev = torch.where((idx > 0).unsqueeze(-1), -g_a, torch.zeros_like(g_a))
        values = sign.unsqueeze(-2) * torch.stack((g_prev, g_a - g_b, g_b), dim=-2)
        points = torch.stack(((f + idx - 1).clamp_min(f), f + idx, f + idx + 1), dim=-1)
        return SparseJacobian(points, values.unsqueeze(-3))

    def jacobian_sparse_all(self, x: Tensor) -> SparseJacobian:
        """Rows of every joint: those of :meth:`jacobian_sparse` on ``arange(P - 1)``,
        from the segment vectors without index gathers (the position projection's
        inner loop)."""
        return self.gaps_and_rows_all(x)[1]

    def gaps_and_rows_all(self, x: Tensor) -> tuple[Tensor, SparseJacobian]:
        """:meth:`gaps` and :meth:`jacobian_sparse_all` from one evaluation of the
        segments and angles."""
        _, seg = _rope_points(x, self.first_point, self.n_points, self.anchor)
        a, b = seg[..., :-1, :], seg[..., 1:, :]
        theta = torch.atan2(_cross(a, b), dot_last(a, b))
        gaps = self.max_angle - theta.abs()
        g_a = -_perp(a) / dot_last(a, a).unsqueeze(-1)
        g_b = _perp(b) / dot_last(b, b).unsqueeze(-1)
        sign = torch.where(theta >= 0, -1.0, 1.0).to(x).unsqueeze(-1)
        inner = _inner_mask(self.n_candidates, x)  # joint 0's point before is the anchor
        values = sign.unsqueeze(-2) * torch.stack((-g_a * inner, g_a - g_b, g_b), dim=-2)
        return gaps, SparseJacobian(
            _row_points(self.n_candidates, 3, self.first_point, x), values.unsqueeze(-3)
        )


@dataclasses.dataclass(frozen=True, eq=False)
class RopeStretch(GeometryBase):
    """Stretch limits of the ``n_points`` segments.

    Attributes:
        lower: ``(n_points,)`` float64 minimum lengths ``min_ratio * l0``.
        upper: ``(n_points,)`` float64 maximum lengths ``max_ratio * l0``.
        anchor: ``(2,)`` float64 fixed anchor.
        first_point: index of the rope's first point in the state.
    """

    lower: Tensor
    upper: Tensor
    anchor: Tensor
    first_point: int = 0

    d: ClassVar[int] = 1

    @property
    def n_candidates(self) -> int:
        return int(self.lower.shape[0])

    def gap_widths(self) -> Tensor:
        """``(n_points,)``: ``upper - lower`` (``gap`` on the other side is ``width - gap``)."""
        return (self.upper - self.lower).to(torch.float64)

    def gaps(self, x: Tensor) -> Tensor:
        """``min(len - lower, upper - len)`` per segment.

        Args:
            x: ``(..., P_total, 2)``.

        Returns:
            ``(..., n_points)``.
        """
        _, seg = _rope_points(x, self.first_point, self.n_candidates, self.anchor)
        length = safe_norm(seg)
        lo, hi = self.lower.to(length), self.upper.to(length)
        return torch.minimum(length - lo, hi - length)

    def jacobian_sparse(self, x: Tensor, idx: Tensor) -> SparseJacobian:
        """Rows of segments ``idx``.

        Args:
            x: ``(..., P_total, 2)``.
            idx: ``(..., Ka)`` long, segment indices.

        Returns:
            ``points (..., Ka, 2)`` (points ``k-1, k``; the anchor's entry is
            zero) and ``values (..., Ka, 1, 2, 2)``.
        """
        x, idx = broadcast_batch(x, idx)
        f = self.first_point
        seg = gather_points(x, f + idx) - _point_before(x, idx, f, self.anchor)
        u, length = safe_normalize(seg)
        lo, hi = self.lower.to(length)[idx], self.upper.to(length)[idx]
        sign = torch.where(length - lo <= hi - length, 1.0, -1.0).to(x).unsqueeze(-1)
        g = sign * u
        g_prev = torch.where((idx > 0).unsqueeze(-1), -g, torch.zeros_like(g))
        values = torch.stack((g_prev, g), dim=-2).unsqueeze(-3)
        points = torch.stack(((f + idx - 1).clamp_min(f), f + idx), dim=-1)
        return SparseJacobian(points, values)

    def jacobian_sparse_all(self, x: Tensor) -> SparseJacobian:
        """Rows of every segment: those of :meth:`jacobian_sparse` on ``arange(P)``,
        without index gathers."""
        return self.gaps_and_rows_all(x)[1]

    def gaps_and_rows_all(self, x: Tensor) -> tuple[Tensor, SparseJacobian]:
        """:meth:`gaps` and :meth:`jacobian_sparse_all` from one evaluation of the
        segments' lengths."""
        _, seg = _rope_points(x, self.first_point, self.n_candidates, self.anchor)
        u, length = safe_normalize(seg)
        lo, hi = self.lower.to(length), self.upper.to(length)
        below, above = length - lo, hi - length
        gaps = torch.minimum(below, above)
        g = torch.where(below <= above, 1.0, -1.0).to(x).unsqueeze(-1) * u
        values = torch.stack((-g * _inner_mask(self.n_candidates, x), g), dim=-2)
        return gaps, SparseJacobian(
            _row_points(self.n_candidates, 2, self.first_point, x), values.unsqueeze(-3)
        )


def rope_limits(
    n_points: int,
    *,
    max_angle: float = 0.2,
    rest_length: float | Sequence[float] = 0.05,
    min_ratio: float = 0.8,
    max_ratio: float = 1.2,
    anchor: Sequence[float] = (0.0, 0.0),
    first_point: int = 0,
) -> ContactGeometry:
    """Bending then stretch limits of a rope (``2 n_points - 1`` candidates).

    Args:
        n_points: rope points ``P`` (>= 2).
        max_angle: bending limit in radians (paper: 0.2).
        rest_length: ``l0`` of every segment, or one per segment.
        min_ratio, max_ratio: stretch limits as fractions of ``l0``.
        anchor: the fixed anchor (not a state point).
        first_point: index of the rope's first point in the state.

    Returns:
        A :class:`ContactGeometry` of ``d = 1``.
    """
    if n_points < 2:
        raise ValueError(f"a rope needs at least 2 points, got n_points={n_points}")
    if not max_angle > 0:
        raise ValueError(f"max_angle must be positive, got {max_angle}")
    if not 0 <= min_ratio < max_ratio:
        raise ValueError(f"need 0 <= min_ratio < max_ratio, got {min_ratio}, {max_ratio}")
    l0 = torch.as_tensor(rest_length, dtype=torch.float64)
    if l0.ndim > 1 or (l0.ndim == 1 and l0.shape[0] != n_points):
        raise ValueError(f"rest_length: need one number or {n_points}, got {l0.tolist()}")
    l0 = l0.expand(n_points).clone()
    if bool((l0 <= 0).any()):
        raise ValueError(f"rest lengths must be positive, got {l0.tolist()}")
    anchor_t = torch.tensor([float(a) for a in anchor], dtype=torch.float64)
    if anchor_t.shape != (2,):
        raise ValueError(f"anchor must be 2 numbers, got {list(anchor)}")
    bending = RopeBending(n_points, float(max_angle), anchor_t, first_point)
    stretch = RopeStretch(min_ratio * l0, max_ratio * l0, anchor_t, first_point)
    return ContactGeometry((bending, stretch))
