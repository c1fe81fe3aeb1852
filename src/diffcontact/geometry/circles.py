"""Circle-circle and circle-line contacts in 2D (bouncing point masses, disks, CP3).

A body is a circle of radius ``r`` around its centre, which is its first point.
It is either a point mass (1 point, never rotates) or a 2D rigid disk (3
points: centre, centre + body x axis, centre + body y axis).

Candidates (paper-facts.md numbering): all body pairs ``i < j`` in
lexicographic order, then body-wall pairs body-major,
``n_pairs + n_walls * i + j``. Walls are lines ``a x + b y + c = 0`` with the
allowed side ``a x + b y + c > 0``.

Contact space ``d = 2``: ``(n, t)`` with ``t = (-n_y, n_x)``. For a pair the
normal points from ``i`` to ``j`` and the contact velocity is that of ``j``'s
rim point ``c_j - r_j n`` relative to ``i``'s rim point ``c_i + r_i n``; for a
wall the normal is the wall normal and the rim point is ``c - r n``. The normal
row of ``J_C`` is ``D_x gap`` (centres only); the tangent row is the tangential
velocity of the rim point(s) as material points of their bodies (extended-body
weights). On velocities that respect the rigid-body constraints the normal row
also equals the normal velocity of the rim points.

Angular momentum. A contact is resolved at the state after the step that made the
gap negative: the two rim points then lie ``-gap`` apart along ``n``, and a pair's
tangential impulse ``f_t`` (on ``j``, ``-f_t`` on ``i``) changes the total angular
momentum by exactly ``gap * f_t`` (``tests/systems/test_simulate.py``): each disk gets
the spin of an impact at its own rim, as when the disks touch, while the centres are
``-gap`` closer. Normal impulses (through the centres) and frictionless contacts keep
it. The change vanishes with the penetration (it is of the order of ``dt`` times the
approach speed). One contact point shared by both disks would keep the angular momentum
but make each disk's spin depend on the penetration, i.e. on where the step grid falls
in the impact; this module keeps the rim points.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import ClassVar

import torch
from torch import Tensor

from .base import (
    ContactGeometry,
    GeometryBase,
    SparseJacobian,
    broadcast_batch,
    gather_points,
    unit_normal_planes,
)
from .frames import material_point_weights, safe_norm, safe_normalize, tangent_basis

__all__ = ["BODY_KINDS", "CirclePairs", "CircleWalls", "circles_2d"]

BODY_KINDS: dict[str, int] = {"point": 1, "disk": 3}
"""Number of points of each 2D body kind."""


def _body_tables(
    kinds: Sequence[str], radii: Sequence[float], first_points: Sequence[int] | None
) -> tuple[Tensor, Tensor, Tensor]:
    """Validated static body tables ``(body_points (B, m_b), is_disk (B,), radii (B,))``.

    ``m_b`` is 3 if any body is a disk, else 1; a point mass repeats its point.
    """
    kinds = list(kinds)
    radii = [float(r) for r in radii]
    for b, kind in enumerate(kinds):
        if kind not in BODY_KINDS:
            raise ValueError(f"body {b}: kind must be one of {sorted(BODY_KINDS)}, got {kind!r}")
    if len(radii) != len(kinds):
        raise ValueError(f"got {len(kinds)} bodies but {len(radii)} radii")
    if any(not r > 0 for r in radii):
        raise ValueError(f"radii must be positive, got {radii}")
    if first_points is None:
        sizes = [BODY_KINDS[k] for k in kinds]
        first_points = [sum(sizes[:b]) for b in range(len(kinds))]
    first_points = [int(s) for s in first_points]
    if len(first_points) != len(kinds):
        raise ValueError(f"got {len(kinds)} bodies but {len(first_points)} first points")
    if any(s < 0 for s in first_points):
        raise ValueError(f"first points must be non-negative, got {first_points}")
    is_disk = torch.tensor([k == "disk" for k in kinds], dtype=torch.bool)
    m_b = 3 if bool(is_disk.any()) else 1
    start = torch.tensor(first_points, dtype=torch.long)
    offs = torch.arange(m_b, dtype=torch.long)
    body_points = start[:, None] + torch.where(is_disk[:, None], offs, 0)
    return body_points, is_disk, torch.tensor(radii, dtype=torch.float64)


def _rim_weights(x: Tensor, body_points: Tensor, is_disk: Tensor, p: Tensor) -> Tensor:
    """Extended-body weights of rim points ``p`` on their bodies.

    Args:
        x: ``(*B, P, 2)``.
        body_points: ``(*B, Ka, m_b)`` long.
        is_disk: ``(*B, Ka)`` bool.
        p: ``(*B, Ka, 2)``.

    Returns:
        ``(*B, Ka, m_b)``: ``(1, 0, 0)`` for point masses, material-point weights
        ``(1 - r1 - r2, r1, r2)`` for disks.
    """
    m_b = body_points.shape[-1]
    if m_b == 1:
        return torch.ones_like(p[..., 0]).unsqueeze(-1)
    pts = gather_points(x, body_points)  # (*B, Ka, 3, 2)
    # point masses get stand-in unit axes so the solve stays regular; masked below
    eye = torch.eye(2, dtype=x.dtype, device=x.device)
    fake = torch.cat((pts[..., :1, :], pts[..., :1, :] + eye), dim=-2)
    disk = is_disk[..., None, None]
    w = material_point_weights(torch.where(disk, pts, fake), p)
    point_w = torch.zeros_like(w)
    point_w[..., 0] = 1.0
    return torch.where(is_disk.unsqueeze(-1), w, point_w)


def _cached_tables(cache: dict, device: torch.device, dtype: torch.dtype, make) -> tuple:
    """``make()``'s tensors moved to ``device``, made once per device and dtype and kept in
    ``cache`` (making index tensors anew costs microseconds per call in the step)."""
    tables = cache.get((device, dtype))
    if tables is None:
        tables = cache[(device, dtype)] = tuple(t.to(device) for t in make())
    return tables


@dataclasses.dataclass(frozen=True, eq=False)
class CirclePairs(GeometryBase):
    """Circle-circle candidates of all body pairs ``i < j`` (lexicographic).

    Attributes:
        body_points: ``(B, m_b)`` long, each body's points (centre first).
        is_disk: ``(B,)`` bool.
        radii: ``(B,)`` float64.
        pair_i, pair_j: ``(K,)`` long, the bodies of each candidate.
    """

    body_points: Tensor
    is_disk: Tensor
    radii: Tensor
    pair_i: Tensor
    pair_j: Tensor
    _tables: dict = dataclasses.field(default_factory=dict, init=False, repr=False)

    d: ClassVar[int] = 2

    @classmethod
    def build(
        cls,
        kinds: Sequence[str],
        radii: Sequence[float],
        first_points: Sequence[int] | None = None,
    ) -> CirclePairs:
        """Candidates for bodies of the given ``kinds`` ("point" or "disk").

        Args:
            kinds: per body, ``"point"`` (1 point) or ``"disk"`` (3 points).
            radii: per body, positive.
            first_points: index of each body's first point; default the bodies'
                points laid out consecutively in order.
        """
        body_points, is_disk, r = _body_tables(kinds, radii, first_points)
        pairs = torch.triu_indices(len(r), len(r), offset=1)
        return cls(body_points, is_disk, r, pairs[0].clone(), pairs[1].clone())

    @property
    def n_candidates(self) -> int:
        return int(self.pair_i.shape[0])

    def gaps(self, x: Tensor) -> Tensor:
        """``|c_j - c_i| - r_i - r_j`` for all pairs.

        Args:
            x: ``(..., P, 2)``.

        Returns:
            ``(..., K)``.
        """
        ci_idx, cj_idx, r_i, r_j = self._gap_tables(x.device, x.dtype)
        dist = safe_norm(x.index_select(-2, cj_idx) - x.index_select(-2, ci_idx))
        return dist - r_i - r_j

    def _gap_tables(self, device: torch.device, dtype: torch.dtype) -> tuple[Tensor, ...]:
        """The points of the pairs' centres and their radii, each ``(K,)``."""

        def make() -> tuple[Tensor, ...]:
            centres, r = self.body_points[:, 0], self.radii.to(dtype)
            return centres[self.pair_i], centres[self.pair_j], r[self.pair_i], r[self.pair_j]

        return _cached_tables(self._tables, device, dtype, make)

    @property
    def separable(self) -> bool:
        """Point masses only: each row is its frame row on the two centres (base.py)."""
        return self.body_points.shape[-1] == 1

    def frames_all(self, x: Tensor) -> Tensor:
        """``(..., K, 2, 2)``: rows ``(n, t)`` of every pair (point masses; base.py)."""
        ci_idx, cj_idx, _, _ = self._gap_tables(x.device, x.dtype)
        n, _ = safe_normalize(x.index_select(-2, cj_idx) - x.index_select(-2, ci_idx))
        return torch.stack((n, tangent_basis(n)[..., 0, :]), dim=-2)

    def point_weights(self, P: int, device: torch.device, dtype: torch.dtype) -> Tensor:
        """``(K, P)``: -1 on body i's centre, +1 on body j's (point masses; base.py)."""
        centres = self.body_points[:, 0]
        k = torch.arange(self.n_candidates)
        w = torch.zeros(self.n_candidates, P, dtype=dtype)
        w[k, centres[self.pair_i]] = -1.0
        w[k, centres[self.pair_j]] = 1.0
        return w.to(device)

    def jacobian_sparse(self, x: Tensor, idx: Tensor) -> SparseJacobian:
        """Rows of pairs ``idx``.

        Args:
            x: ``(..., P, 2)``.
            idx: ``(..., Ka)`` long, pair candidate indices.

        Returns:
            ``points (..., Ka, 2 m_b)`` (body i's points, then body j's) and
            ``values (..., Ka, 2, 2 m_b, 2)``.
        """
        x, idx = broadcast_batch(x, idx)
        dev = x.device
        bp = self.body_points.to(dev)
        disk = self.is_disk.to(dev)
        r = self.radii.to(device=dev, dtype=x.dtype)
        bi, bj = self.pair_i.to(dev)[idx], self.pair_j.to(dev)[idx]
        pts_i, pts_j = bp[bi], bp[bj]  # (*B, Ka, m_b)
        ci = gather_points(x, pts_i[..., 0])
        cj = gather_points(x, pts_j[..., 0])
        n, _ = safe_normalize(cj - ci)  # (*B, Ka, 2)
        t = tangent_basis(n)[..., 0, :]
        w_i = _rim_weights(x, pts_i, disk[bi], ci + r[bi].unsqueeze(-1) * n)
        w_j = _rim_weights(x, pts_j, disk[bj], cj - r[bj].unsqueeze(-1) * n)
        centre = torch.zeros_like(w_i)
        centre[..., 0] = 1.0
        normal_w = torch.cat((-centre, centre), dim=-1)  # (*B, Ka, 2 m_b)
        tangent_w = torch.cat((-w_i, w_j), dim=-1)
        values = torch.stack(
            (normal_w.unsqueeze(-1) * n.unsqueeze(-2), tangent_w.unsqueeze(-1) * t.unsqueeze(-2)),
            dim=-3,
        )
        return SparseJacobian(torch.cat((pts_i, pts_j), dim=-1), values)


@dataclasses.dataclass(frozen=True, eq=False)
class CircleWalls(GeometryBase):
    """Circle-line candidates, body-major: candidate ``n_walls * i + j``.

    Attributes:
        body_points: ``(B, m_b)`` long, each body's points (centre first).
        is_disk: ``(B,)`` bool.
        radii: ``(B,)`` float64.
        walls: ``(W, 3)`` float64 lines ``(a, b, c)`` with ``a^2 + b^2 = 1``.
    """

    body_points: Tensor
    is_disk: Tensor
    radii: Tensor
    walls: Tensor
    _tables: dict = dataclasses.field(default_factory=dict, init=False, repr=False)

    d: ClassVar[int] = 2

    @classmethod
    def build(
        cls,
        kinds: Sequence[str],
        radii: Sequence[float],
        walls: Sequence[Sequence[float]],
        first_points: Sequence[int] | None = None,
    ) -> CircleWalls:
        """Candidates of every body against every wall.

        Args:
            kinds: per body, ``"point"`` or ``"disk"``.
            radii: per body, positive.
            walls: lines ``[a, b, c]``, allowed side ``a x + b y + c > 0``;
                normalised here so that ``(a, b)`` is a unit vector.
            first_points: index of each body's first point (default consecutive).
        """
        body_points, is_disk, r = _body_tables(kinds, radii, first_points)
        w = torch.tensor([[float(v) for v in wall] for wall in walls], dtype=torch.float64)
        if w.numel() == 0:
            w = w.reshape(0, 3)
        if w.ndim != 2 or w.shape[1] != 3:
            raise ValueError(f"walls must be [a, b, c] lines, got shape {tuple(w.shape)}")
        if bool((w[:, :2] == 0).all(dim=-1).any()):
            raise ValueError(f"wall normals (a, b) must be non-zero, got {w.tolist()}")
        return cls(body_points, is_disk, r, unit_normal_planes(w, 2))

    @property
    def n_walls(self) -> int:
        return int(self.walls.shape[0])

    @property
    def n_candidates(self) -> int:
        return int(self.radii.shape[0]) * self.n_walls

    def gaps(self, x: Tensor) -> Tensor:
        """Signed distance of each centre to each wall minus the radius.

        Args:
            x: ``(..., P, 2)``.

        Returns:
            ``(..., K)``, body-major.
        """

        def make() -> tuple[Tensor, ...]:
            w = self.walls.to(x.dtype)
            r = self.radii.to(x.dtype).unsqueeze(-1)
            return self.body_points[:, 0], w[:, :2].T.contiguous(), w[:, 2], r

        centres, normals, offsets, r = _cached_tables(self._tables, x.device, x.dtype, make)
        c = x.index_select(-2, centres)  # (..., B, 2)
        return (c @ normals + offsets - r).flatten(-2)  # (..., B, W)

    @property
    def separable(self) -> bool:
        """Point masses only: each row is its frame row on the body's centre (base.py)."""
        return self.body_points.shape[-1] == 1

    def frames_all(self, x: Tensor) -> Tensor:
        """``(K, 2, 2)``: rows ``(n, t)`` of every candidate, the wall's (base.py)."""

        key = ("frames", x.device, x.dtype)  # (the gap tables are keyed (device, dtype))
        if key not in self._tables:
            n = self.walls[:, :2].to(x.dtype)
            frames = torch.stack((n, tangent_basis(n)[..., 0, :]), dim=-2)  # (W, 2, 2)
            self._tables[key] = frames.repeat(int(self.radii.shape[0]), 1, 1).to(x.device)
        return self._tables[key]

    def point_weights(self, P: int, device: torch.device, dtype: torch.dtype) -> Tensor:
        """``(K, P)``: +1 on the body's centre (point masses; base.py)."""
        centres = self.body_points[:, 0].repeat_interleave(self.n_walls)
        w = torch.zeros(self.n_candidates, P, dtype=dtype)
        w[torch.arange(self.n_candidates), centres] = 1.0
        return w.to(device)

    def jacobian_sparse(self, x: Tensor, idx: Tensor) -> SparseJacobian:
        """Rows of body-wall candidates ``idx``.

        Args:
            x: ``(..., P, 2)``.
            idx: ``(..., Ka)`` long.

        Returns:
            ``points (..., Ka, m_b)`` and ``values (..., Ka, 2, m_b, 2)``.
        """
        x, idx = broadcast_batch(x, idx)
        dev = x.device
        n_w = self.n_walls
        body, wall = idx // n_w, idx % n_w
        pts = self.body_points.to(dev)[body]  # (*B, Ka, m_b)
        r = self.radii.to(device=dev, dtype=x.dtype)[body]
        n = self.walls.to(device=dev, dtype=x.dtype)[wall][..., :2]  # (*B, Ka, 2)
        t = tangent_basis(n)[..., 0, :]
        c = gather_points(x, pts[..., 0])
        w = _rim_weights(x, pts, self.is_disk.to(dev)[body], c - r.unsqueeze(-1) * n)
        centre = torch.zeros_like(w)
        centre[..., 0] = 1.0
        values = torch.stack(
            (centre.unsqueeze(-1) * n.unsqueeze(-2), w.unsqueeze(-1) * t.unsqueeze(-2)), dim=-3
        )
        return SparseJacobian(pts, values)


def circles_2d(
    kinds: Sequence[str],
    radii: Sequence[float],
    walls: Sequence[Sequence[float]] = (),
    *,
    pairs: bool = True,
    first_points: Sequence[int] | None = None,
) -> ContactGeometry:
    """All circle contacts of a 2D system, numbered as in paper-facts.md.

    Args:
        kinds: per body, ``"point"`` or ``"disk"``.
        radii: per body.
        walls: lines ``[a, b, c]`` (allowed side ``> 0``).
        pairs: include body-body candidates; ``False`` for a chain pendulum
            whose links may not collide (CP3), whose candidates are then only
            ``n_walls * i + j``.
        first_points: index of each body's first point (default consecutive).

    Returns:
        A :class:`ContactGeometry` of ``d = 2``: pairs (if any), then walls.
    """
    parts: list = []
    if pairs and len(kinds) > 1:
        parts.append(CirclePairs.build(kinds, radii, first_points))
    if len(walls) > 0:
        parts.append(CircleWalls.build(kinds, radii, walls, first_points))
    if not parts:
        raise ValueError("circles_2d: no candidate contacts (need pairs or walls)")
    return ContactGeometry(tuple(parts))
