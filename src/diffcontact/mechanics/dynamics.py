"""Constrained Lagrangian (S.2) and Hamiltonian (S.4-S.7) dynamics in Cartesian points.

States are ``x, v: (..., P, dim)``; the mass matrix over points
``M: (P, P)`` (or batched ``(..., P, P)``) acts identically on each spatial
coordinate, so the full inverse mass matrix is ``kron(M_inv, I_dim)``.
Constraints are an :class:`~diffcontact.mechanics.constraints.EqualityConstraints`
(``None`` or an empty set means unconstrained).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from diffcontact.fastops import left_matmul, spd_solve
from diffcontact.mechanics.bodies import kron_identity
from diffcontact.mechanics.constraints import EqualityConstraints
from diffcontact.shapes import broadcast_shapes

__all__ = [
    "Mhat_inv",
    "gravity_potential",
    "hamiltonian_flow",
    "hamiltonian_vector_field",
    "lagrangian_vector_field",
    "potential_gradient",
]


def Mhat_inv(M_inv: Tensor, J_E: Tensor) -> Tensor:
    """Constrained inverse mass matrix (S.12).

    ``Mhat^-1 = M^-1 - M^-1 J_E^T (J_E M^-1 J_E^T)^-1 J_E M^-1`` with
    ``M^-1 = kron(M_inv, I_dim)``; the inner system is solved by Cholesky
    (J_E must have full row rank) and the correction is symmetrised.

    Args:
        M_inv: ``(..., P, P)`` inverse mass matrix over points.
        J_E: ``(..., E, D)`` constraint Jacobian, ``D = P * dim``; E may be 0.

    Returns:
        ``(..., D, D)`` symmetric PSD with ``J_E Mhat_inv = 0``; equal to
        ``kron(M_inv, I_dim)`` when E = 0.
    """
    P, D = M_inv.shape[-1], J_E.shape[-1]
    if D % P != 0:
        raise ValueError(f"J_E has {D} columns, not a multiple of P = {P} points")
    Minv_full = kron_identity(M_inv, D // P)
    batch = broadcast_shapes(M_inv.shape[:-2], J_E.shape[:-2])
    if J_E.shape[-2] == 0:
        return Minv_full.expand(*batch, D, D)
    B = Minv_full @ J_E.transpose(-1, -2)  # (..., D, E) = M^-1 J^T
    A = J_E @ B  # (..., E, E)
    C = spd_solve(A, B.transpose(-1, -2))  # (..., E, D) = A^-1 J M^-1
    correction = B @ C
    correction = 0.5 * (correction + correction.transpose(-1, -2))
    return Minv_full - correction


def lagrangian_vector_field(
    x: Tensor,
    v: Tensor,
    M_inv: Tensor,
    grad_V: Tensor,
    constraints: EqualityConstraints | None = None,
) -> Tensor:
    """Acceleration of the constrained Lagrangian dynamics (S.2).

    ``a = M^-1 J^T [J M^-1 J^T]^-1 [J M^-1 grad V - (D_x(J v)) v] - M^-1 grad V``,
    with the inner system solved by Cholesky.

    Args:
        x: ``(..., P, dim)`` positions.
        v: ``(..., P, dim)`` velocities.
        M_inv: ``(P, P)`` or ``(..., P, P)`` inverse mass matrix over points.
        grad_V: ``(..., P, dim)`` gradient of the potential at x.
        constraints: equality constraints (``None``: unconstrained).

    Returns:
        ``(..., P, dim)`` acceleration ``dv/dt`` (``dx/dt = v``).
    """
    f = left_matmul(M_inv, grad_V)  # M^-1 grad V, (..., P, dim)
    if constraints is None or constraints.num_equations == 0:
        return -f
    P, dim = x.shape[-2:]
    J = constraints.jacobian(x)  # (..., E, D)
    Jr = J.unflatten(-1, (P, dim))  # (..., E, P, dim)
    # rows of (M^-1 J^T)^T, (..., E, P, dim); one product for a model's shared masses
    MJ = left_matmul(M_inv if M_inv.dim() == 2 else M_inv.unsqueeze(-3), Jr)
    # products of the flattened (E, P * dim) rows: one batched matmul each (einsum's
    # permutes and copies cost more than the products at these sizes)
    MJf = MJ.flatten(-2)
    A = J @ MJf.transpose(-1, -2)  # (..., E, E)
    rhs = (J @ f.flatten(-2).unsqueeze(-1)).squeeze(-1) - constraints.jacobian_dot_v(x, v)
    lam = spd_solve(A, rhs.unsqueeze(-1))  # (..., E, 1)
    return (lam.transpose(-1, -2) @ MJf).squeeze(-2).unflatten(-1, (P, dim)) - f


def _symplectic(D: int, like: Tensor) -> Tensor:
    """``J = [[0, I_D], [-I_D, 0]]`` (S.5), ``(2D, 2D)``."""
    eye = torch.eye(D, dtype=like.dtype, device=like.device)
    zero = torch.zeros_like(eye)
    return torch.cat([torch.cat([zero, eye], -1), torch.cat([-eye, zero], -1)], -2)


def hamiltonian_flow(
    x: Tensor,
    v: Tensor,
    M_inv: Tensor,
    grad_V: Tensor,
    constraints: EqualityConstraints | None = None,
) -> tuple[Tensor, Tensor]:
    """Both components ``(x_dot, v_dot)`` of the constrained Hamiltonian ODE (S.4-S.7).

    In ``z = (x, p)`` with ``p = M v`` and ``H = p^T M^-1 p / 2 + V(x)`` (S.3),
    ``grad_z H = (grad V, M^-1 p) = (grad V, v)``. The constraints
    ``Psi = (Phi, Phi_dot)`` with ``Phi_dot = J_E M^-1 p`` have

        D_z Psi = [[J_E, 0], [D_x(J_E v), J_E M^-1]]  (2E, 2D),

    and S.4 projects the symplectic flow ``J grad_z H`` with the multipliers
    of the (skew-symmetric, LU-solved) system
    ``(D_z Psi) J (D_z Psi)^T lam = (D_z Psi) J grad_z H``; S.6-S.7 convert
    ``p_dot`` to ``v_dot = M^-1 p_dot``.

    ``x_dot`` is the M-orthogonal projection of v onto ``J_E x_dot = 0``: equal
    to v on consistent states, but off the constraint manifold (e.g. at RK4's
    intermediate stages) it keeps ``Phi`` from drifting, so integrating
    ``(x_dot, v_dot)`` holds the constraints markedly better than ``(v, v_dot)``.

    Args:
        x: ``(..., P, dim)`` positions.
        v: ``(..., P, dim)`` velocities (``M^-1 p``).
        M_inv: ``(P, P)`` or ``(..., P, P)`` inverse mass matrix over points.
        grad_V: ``(..., P, dim)`` gradient of the potential at x.
        constraints: equality constraints (``None``: unconstrained).

    Returns:
        ``(x_dot, v_dot)``, each ``(..., P, dim)``.
    """
    P, dim = x.shape[-2:]
    D = P * dim
    batch = broadcast_shapes(x.shape[:-2], v.shape[:-2], grad_V.shape[:-2], M_inv.shape[:-2])
    Minv_full = kron_identity(M_inv, dim).expand(*batch, D, D)
    grad_H = torch.cat(
        [
            grad_V.expand(*batch, P, dim).reshape(*batch, D),
            v.expand(*batch, P, dim).reshape(*batch, D),
        ],
        dim=-1,
    ).unsqueeze(-1)  # (..., 2D, 1)
    Js = _symplectic(D, x)
    flow = Js @ grad_H  # (..., 2D, 1)
    if constraints is None or constraints.num_equations == 0:
        z_dot = flow
    else:
        E = constraints.num_equations
        J = constraints.jacobian(x).expand(*batch, E, D)
        K = constraints.velocity_jacobian(x, v).expand(*batch, E, D)
        D_psi = torch.cat(
            [torch.cat([J, torch.zeros_like(J)], -1), torch.cat([K, J @ Minv_full], -1)], -2
        )  # (..., 2E, 2D)
        D_psi_T = D_psi.transpose(-1, -2)
        G = D_psi @ Js @ D_psi_T  # (..., 2E, 2E), skew-symmetric
        lam = torch.linalg.solve(G, D_psi @ flow)
        z_dot = flow - Js @ (D_psi_T @ lam)
    x_dot = z_dot[..., :D, :]
    v_dot = Minv_full @ z_dot[..., D:, :]  # S.6
    return (
        x_dot.squeeze(-1).unflatten(-1, (P, dim)),
        v_dot.squeeze(-1).unflatten(-1, (P, dim)),
    )


def hamiltonian_vector_field(
    x: Tensor,
    v: Tensor,
    M_inv: Tensor,
    grad_V: Tensor,
    constraints: EqualityConstraints | None = None,
) -> Tensor:
    """Acceleration of the constrained Hamiltonian dynamics (S.4-S.7).

    The ``v_dot`` component of :func:`hamiltonian_flow`; on consistent states
    it equals :func:`lagrangian_vector_field`.

    Args:
        x: ``(..., P, dim)`` positions.
        v: ``(..., P, dim)`` velocities.
        M_inv: ``(P, P)`` or ``(..., P, P)`` inverse mass matrix over points.
        grad_V: ``(..., P, dim)`` gradient of the potential at x.
        constraints: equality constraints (``None``: unconstrained).

    Returns:
        ``(..., P, dim)`` acceleration ``dv/dt``.
    """
    return hamiltonian_flow(x, v, M_inv, grad_V, constraints)[1]


def potential_gradient(
    V: Callable[[Tensor], Tensor], x: Tensor, create_graph: bool = False
) -> Tensor:
    """``grad_x V(x)`` by autograd, also inside ``torch.no_grad``.

    A potential with a ``gradient(x)`` method (its exact gradient written out, e.g.
    :meth:`diffcontact.learning.models.physical.PotentialMLP.gradient`) is
    differentiated by that method instead: the same value, and a graph that a
    training step differentiates once rather than through autograd's double backward.

    Args:
        V: potential, ``(..., P, dim) -> (...)``.
        x: ``(..., P, dim)`` positions. If ``x`` already requires grad the
            gradient is taken with respect to it (so a caller can differentiate
            through it); otherwise a detached copy is used.
        create_graph: keep the graph of the gradient (needed to differentiate
            the resulting forces wrt x or wrt V's parameters, e.g. in training
            or in gradients of a rollout).

    Returns:
        ``(..., P, dim)``; zeros where V does not depend on x.
    """
    gradient = getattr(V, "gradient", None)
    if callable(gradient):  # the potential's own exact gradient (PotentialMLP.gradient)
        if create_graph:
            return gradient(x)
        with torch.no_grad():
            return gradient(x)
    with torch.enable_grad():
        xg = x if x.requires_grad else x.detach().requires_grad_(True)
        energy = V(xg)
        if not energy.requires_grad:
            return torch.zeros_like(x)
        (grad,) = torch.autograd.grad(
            energy.sum(), xg, create_graph=create_graph, allow_unused=True
        )
    return torch.zeros_like(x) if grad is None else grad


def gravity_potential(x: Tensor, M: Tensor, gravity: Tensor) -> Tensor:
    """Uniform gravity ``V = -g . sum_p (M 1)_p x_p`` for extended bodies.

    The column sums of a body's mass matrix are ``(m, 0, ..., 0)``, so
    ``1^T M x`` is the mass-weighted sum of the centres of mass.

    Args:
        x: ``(..., P, dim)`` positions.
        M: ``(P, P)`` or ``(..., P, P)`` mass matrix over points.
        gravity: ``(dim,)`` or ``(..., dim)`` gravitational acceleration, e.g.
            ``(0, -9.81)``.

    Returns:
        ``(...)`` potential energy.
    """
    weights = M.sum(-1)  # (..., P)
    return -(weights * (x @ gravity.unsqueeze(-1)).squeeze(-1)).sum(-1)
