"""Shared pieces of the contact geometries.

Every geometry is a small frozen dataclass holding static index tensors (built
from plain config numbers) and offers

- ``gaps(x) -> (..., K)``: signed gaps of all ``K = n_candidates`` candidates;
- ``jacobian_sparse(x, idx) -> SparseJacobian``: the contact Jacobian rows of
  the candidates ``idx`` as ``m`` (point, coefficient) entries per row;
- ``jacobian(x, idx) -> (..., Ka, d, P, dim)``: the same rows, dense.

A geometry whose every row is a frame row times fixed point weights (point masses:
``J_C`` block of candidate ``k`` is ``frame_k(x) (x) weights_k``, the same weights for
its ``d`` rows) may say so with ``separable = True`` and offer ``frames_all(x) ->
(..., K, d, dim)`` and ``point_weights(P, device, dtype) -> (K, P)``;
:class:`ContactGeometry` then builds the
dense rows from those in a few operations instead of from the sparse entries
(:meth:`ContactGeometry.jacobian`; bitwise the same values).

The contact-space velocity of candidate ``idx[..., k]`` is
``v_C[..., k, :] = sum_{p,c} J_C[..., k, :, p, c] v[..., p, c]`` with components
``(normal, tangent...)``; the normal row is ``D_x gap``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar, NamedTuple, Protocol, runtime_checkable

import torch
from torch import Tensor

from diffcontact.shapes import broadcast_shapes

__all__ = [
    "ContactGeometry",
    "Geometry",
    "GeometryBase",
    "SparseJacobian",
    "assemble_jacobian",
    "at_points",
    "broadcast_batch",
    "gather_points",
    "jacobian_matvec",
    "jacobian_rmatvec",
    "take_rows",
    "unit_normal_planes",
]


class SparseJacobian(NamedTuple):
    """Contact Jacobian rows as ``m`` entries per candidate.

    ``J_C[..., k, r, points[..., k, a], :] += values[..., k, r, a, :]`` for every
    entry ``a``; unused entries have zero ``values`` (and any valid point).

    Attributes:
        points: ``(..., Ka, m)`` long, point indices.
        values: ``(..., Ka, d, m, dim)``.
    """

    points: Tensor
    values: Tensor


@runtime_checkable
class Geometry(Protocol):
    """What the simulator needs from a set of static contact candidates."""

    d: int
    n_candidates: int

    def gaps(self, x: Tensor) -> Tensor:
        """Signed gaps ``(..., K)`` of positions ``x: (..., P, dim)``."""
        ...

    def jacobian_sparse(self, x: Tensor, idx: Tensor) -> SparseJacobian:
        """Rows of the candidates ``idx: (..., Ka)`` as a :class:`SparseJacobian`."""
        ...

    def jacobian(self, x: Tensor, idx: Tensor) -> Tensor:
        """Dense rows ``J_C: (..., Ka, d, P, dim)`` of the candidates ``idx``."""
        ...

    def to(self, device: torch.device | str) -> Geometry:
        """A copy with its static tensors on ``device``."""
        ...


def unit_normal_planes(w: Tensor, n_normal: int) -> Tensor:
    """Lines or planes ``(..., n_normal + 1)`` (normal, offset) scaled so that the normal
    part is a unit vector, without overflow or underflow: divided by the normal's largest
    ``|component|`` first (``[1e160, 0, 0]`` had a norm of inf, hence a zero normal, and
    ``[1e-170, 0, 0]`` one of 0). A zero normal gives NaN rows; callers refuse them."""
    largest = w[..., :n_normal].abs().amax(dim=-1, keepdim=True)
    w = w / largest
    return w / w[..., :n_normal].norm(dim=-1, keepdim=True)


def broadcast_batch(x: Tensor, idx: Tensor) -> tuple[Tensor, Tensor]:
    """Expand ``x: (..., P, dim)`` and ``idx: (..., Ka)`` to common leading dims."""
    batch = broadcast_shapes(x.shape[:-2], idx.shape[:-1])
    return x.expand(*batch, *x.shape[-2:]), idx.expand(*batch, idx.shape[-1])


def gather_points(x: Tensor, points: Tensor) -> Tensor:
    """Batched point lookup.

    Args:
        x: ``(*B, P, dim)``.
        points: ``(*B, *S)`` long, with exactly ``x``'s leading dims ``B``.

    Returns:
        ``(*B, *S, dim)`` with ``out[b, s] = x[b, points[b, s]]``.
    """
    batch = x.shape[:-2]
    tail = points.shape[len(batch) :]
    flat = points.reshape(*batch, math.prod(tail))  # (not -1: ambiguous for an empty batch)
    out = torch.gather(x, -2, flat.unsqueeze(-1).expand(*flat.shape, x.shape[-1]))
    return out.reshape(*batch, *tail, x.shape[-1])


def at_points(per_point: Tensor, points: Tensor) -> Tensor:
    """A per-point quantity at sparse entries' points: ``per_point: (P,)`` (shared) or
    ``(n, P)`` (per state), ``points: (n, *S)`` long -> ``(n, *S)``."""
    if per_point.dim() == 1:
        return per_point[points]
    n = points.shape[0]
    return per_point.gather(-1, points.reshape(n, -1)).view(points.shape)


def assemble_jacobian(jac: SparseJacobian, n_points: int) -> Tensor:
    """Dense ``J_C: (..., Ka, d, P, dim)`` from a :class:`SparseJacobian`."""
    values = jac.values
    *lead, d, m, dim = values.shape
    index = jac.points[..., None, :, None].expand(*lead, d, m, dim)
    out = values.new_zeros(*lead, d, n_points, dim)
    return out.scatter_add_(-2, index, values)  # (in place: no copy of the zeros)


def take_rows(jac: SparseJacobian, idx: Tensor) -> SparseJacobian:
    """Rows ``idx: (*B, Ka)`` (long) of ``jac`` (leading dims ``B``, ``K`` rows)."""
    m = jac.points.shape[-1]
    d, dim = jac.values.shape[-3], jac.values.shape[-1]
    points = jac.points.expand(*idx.shape[:-1], *jac.points.shape[-2:])
    points = points.gather(-2, idx.unsqueeze(-1).expand(*idx.shape, m))
    index = idx[..., None, None, None].expand(*idx.shape, d, m, dim)
    return SparseJacobian(points, jac.values.gather(-4, index))


def jacobian_matvec(jac: SparseJacobian, v: Tensor) -> Tensor:
    """Contact-space velocity ``J_C v``.

    Args:
        jac: rows for ``Ka`` candidates, leading dims ``B``.
        v: ``(*B, P, dim)``.

    Returns:
        ``(*B, Ka, d)``.
    """
    v_pts = gather_points(v, jac.points)  # (*B, Ka, m, dim)
    return (jac.values * v_pts.unsqueeze(-3)).sum((-1, -2))


def jacobian_rmatvec(jac: SparseJacobian, f: Tensor, n_points: int) -> Tensor:
    """Cartesian impulse ``J_C^T f``.

    Args:
        jac: rows for ``Ka`` candidates, leading dims ``B``.
        f: ``(*B, Ka, d)``.
        n_points: ``P``.

    Returns:
        ``(*B, P, dim)``.
    """
    contrib = (jac.values * f[..., None, None]).sum(-3)  # (*B, Ka, m, dim)
    batch = contrib.shape[:-3]
    dim = contrib.shape[-1]
    contrib = contrib.reshape(*batch, -1, dim)
    index = jac.points.reshape(*batch, -1, 1).expand(*batch, contrib.shape[-2], dim)
    return contrib.new_zeros(*batch, n_points, dim).scatter_add(-2, index, contrib)


class GeometryBase:
    """Mix-in for frozen-dataclass geometries: dense Jacobian and device moves."""

    d: ClassVar[int]

    @property
    def n_candidates(self) -> int:
        raise NotImplementedError

    def gaps(self, x: Tensor) -> Tensor:
        raise NotImplementedError

    def jacobian_sparse(self, x: Tensor, idx: Tensor) -> SparseJacobian:
        raise NotImplementedError

    def gap_widths(self) -> Tensor:
        """``(K,)`` float64: the width of each candidate's admissible band.

        A two-sided limit (the rope's) reports the smaller of its two side gaps, and the
        two sides' gaps sum to a constant, the width: ``gap_other = width - gap``, with the
        Jacobian row negated. One-sided contacts (all others) have width ``inf``. Used by
        the position projection (``systems/projection.py``) to linearise both sides.
        """
        return torch.full((self.n_candidates,), math.inf, dtype=torch.float64)

    def jacobian(self, x: Tensor, idx: Tensor) -> Tensor:
        """Dense rows ``J_C: (..., Ka, d, P, dim)`` of candidates ``idx: (..., Ka)``.

        Padded entries of ``idx`` must hold a valid candidate index; their rows
        are those of that candidate (the caller masks them).
        """
        return assemble_jacobian(self.jacobian_sparse(x, idx), x.shape[-2])

    def jacobian_sparse_all(self, x: Tensor) -> SparseJacobian:
        """Rows of every candidate, ``(..., K, m)`` entries (``x: (..., P, dim)``).

        What a caller that needs many rows of one state computes once and then
        gathers from (:func:`take_rows`); a geometry may override it with a cheaper
        evaluation than :meth:`jacobian_sparse` on ``arange(K)`` (the rope's).
        """
        K = self.n_candidates
        idx = torch.arange(K, device=x.device).expand(*x.shape[:-2], K)
        return self.jacobian_sparse(x, idx)

    def gaps_and_rows_all(self, x: Tensor) -> tuple[Tensor, SparseJacobian]:
        """:meth:`gaps` and :meth:`jacobian_sparse_all` at ``x``, together: what the
        position projection needs in each iteration; a geometry may share the work of the
        two (the rope's segment vectors and angles)."""
        return self.gaps(x), self.jacobian_sparse_all(x)

    def to(self, device: torch.device | str):
        """A copy with every tensor field on ``device`` (dtypes kept)."""
        changes = {
            f.name: getattr(self, f.name).to(device)
            for f in dataclasses.fields(self)  # type: ignore[arg-type]
            if isinstance(getattr(self, f.name), Tensor)
        }
        return dataclasses.replace(self, **changes)  # type: ignore[type-var]


@dataclasses.dataclass(frozen=True, eq=False)
class ContactGeometry(GeometryBase):
    """Several geometries with the same ``d``, candidates numbered part after part.

    Candidate ``k`` of part ``i`` is candidate ``offsets[i] + k`` of the whole.

    Attributes:
        parts: the geometries, in numbering order.
    """

    parts: tuple[Geometry, ...]
    _tables: dict = dataclasses.field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.parts:
            raise ValueError("ContactGeometry needs at least one part")
        ds = {p.d for p in self.parts}
        if len(ds) != 1:
            raise ValueError(f"ContactGeometry parts must share d, got {sorted(ds)}")

    @property
    def d(self) -> int:  # type: ignore[override]
        return self.parts[0].d

    @property
    def n_candidates(self) -> int:
        return sum(p.n_candidates for p in self.parts)

    @property
    def offsets(self) -> tuple[int, ...]:
        """First candidate index of each part."""
        out, acc = [], 0
        for p in self.parts:
            out.append(acc)
            acc += p.n_candidates
        return tuple(out)

    def gaps(self, x: Tensor) -> Tensor:
        """Signed gaps ``(..., K)`` of all candidates for ``x: (..., P, dim)``."""
        return torch.cat([p.gaps(x) for p in self.parts], dim=-1)

    def gap_widths(self) -> Tensor:
        """``(K,)`` the parts' widths (``inf`` for a part without its own ``gap_widths``), on
        the device of the first part whose widths live on one (a rope moved to CUDA). Made
        without a copy from the host where the parts make theirs on the device: the
        position projection asks for them inside a captured CUDA step."""
        widths = [  # the default (all inf) is made on the device here: no copy from the host
            None if type(p).gap_widths is GeometryBase.gap_widths else p.gap_widths()
            for p in self.parts
        ]
        device = next((w.device for w in widths if w is not None and w.device.type != "cpu"), None)
        return torch.cat(
            [
                w.to(dtype=torch.float64, device=device)
                if w is not None
                else torch.full((p.n_candidates,), math.inf, dtype=torch.float64, device=device)
                for p, w in zip(self.parts, widths, strict=True)
            ]
        )

    def jacobian_sparse(self, x: Tensor, idx: Tensor) -> SparseJacobian:
        """Rows of candidates ``idx: (..., Ka)``; entries padded to the largest ``m``.

        Each part is evaluated on all ``Ka`` entries (indices clamped into its
        range) and the right part is selected per entry; the parts are few.
        """
        x, idx = broadcast_batch(x, idx)
        parts = []
        for part, off in zip(self.parts, self.offsets, strict=True):
            local = (idx - off).clamp(0, part.n_candidates - 1)
            jac = part.jacobian_sparse(x, local)
            inside = (idx >= off) & (idx < off + part.n_candidates)
            parts.append((jac, inside))
        m = max(jac.points.shape[-1] for jac, _ in parts)
        points = values = None
        for jac, inside in parts:
            pad = m - jac.points.shape[-1]
            p_pts = torch.nn.functional.pad(jac.points, (0, pad))
            p_val = torch.nn.functional.pad(jac.values, (0, 0, 0, pad))
            if points is None:
                points, values = p_pts, p_val
            else:
                points = torch.where(inside.unsqueeze(-1), p_pts, points)
                values = torch.where(inside[..., None, None, None], p_val, values)
        assert points is not None and values is not None
        return SparseJacobian(points, values)

    @property
    def separable(self) -> bool:
        """Whether every part's rows are frame rows times fixed point weights (module
        docstring): then :meth:`jacobian` takes the few-operation path."""
        return all(
            getattr(p, "separable", False)
            and hasattr(p, "frames_all")
            and hasattr(p, "point_weights")
            for p in self.parts
        )

    def jacobian(self, x: Tensor, idx: Tensor) -> Tensor:
        """Dense rows ``J_C: (..., Ka, d, P, dim)`` of candidates ``idx: (..., Ka)``.

        For separable parts (point masses) ``frames_all(x)[idx] (x) point_weights[idx]``:
        a simulation step's Jacobian in about 15 operations instead of the sparse entries
        of every part and their scatter (about 100 on BP5); else as
        :meth:`GeometryBase.jacobian`.
        """
        if not self.separable:
            return super().jacobian(x, idx)
        x, idx = broadcast_batch(x, idx)
        P, dim, d = x.shape[-2], x.shape[-1], self.d
        key = (P, x.device, x.dtype)
        weights = self._tables.get(key)
        if weights is None:  # (K, P), static
            weights = self._tables[key] = torch.cat(
                [p.point_weights(P, x.device, x.dtype) for p in self.parts]
            )
        frames = [p.frames_all(x) for p in self.parts]  # each (..., K_part, d, dim)
        batch = broadcast_shapes(*(f.shape[:-3] for f in frames), x.shape[:-2])
        frames = torch.cat([f.expand(*batch, *f.shape[-3:]) for f in frames], dim=-3)
        rows = frames.gather(-3, idx[..., None, None].expand(*idx.shape, d, dim))
        return rows.unsqueeze(-2) * weights[idx][..., None, :, None]

    def jacobian_sparse_all(self, x: Tensor) -> SparseJacobian:
        """Every part's rows (:meth:`GeometryBase.jacobian_sparse_all`), part after part,
        entries padded to the largest ``m``."""
        return _cat_rows([p.jacobian_sparse_all(x) for p in self.parts])

    def gaps_and_rows_all(self, x: Tensor) -> tuple[Tensor, SparseJacobian]:
        """:meth:`gaps` and :meth:`jacobian_sparse_all` together, from each part's own
        (:meth:`GeometryBase.gaps_and_rows_all`)."""
        both = [
            p.gaps_and_rows_all(x)
            if hasattr(p, "gaps_and_rows_all")
            else (p.gaps(x), p.jacobian_sparse_all(x))
            for p in self.parts
        ]
        return torch.cat([g for g, _ in both], dim=-1), _cat_rows([j for _, j in both])

    def to(self, device: torch.device | str) -> ContactGeometry:
        """A copy with every part's tensors on ``device``."""
        return ContactGeometry(tuple(p.to(device) for p in self.parts))


def _cat_rows(jacs: list[SparseJacobian]) -> SparseJacobian:
    """Sparse rows of several parts, part after part, entries padded to the largest ``m``
    (a padded entry: zero values at the row's last point, so that a row's points stay
    those it touches; ``sparse_gram`` skips rows whose point ranges do not overlap)."""
    m = max(j.points.shape[-1] for j in jacs)
    batch = broadcast_shapes(*(j.points.shape[:-2] for j in jacs))
    points = []
    for j in jacs:
        p = j.points
        if p.shape[-1] < m:
            p = torch.cat([p, p[..., -1:].expand(*p.shape[:-1], m - p.shape[-1])], -1)
        points.append(p.expand(*batch, p.shape[-2], m))
    values = [torch.nn.functional.pad(j.values, (0, 0, 0, m - j.points.shape[-1])) for j in jacs]
    return SparseJacobian(torch.cat(points, -2), torch.cat(values, -4))
