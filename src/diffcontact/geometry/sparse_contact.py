"""The contact problem of point masses from the rows' sparse entries (long ropes).

A rope limit's row touches two or three of the rope's points. With ``K`` active limits
(``d`` rows each) on a 200-point rope, the dense ``J_C: (n, K*d, 400)`` is almost all
zeros, and its fill and products (``A = J_C Mhat^-1 J_C^T``, ``Mhat^-1 J_C^T f``, and
their backward passes) cost a long rope's rollout a third more time than the entries do
(``python benchmarks/run.py simulate --all-tasks --tasks Rope-D400 --contact-rows
dense``, then ``sparse``; ``systems.system.SPARSE_CONTACT_COLUMNS``). With point masses and no
equality constraints, ``Mhat^-1 = M^-1`` is diagonal (``w``, one inverse mass per point)
and every map the contact impulse needs comes from the entries
(:class:`~diffcontact.contact.operator.ContactOperator`):

    A = J_s J_s^T,  J_s = J_C M^-1/2   (:func:`~diffcontact.geometry.sparse_gram.sparse_gram`)
    J_C v           a gather of v at the entries' points
    M^-1 J_C^T f    a scatter of the entries times f, times w

The same numbers as the dense products to rounding, differentiable in the entries
(positions) and in ``w`` (learned masses).
"""

from __future__ import annotations

import torch
from torch import Tensor

from .base import (
    SparseJacobian,
    assemble_jacobian,
    at_points,
    jacobian_matvec,
    jacobian_rmatvec,
)
from .sparse_gram import sparse_gram

__all__ = ["SparseContact"]


class SparseContact:
    """:class:`~diffcontact.contact.operator.ContactOperator` of sparse rows and point masses.

    Args:
        rows: the rows of ``n`` states' ``K`` (padded) contacts: ``points: (n, K, m)``,
            ``values: (n, K, d, m, dim)``, padded contacts' values exactly zero.
        inverse_mass: ``(P,)`` or ``(n, P)`` each point's inverse mass (the diagonal of
            ``M^-1`` over points; positive).

    :meth:`delassus` and :meth:`gram` use Warp's kernel
    (:func:`~diffcontact.geometry.sparse_gram.sparse_gram`); build one only where it is
    available (:func:`~diffcontact.geometry.sparse_gram.sparse_gram_available`).
    """

    def __init__(self, rows: SparseJacobian, inverse_mass: Tensor) -> None:
        n, K, d, m, dim = rows.values.shape
        self.rows = rows
        self.inverse_mass = inverse_mass
        self.n_points = inverse_mass.shape[-1]
        self._shape = (n, K, d, m, dim)

    def _entries(self, scale: Tensor | None) -> tuple[Tensor, Tensor]:
        """Each of the ``K*d`` rows' entries: ``points: (n, K*d, m)``, ``values: (n, K*d,
        m, dim)`` (times ``scale`` at their points, if given)."""
        n, K, d, m, dim = self._shape
        points = self.rows.points.unsqueeze(-2).expand(n, K, d, m)
        values = self.rows.values
        if scale is not None:
            values = values * at_points(scale, self.rows.points)[:, :, None, :, None]
        return points.reshape(n, K * d, m), values.reshape(n, K * d, m, dim)

    def contact_velocity(self, v: Tensor) -> Tensor:
        n, K, d, _, dim = self._shape
        return jacobian_matvec(self.rows, v.reshape(n, self.n_points, dim)).reshape(n, K * d)

    def generalized_impulse(self, f: Tensor) -> Tensor:
        n, K, d, _, _ = self._shape
        return jacobian_rmatvec(self.rows, f.reshape(n, K, d), self.n_points).flatten(-2)

    def velocity_change(self, f: Tensor) -> Tensor:
        n, _, _, _, dim = self._shape
        impulse = self.generalized_impulse(f).view(n, self.n_points, dim)
        return (impulse * self.inverse_mass.unsqueeze(-1)).flatten(-2)  # w: (P,) or (n, P)

    def delassus(self) -> Tensor:
        return sparse_gram(*self._entries(self.inverse_mass.sqrt()))

    def gram(self) -> Tensor:
        return sparse_gram(*self._entries(None))

    def dense(self) -> Tensor:
        n, K, d, _, _ = self._shape
        return assemble_jacobian(self.rows, self.n_points).reshape(n, K * d, -1)

    def to(self, dtype: torch.dtype) -> SparseContact:
        """The same operator in ``dtype`` (its products then formed in ``dtype``)."""
        rows = SparseJacobian(self.rows.points, self.rows.values.to(dtype))
        return SparseContact(rows, self.inverse_mass.to(dtype))
