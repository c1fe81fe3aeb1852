"""Holonomic equality constraints Phi(x) = 0 on point sets, fully vectorised.

Two kinds of constraints cover every built-in system:

- **dot constraints** ``(y_a - y_b) . (y_c - y_e) = target``, one scalar
  equation each, where ``y`` is the state's points followed by fixed anchor
  points: index ``i < num_points`` is state point i and index
  ``num_points + j`` is anchor j. Squared distances between points
  (a = c, b = e), a point's squared distance to a fixed pivot, and the unit
  length and mutual orthogonality of an extended body's axes are all of this
  form.
- **linear constraints** ``sum_p w_p x_p = anchor``, ``dim`` scalar equations
  each (pins, ball joints at a material point of an extended body).

Equations are ordered dot constraints first, then linear constraint j,
coordinate c at ``E_dot + j * dim + c``. Flattened coordinates are point-major
(``p * dim + c``), so ``J_E: (..., E, P*dim)``.

With ``u = y_a - y_b`` and ``w = y_c - y_e``, everything is analytic:
``dPhi/dx = (S_a - S_b) w + (S_c - S_e) u`` (S_i selects point i), and since
``J_E v = w . (v_a - v_b) + u . (v_c - v_e)``,
``(D_x(J_E v)) v = 2 (v_a - v_b) . (v_c - v_e)``; linear constraints have a
constant Jacobian ``kron(W, I_dim)`` and a zero second-order term.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import torch
import torch.nn.functional as F
from torch import Tensor

from diffcontact.fastops import dot_last, left_matmul
from diffcontact.shapes import broadcast_shapes

__all__ = [
    "EqualityConstraints",
    "ball_joint",
    "chain_constraints",
    "concat_constraints",
    "dot_constraints",
    "linear_constraints",
    "rigid_body_constraints",
]

_FLOAT = torch.float64


def _as_float(value: Tensor | Sequence[float] | float, name: str) -> Tensor:
    t = value if isinstance(value, Tensor) else torch.as_tensor(value, dtype=_FLOAT)
    if not t.is_floating_point():
        t = t.to(_FLOAT)
    if not bool(torch.isfinite(t.detach()).all()):
        raise ValueError(f"{name} must be finite; got {t}")
    return t


@dataclass(frozen=True, eq=False)
class EqualityConstraints:
    """A set of holonomic constraints on ``num_points`` points in ``dim`` dims.

    Attributes:
        num_points: P, the number of state points the indices refer to. The
            methods accept states with more points (extra points unconstrained).
        dim: spatial dimension (2 or 3).
        dot_index: ``(E_dot, 4)`` int64 indices (a, b, c, e) into the state
            points followed by the anchors.
        dot_target: ``(E_dot,)`` right-hand sides.
        lin_weight: ``(E_lin, P)`` weights w of the linear constraints.
        lin_anchor: ``(E_lin, dim)`` their right-hand sides.
        anchors: ``(A, dim)`` fixed anchor points.

    Build instances with :func:`dot_constraints`, :func:`linear_constraints`,
    :func:`rigid_body_constraints`, :func:`chain_constraints`,
    :func:`ball_joint`, :meth:`empty` and combine them with
    :func:`concat_constraints`. Stored float tensors are cast to the dtype and
    device of ``x`` when evaluated (they may carry gradients).
    """

    num_points: int
    dim: int
    dot_index: Tensor
    dot_target: Tensor
    lin_weight: Tensor
    lin_anchor: Tensor
    anchors: Tensor

    def __post_init__(self) -> None:
        P, dim = self.num_points, self.dim
        if P < 0 or dim < 1:
            raise ValueError(f"need num_points >= 0 and dim >= 1; got {P}, {dim}")
        n_anchor = self.anchors.shape[0] if self.anchors.dim() == 2 else -1
        if self.anchors.dim() != 2 or self.anchors.shape[1] != dim:
            raise ValueError(f"anchors must be (A, {dim}); got {tuple(self.anchors.shape)}")
        if self.dot_index.dim() != 2 or self.dot_index.shape[1] != 4:
            raise ValueError(f"dot_index must be (E_dot, 4); got {tuple(self.dot_index.shape)}")
        if self.dot_index.dtype != torch.int64:
            raise ValueError(f"dot_index must be int64; got {self.dot_index.dtype}")
        if self.dot_target.shape != (self.dot_index.shape[0],):
            raise ValueError(
                f"dot_target must be ({self.dot_index.shape[0]},); "
                f"got {tuple(self.dot_target.shape)}"
            )
        if self.dot_index.numel() and (
            int(self.dot_index.min()) < 0 or int(self.dot_index.max()) >= P + n_anchor
        ):
            raise ValueError(
                f"dot_index entries must lie in [0, num_points + num_anchors) = [0, {P + n_anchor})"
            )
        if self.lin_weight.dim() != 2 or self.lin_weight.shape[1] != P:
            raise ValueError(f"lin_weight must be (E_lin, {P}); got {tuple(self.lin_weight.shape)}")
        if self.lin_anchor.shape != (self.lin_weight.shape[0], dim):
            raise ValueError(
                f"lin_anchor must be ({self.lin_weight.shape[0]}, {dim}); "
                f"got {tuple(self.lin_anchor.shape)}"
            )

    # ------------------------------------------------------------------ sizes
    @property
    def num_dot(self) -> int:
        """Number of dot constraints E_dot."""
        return self.dot_index.shape[0]

    @property
    def num_linear(self) -> int:
        """Number of linear (vector) constraints E_lin, each ``dim`` equations."""
        return self.lin_weight.shape[0]

    @property
    def num_anchors(self) -> int:
        """Number of fixed anchor points A."""
        return self.anchors.shape[0]

    @property
    def num_equations(self) -> int:
        """Number of scalar equations ``E = E_dot + E_lin * dim``."""
        return self.num_dot + self.num_linear * self.dim

    # ----------------------------------------------------------- constructors
    @classmethod
    def empty(cls, num_points: int, dim: int) -> EqualityConstraints:
        """No constraints (E = 0) on ``num_points`` points in ``dim`` dims."""
        return cls(
            num_points=num_points,
            dim=dim,
            dot_index=torch.zeros(0, 4, dtype=torch.int64),
            dot_target=torch.zeros(0, dtype=_FLOAT),
            lin_weight=torch.zeros(0, num_points, dtype=_FLOAT),
            lin_anchor=torch.zeros(0, dim, dtype=_FLOAT),
            anchors=torch.zeros(0, dim, dtype=_FLOAT),
        )

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> EqualityConstraints:
        """Copy with float tensors moved/cast (indices only moved)."""
        return EqualityConstraints(
            num_points=self.num_points,
            dim=self.dim,
            dot_index=self.dot_index.to(device=device),
            dot_target=self.dot_target.to(device=device, dtype=dtype),
            lin_weight=self.lin_weight.to(device=device, dtype=dtype),
            lin_anchor=self.lin_anchor.to(device=device, dtype=dtype),
            anchors=self.anchors.to(device=device, dtype=dtype),
        )

    def split(self, size: int) -> EqualityConstraints | None:
        """The constraints of one group, if they act on groups of points independently.

        When the points form ``num_points / size`` consecutive groups of ``size`` points
        (e.g. extended bodies without joints), every equation involves the points of one
        group only, the equations are ordered group by group, and every group has the same
        equations on its own points (same local indices and targets), the dynamics of the
        groups decouple: they can run as a batch of groups of ``size`` points
        (:func:`~diffcontact.mechanics.dynamics.lagrangian_vector_field` on states
        ``(..., groups, size, dim)``), with ``E / groups`` equations instead of ``E``.

        Returns:
            The first group's constraints on ``size`` points, or ``None`` if they do not
            split so (anchors and linear constraints never do: they are left to the dense
            path).
        """
        P = self.num_points
        if size <= 0 or P % size or P // size < 2 or self.num_linear or self.num_anchors:
            return None
        groups, E = P // size, self.num_dot
        if E == 0 or E % groups:
            return None
        index = self.dot_index.cpu().reshape(groups, E // groups, 4)
        offset = (torch.arange(groups) * size).view(groups, 1, 1)
        local = index - offset
        target = self.dot_target.detach().cpu().reshape(groups, E // groups)
        if local.min() < 0 or local.max() >= size:
            return None
        if not (local == local[0]).all() or not (target == target[0]).all():
            return None
        return dot_constraints(
            local[0].tolist(), target[0].tolist(), dim=self.dim, num_points=size
        ).to(device=self.dot_index.device, dtype=self.dot_target.dtype)

    # ---------------------------------------------------------------- helpers
    def _check(self, x: Tensor, name: str = "x") -> None:
        if x.dim() < 2 or x.shape[-1] != self.dim or x.shape[-2] < self.num_points:
            raise ValueError(
                f"{name} must have shape (..., P, {self.dim}) with P >= {self.num_points}; "
                f"got {tuple(x.shape)}"
            )

    @cached_property
    def _index_selectors(self) -> tuple[Tensor, Tensor]:
        """``(S_a - S_b, S_c - S_e)``: two ``(E_dot, P + A)`` float64 constants."""
        one_hot = F.one_hot(self.dot_index, self.num_points + self.num_anchors).to(_FLOAT)
        return one_hot[:, 0] - one_hot[:, 1], one_hot[:, 2] - one_hot[:, 3]

    def _selectors(
        self, x: Tensor, offsets: bool = True
    ) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None]:
        """Difference selectors over the state points and constant anchor offsets.

        Returns ``G_ab, G_ce: (E_dot, P_x)`` with ``u = G_ab x + u0``,
        ``w = G_ce x + w0`` and ``u0, w0: (E_dot, dim)``, or ``None`` for both when
        there are no anchors or ``offsets`` is false (the callers that need only
        differences of points: no product, no addition).
        """
        P, P_x = self.num_points, x.shape[-2]
        key = (x.dtype, x.device, P_x)
        tables = self._selector_tables.get(key)
        if tables is None:  # constants of the indices: made once per dtype, device and P_x
            G_ab, G_ce = (G.to(dtype=x.dtype, device=x.device) for G in self._index_selectors)
            A_ab, A_ce = G_ab[:, P:], G_ce[:, P:]
            G_ab, G_ce = G_ab[:, :P], G_ce[:, :P]
            if P_x != P:
                G_ab, G_ce = F.pad(G_ab, (0, P_x - P)), F.pad(G_ce, (0, P_x - P))
            tables = self._selector_tables[key] = (G_ab, G_ce, A_ab, A_ce)
        G_ab, G_ce, A_ab, A_ce = tables
        if not offsets or self.num_anchors == 0:
            return G_ab, G_ce, None, None
        anchors = self.anchors.to(dtype=x.dtype, device=x.device)  # (may carry a gradient)
        return G_ab, G_ce, A_ab @ anchors, A_ce @ anchors

    @cached_property
    def _selector_tables(self) -> dict:
        return {}

    def _lin_weight(self, x: Tensor) -> Tensor:
        W = self.lin_weight.to(dtype=x.dtype, device=x.device)
        P_x = x.shape[-2]
        return W if P_x == self.num_points else F.pad(W, (0, P_x - self.num_points))

    # ------------------------------------------------------------- evaluation
    def phi(self, x: Tensor) -> Tensor:
        """Constraint values ``Phi(x)``.

        Args:
            x: ``(..., P, dim)`` positions.

        Returns:
            ``(..., E)``.
        """
        self._check(x)
        G_ab, G_ce, u0, w0 = self._selectors(x)
        u = _plus(G_ab @ x, u0)
        w = _plus(G_ce @ x, w0)
        target = self.dot_target.to(dtype=x.dtype, device=x.device)
        phi_dot = (u * w).sum(-1) - target
        anchor = self.lin_anchor.to(dtype=x.dtype, device=x.device)
        phi_lin = (self._lin_weight(x) @ x - anchor).flatten(-2)
        phi_dot, phi_lin = _common_batch(phi_dot, phi_lin)
        return torch.cat([phi_dot, phi_lin], dim=-1)

    def relative_residual(self, x: Tensor) -> Tensor:
        """Each equation's ``|Phi(x)|`` without units, for telling data that break the
        constraints (wrong link lengths, pivot or axis points) from rounding and drift.

        A dot-product equation ``u . w = c`` (a length squared, a unit axis, two
        orthogonal axes) over ``max(|u| |w|, |c|)``; a linear one (a point held at a
        pivot) over the state's extent: the largest coordinate range of its points, or
        its largest coordinate if that is larger (a lone point), at least ``1e-12``.

        Args:
            x: ``(..., P, dim)`` positions.

        Returns:
            ``(..., E)``, ordered as :meth:`phi`.
        """
        self._check(x)
        G_ab, G_ce, u0, w0 = self._selectors(x)
        u = _plus(G_ab @ x, u0)
        w = _plus(G_ce @ x, w0)
        target = self.dot_target.to(dtype=x.dtype, device=x.device)
        scale = torch.maximum(u.norm(dim=-1) * w.norm(dim=-1), target.abs())
        rel_dot = ((u * w).sum(-1) - target).abs() / scale.clamp_min(1e-300)
        anchor = self.lin_anchor.to(dtype=x.dtype, device=x.device)
        # the points' spread, or for a lone point its distance from the origin
        spread = (x.amax(-2) - x.amin(-2)).amax(-1)
        extent = torch.maximum(spread, x.abs().amax((-2, -1))).clamp_min(1e-12)  # (...,)
        rel_lin = (self._lin_weight(x) @ x - anchor).abs() / extent[..., None, None]
        rel_dot, rel_lin = _common_batch(rel_dot, rel_lin.flatten(-2))
        return torch.cat([rel_dot, rel_lin], dim=-1)

    def jacobian(self, x: Tensor) -> Tensor:
        """Constraint Jacobian ``J_E = D_x Phi``.

        Args:
            x: ``(..., P, dim)`` positions.

        Returns:
            ``(..., E, P*dim)`` (point-major columns).
        """
        self._check(x)
        P_x, dim = x.shape[-2], self.dim
        G_ab, G_ce, u0, w0 = self._selectors(x)
        u = _plus(left_matmul(G_ab, x), u0)  # (..., E_dot, dim)
        w = _plus(left_matmul(G_ce, x), w0)
        J_dot = G_ab[:, :, None] * w[..., :, None, :] + G_ce[:, :, None] * u[..., :, None, :]
        J_dot = J_dot.flatten(-2)  # (..., E_dot, P_x*dim)
        if self.num_linear == 0:  # (a step's dynamics call this at every RK4 stage)
            return J_dot
        W = self._lin_weight(x)
        eye = torch.eye(dim, dtype=x.dtype, device=x.device)
        J_lin = (W[:, None, :, None] * eye[None, :, None, :]).reshape(
            self.num_linear * dim, P_x * dim
        )
        J_lin = J_lin.expand(*x.shape[:-2], *J_lin.shape)
        return torch.cat([J_dot, J_lin], dim=-2)

    def phi_dot(self, x: Tensor, v: Tensor) -> Tensor:
        """Time derivative ``J_E(x) v``.

        Args:
            x: ``(..., P, dim)`` positions.
            v: ``(..., P, dim)`` velocities.

        Returns:
            ``(..., E)``.
        """
        self._check(x)
        self._check(v, "v")
        G_ab, G_ce, u0, w0 = self._selectors(x)
        u = _plus(G_ab @ x, u0)
        w = _plus(G_ce @ x, w0)
        du = G_ab @ v
        dw = G_ce @ v
        rate_dot = (w * du).sum(-1) + (u * dw).sum(-1)
        rate_lin = (self._lin_weight(x) @ v).flatten(-2)
        rate_dot, rate_lin = _common_batch(rate_dot, rate_lin)
        return torch.cat([rate_dot, rate_lin], dim=-1)

    def velocity_jacobian(self, x: Tensor, v: Tensor) -> Tensor:
        """``D_x(J_E(x) v)`` at fixed v (the x-block of ``D_z Psi`` in S.4).

        Args:
            x: ``(..., P, dim)`` positions (only the shape and dtype matter:
                the result is linear in v and independent of x here).
            v: ``(..., P, dim)`` velocities.

        Returns:
            ``(..., E, P*dim)``; zero rows for linear constraints.
        """
        self._check(x)
        self._check(v, "v")
        G_ab, G_ce, _, _ = self._selectors(x, offsets=False)
        du = left_matmul(G_ab, v)
        dw = left_matmul(G_ce, v)
        K_dot = G_ce[:, :, None] * du[..., :, None, :] + G_ab[:, :, None] * dw[..., :, None, :]
        K_dot = K_dot.flatten(-2)
        batch = broadcast_shapes(x.shape[:-2], v.shape[:-2])
        K_dot = K_dot.expand(*batch, *K_dot.shape[-2:])
        if self.num_linear == 0:
            return K_dot
        K_lin = K_dot.new_zeros(*batch, self.num_linear * self.dim, K_dot.shape[-1])
        return torch.cat([K_dot, K_lin], dim=-2)

    def jacobian_dot_v(self, x: Tensor, v: Tensor) -> Tensor:
        """Second-order term ``(D_x(J_E v)) v`` of ``d^2 Phi / dt^2``.

        Args:
            x: ``(..., P, dim)`` positions.
            v: ``(..., P, dim)`` velocities.

        Returns:
            ``(..., E)``: ``2 (v_a - v_b) . (v_c - v_e)`` for dot constraints,
            0 for linear ones.
        """
        self._check(x)
        self._check(v, "v")
        G_ab, G_ce, _, _ = self._selectors(x, offsets=False)
        term = 2.0 * dot_last(left_matmul(G_ab, v), left_matmul(G_ce, v))
        batch = broadcast_shapes(x.shape[:-2], v.shape[:-2])
        term = term.expand(*batch, term.shape[-1])
        if self.num_linear == 0:
            return term
        return torch.cat([term, term.new_zeros(*batch, self.num_linear * self.dim)], dim=-1)


def _plus(t: Tensor, offset: Tensor | None) -> Tensor:
    return t if offset is None else t + offset


def _common_batch(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    batch = broadcast_shapes(a.shape[:-1], b.shape[:-1])
    return a.expand(*batch, a.shape[-1]), b.expand(*batch, b.shape[-1])


# --------------------------------------------------------------------- builders
def dot_constraints(
    index: Tensor | Sequence[Sequence[int]],
    target: Tensor | Sequence[float],
    dim: int,
    num_points: int,
    anchors: Tensor | Sequence[Sequence[float]] | None = None,
) -> EqualityConstraints:
    """Dot constraints ``(y_a - y_b) . (y_c - y_e) = target``.

    Args:
        index: ``(E, 4)`` indices (a, b, c, e); ``num_points + j`` is anchor j.
        target: ``(E,)`` right-hand sides.
        dim: spatial dimension.
        num_points: number of state points P.
        anchors: ``(A, dim)`` fixed points (none when ``None``).
    """
    idx = torch.as_tensor(index, dtype=torch.int64).reshape(-1, 4)
    tgt = _as_float(target, "target").reshape(-1)
    anc = (
        torch.zeros(0, dim, dtype=_FLOAT)
        if anchors is None
        else _as_float(anchors, "anchors").reshape(-1, dim)
    )
    base = EqualityConstraints.empty(num_points, dim)
    return EqualityConstraints(
        num_points=num_points,
        dim=dim,
        dot_index=idx,
        dot_target=tgt,
        lin_weight=base.lin_weight,
        lin_anchor=base.lin_anchor,
        anchors=anc,
    )


def linear_constraints(
    weights: Tensor | Sequence[Sequence[float]],
    anchor: Tensor | Sequence[Sequence[float]],
) -> EqualityConstraints:
    """Linear constraints ``sum_p weights[j, p] x_p = anchor[j]``.

    Args:
        weights: ``(E_lin, P)`` weights over the state points.
        anchor: ``(E_lin, dim)`` right-hand sides (``dim`` equations each).
    """
    W = _as_float(weights, "weights")
    b = _as_float(anchor, "anchor")
    if W.dim() != 2 or b.dim() != 2 or W.shape[0] != b.shape[0]:
        raise ValueError(
            f"weights must be (E_lin, P) and anchor (E_lin, dim); got "
            f"{tuple(W.shape)} and {tuple(b.shape)}"
        )
    P, dim = W.shape[1], b.shape[1]
    base = EqualityConstraints.empty(P, dim)
    return EqualityConstraints(
        num_points=P,
        dim=dim,
        dot_index=base.dot_index,
        dot_target=base.dot_target,
        lin_weight=W,
        lin_anchor=b,
        anchors=base.anchors,
    )


def rigid_body_constraints(
    first_point: int, dim: int, num_points: int | None = None
) -> EqualityConstraints:
    """Rigidity of one extended body whose points start at ``first_point``.

    The body axes ``x_i - x_0`` (i = 1..dim) have unit length and are mutually
    orthogonal: 3 equations in 2D, 6 in 3D (unit lengths first, then the pairs
    (1, 2), (1, 3), (2, 3)).

    Args:
        first_point: index of the body's centre-of-mass point.
        dim: spatial dimension (2 or 3); the body has ``dim + 1`` points.
        num_points: P (defaults to the smallest that holds the body).
    """
    if first_point < 0:
        raise ValueError(f"first_point must be >= 0; got {first_point}")
    P = first_point + dim + 1 if num_points is None else num_points
    if P < first_point + dim + 1:
        raise ValueError(f"num_points={P} is too small for a body at point {first_point}")
    o = first_point
    axes = [o + i for i in range(1, dim + 1)]
    rows = [[a, o, a, o] for a in axes]
    targets = [1.0] * dim
    for i in range(dim):
        for j in range(i + 1, dim):
            rows.append([axes[i], o, axes[j], o])
            targets.append(0.0)
    return dot_constraints(rows, targets, dim=dim, num_points=P)


def chain_constraints(
    link_lengths: Tensor | Sequence[float],
    dim: int = 2,
    first_point: int = 0,
    pivot: Tensor | Sequence[float] | None = None,
    num_points: int | None = None,
) -> EqualityConstraints:
    """Chain pendulum pinned at a fixed pivot, point masses at the joints.

    Joint i is point ``first_point + i``; link 0 joins the pivot to joint 0 and
    link i joins joint i-1 to joint i: ``|x_i - x_{i-1}|^2 = l_i^2``.

    Args:
        link_lengths: ``(n,)`` positive link lengths (may require grad).
        dim: spatial dimension.
        first_point: index of the first joint.
        pivot: ``(dim,)`` fixed pivot; the origin when ``None``.
        num_points: P (defaults to ``first_point + n``).
    """
    lengths = _as_float(link_lengths, "link_lengths").reshape(-1)
    n = lengths.shape[0]
    if n == 0 or bool((lengths.detach() <= 0).any()):
        raise ValueError(
            f"link_lengths must be a non-empty list of positive numbers; got {lengths}"
        )
    P = first_point + n if num_points is None else num_points
    if first_point < 0 or P < first_point + n:
        raise ValueError(f"num_points={P} cannot hold {n} joints from point {first_point}")
    piv = (
        torch.zeros(1, dim, dtype=lengths.dtype)
        if pivot is None
        else _as_float(pivot, "pivot").reshape(1, dim)
    )
    joints = [first_point + i for i in range(n)]
    previous = [P, *joints[:-1]]  # anchor 0 (the pivot) is index P
    rows = [[j, q, j, q] for j, q in zip(joints, previous, strict=True)]
    return dot_constraints(rows, lengths**2, dim=dim, num_points=P, anchors=piv)


def ball_joint(
    first_point: int,
    body_coords: Tensor | Sequence[float],
    anchor: Tensor | Sequence[float],
    num_points: int | None = None,
) -> EqualityConstraints:
    """Pin a material point of an extended body to a fixed world point.

    The material point with body coordinates r (k numbers) of the body whose
    points are ``first_point .. first_point + k`` sits at
    ``sum_a c_a x_a`` with ``c = (1 - sum r, r_1, ..., r_k)``; the joint imposes
    ``sum_a c_a x_a = anchor`` (``dim`` equations). With k = 0 it pins a point
    mass. Example (gyroscope, pivot at body coords (0, 0, -0.5), origin):
    ``1.5 x_0 - 0.5 x_3 = 0``.

    Args:
        first_point: index of the body's centre-of-mass point.
        body_coords: ``(k,)`` body coordinates r of the joint.
        anchor: ``(dim,)`` world position of the joint.
        num_points: P (defaults to ``first_point + k + 1``).
    """
    r = _as_float(body_coords, "body_coords").reshape(-1)
    b = _as_float(anchor, "anchor").reshape(1, -1)
    k = r.shape[0]
    P = first_point + k + 1 if num_points is None else num_points
    if first_point < 0 or P < first_point + k + 1:
        raise ValueError(f"num_points={P} cannot hold a {k + 1}-point body at {first_point}")
    c = torch.cat([(1.0 - r.sum()).reshape(1), r])
    W = F.pad(c, (first_point, P - first_point - k - 1)).reshape(1, P)
    return linear_constraints(W, b)


def concat_constraints(
    *sets: EqualityConstraints, num_points: int | None = None
) -> EqualityConstraints:
    """Concatenate constraint sets (equations in argument order, per kind).

    Sets may have been built for different ``num_points``; the result uses the
    largest (or ``num_points`` when given) and renumbers anchors.

    Args:
        sets: constraint sets with the same ``dim``.
        num_points: P of the result (default: the largest of the sets).
    """
    if not sets:
        raise ValueError("concat_constraints needs at least one constraint set")
    dims = {s.dim for s in sets}
    if len(dims) != 1:
        raise ValueError(f"all constraint sets must share one dim; got {sorted(dims)}")
    dim = dims.pop()
    P = max(s.num_points for s in sets)
    if num_points is not None:
        if num_points < P:
            raise ValueError(f"num_points={num_points} is smaller than a set's {P}")
        P = num_points
    dtype = sets[0].dot_target.dtype
    for s in sets:
        for t in (s.dot_target, s.lin_weight, s.anchors, s.lin_anchor):
            dtype = torch.promote_types(dtype, t.dtype)
    idx, tgt, W, b, anchors = [], [], [], [], []
    anchor_offset = 0
    for s in sets:
        i = s.dot_index
        i = torch.where(i >= s.num_points, i - s.num_points + P + anchor_offset, i)
        idx.append(i)
        tgt.append(s.dot_target.to(dtype))
        W.append(F.pad(s.lin_weight.to(dtype), (0, P - s.num_points)))
        b.append(s.lin_anchor.to(dtype))
        anchors.append(s.anchors.to(dtype))
        anchor_offset += s.num_anchors
    return EqualityConstraints(
        num_points=P,
        dim=dim,
        dot_index=torch.cat(idx),
        dot_target=torch.cat(tgt),
        lin_weight=torch.cat(W),
        lin_anchor=torch.cat(b),
        anchors=torch.cat(anchors),
    )
