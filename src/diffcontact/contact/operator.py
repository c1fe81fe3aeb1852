"""The contact problem's linear maps, with or without the dense contact Jacobian.

The two-phase impulse (:func:`~diffcontact.contact.two_phase_impulse`) and the
penetration target (:func:`~diffcontact.contact.penetration_target`) use the contact
Jacobian ``J_C: (n, K*d, D)`` and the constrained inverse inertia ``Mhat_inv: (n, D, D)``
only through five maps:

- ``J_C v`` (:meth:`ContactOperator.contact_velocity`),
- ``J_C^T f`` (:meth:`ContactOperator.generalized_impulse`),
- ``Mhat^-1 J_C^T f`` (:meth:`ContactOperator.velocity_change`),
- ``A = J_C Mhat^-1 J_C^T`` (:meth:`ContactOperator.delassus`),
- ``J_C J_C^T`` (:meth:`ContactOperator.gram`).

A :class:`ContactOperator` is anything that provides them; one that also has
``to(dtype)`` (both built in do) is cast to the solver's compute dtype when the states are
narrower (float32 states: the impulse's products formed in float64,
:func:`~diffcontact.contact.two_phase_impulse`). :class:`DenseContact` computes
them from the dense matrices (every system, every device). A long rope's rows touch two
or three of its hundreds of points, and its masses are point masses without equality
constraints (a diagonal ``Mhat^-1``): there
:class:`~diffcontact.geometry.sparse_contact.SparseContact` computes the same maps from
the rows' few entries, without the ``(n, K*d, D)`` zeros.

The simulator passes an operator (as ``J_C``, with ``Mhat_inv=None``) only to contact
models whose class sets ``accepts_contact_operator = True`` (the four built in: CM, CMr,
LCP and Coulomb); every other model gets the dense ``J_C`` and ``Mhat_inv`` as before.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch
from torch import Tensor

from diffcontact.fastops import times_matrix

__all__ = ["ContactOperator", "DenseContact", "as_operator"]


@runtime_checkable
class ContactOperator(Protocol):
    """The linear maps of the contact problem of ``n`` states (``m = K*d`` contact rows,
    ``D`` Cartesian coordinates; padded rows are exactly zero)."""

    def contact_velocity(self, v: Tensor) -> Tensor:
        """``J_C v``: ``(n, D) -> (n, m)``."""
        ...

    def generalized_impulse(self, f: Tensor) -> Tensor:
        """``J_C^T f``: ``(n, m) -> (n, D)``."""
        ...

    def velocity_change(self, f: Tensor) -> Tensor:
        """``Mhat^-1 J_C^T f``: ``(n, m) -> (n, D)``."""
        ...

    def delassus(self) -> Tensor:
        """``A = J_C Mhat^-1 J_C^T``: ``(n, m, m)``, symmetric."""
        ...

    def gram(self) -> Tensor:
        """``J_C J_C^T``: ``(n, m, m)``."""
        ...

    def dense(self) -> Tensor:
        """``J_C``: ``(n, m, D)``, for what needs the rows themselves."""
        ...


class DenseContact:
    """:class:`ContactOperator` of a dense ``J_C: (..., m, D)`` and ``Mhat_inv: (..., D, D)``
    (``None``: only the maps without it, :meth:`gram`, :meth:`contact_velocity` and
    :meth:`generalized_impulse`).

    ``J_C Mhat^-1`` is computed once, on first use (one product where ``Mhat_inv`` is one
    matrix broadcast over the batch, :func:`~diffcontact.fastops.times_matrix`).
    """

    def __init__(self, J_C: Tensor, Mhat_inv: Tensor | None) -> None:
        self.J_C = J_C
        self.Mhat_inv = Mhat_inv
        self._JM: Tensor | None = None

    def _rows_times_minv(self) -> Tensor:  # J_C Mhat^-1
        if self.Mhat_inv is None:
            raise ValueError("this DenseContact has no Mhat_inv")
        if self._JM is None:
            self._JM = times_matrix(self.J_C, self.Mhat_inv)
        return self._JM

    def contact_velocity(self, v: Tensor) -> Tensor:
        return (self.J_C @ v.unsqueeze(-1)).squeeze(-1)

    def generalized_impulse(self, f: Tensor) -> Tensor:
        return (self.J_C.transpose(-1, -2) @ f.unsqueeze(-1)).squeeze(-1)

    def velocity_change(self, f: Tensor) -> Tensor:
        return (self._rows_times_minv().transpose(-1, -2) @ f.unsqueeze(-1)).squeeze(-1)

    def delassus(self) -> Tensor:
        A = self._rows_times_minv() @ self.J_C.transpose(-1, -2)
        return 0.5 * (A + A.transpose(-1, -2))

    def gram(self) -> Tensor:
        return self.J_C @ self.J_C.transpose(-1, -2)

    def dense(self) -> Tensor:
        return self.J_C

    def to(self, dtype: torch.dtype) -> DenseContact:
        """The same operator in ``dtype`` (its products then formed in ``dtype``)."""
        M = None if self.Mhat_inv is None else self.Mhat_inv.to(dtype)
        return DenseContact(self.J_C.to(dtype), M)


def as_operator(J_C: Tensor | ContactOperator, Mhat_inv: Tensor | None) -> ContactOperator:
    """``J_C`` itself where it is a :class:`ContactOperator` (then ``Mhat_inv`` must be
    ``None``: the operator carries it), else :class:`DenseContact` of the two tensors."""
    if isinstance(J_C, Tensor):
        return DenseContact(J_C, Mhat_inv)
    if Mhat_inv is not None:
        raise ValueError(
            "J_C is a ContactOperator, which carries Mhat^-1: pass Mhat_inv=None with it"
        )
    if not isinstance(J_C, ContactOperator):
        raise TypeError(f"J_C must be a tensor or a ContactOperator, got {type(J_C).__name__}")
    return J_C
