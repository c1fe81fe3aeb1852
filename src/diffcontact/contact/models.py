"""Contact models: objects that turn a contact problem into impulses.

A contact model is anything with the :class:`ContactModel` protocol's
``resolve`` method. The simulator (``System.simulate``) does the collision
detection, gathers the active contacts of the states that have any, pads them
to a common count (``active`` marks the real ones) and calls ``resolve`` once
per step for the whole batch; what happens at an impact is the model's alone.
Models are looked up by name in :mod:`diffcontact.contact.registry`.

Built in: :class:`PoissonTwoPhase`, the paper's two-phase (compression /
restitution) impulse with Poisson's hypothesis, as ``"CM"`` (exact ``A``) and
``"CMr"`` (``A + eps I``).

Example, CM with friction switched off, usable by name everywhere::

    from diffcontact.contact import PoissonTwoPhase, register_contact_model

    class Frictionless:
        def __init__(self):
            self.inner = PoissonTwoPhase()

        def resolve(self, J_C, Mhat_inv, v, params, active, d, **kwargs):
            params = params.replace(mu=params.mu * 0)
            return self.inner.resolve(J_C, Mhat_inv, v, params, active, d, **kwargs)

    register_contact_model("Frictionless", Frictionless)
    system.simulate(z0, 100, contact_model="Frictionless")
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

from torch import Tensor

from diffcontact.contact.cone_qp import SolverSettings
from diffcontact.contact.impulse import ImpulseResult, two_phase_impulse
from diffcontact.contact.operator import ContactOperator

__all__ = ["CM", "CMr", "ContactModel", "ContactParams", "ContactState", "PoissonTwoPhase"]


@dataclass(frozen=True)
class ContactParams:
    """Per-contact parameters of the active contacts of a batch of states.

    Attributes:
        mu: ``(n, K)`` friction coefficients (padded entries arbitrary).
        cor: ``(n, K)`` coefficients of restitution in [0, 1].
        eps: ``()`` or ``(n,)`` a regulariser for models that use one (CMr),
            or ``None``.
    """

    mu: Tensor
    cor: Tensor
    eps: Tensor | float | None = None

    def replace(self, **changes: Any) -> ContactParams:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class ContactState:
    """Where the contacts of a step are, for models that look beyond the contact problem.

    Learned contact models (the MLP and interaction-network baselines of
    :mod:`diffcontact.learning.models.baselines`) need the positions of the
    bodies and which candidate each padded contact is. The simulator passes
    one as ``resolve(..., state=...)`` to models whose class sets
    ``needs_contact_state = True``; other models are called exactly as before.

    Attributes:
        x: ``(n, P, dim)`` positions of the states with an active contact
            (after the smooth step, with their graph).
        gaps: ``(n, Ka)`` gaps of the padded contacts as detected (detached;
            padded entries are those of an inactive candidate).
        contact_index: ``(n, Ka)`` long, the candidate index of each padded
            contact (active ones first, in candidate order).
        batch_index: ``(n,)`` long, which of the ``N`` simulated states each row is.
        geometry: the system's contact geometry on ``x``'s device
            (``gaps(x)``, ``jacobian_sparse(x, idx)``), for differentiable gaps.
    """

    x: Tensor
    gaps: Tensor
    contact_index: Tensor
    batch_index: Tensor
    geometry: Any


@runtime_checkable
class ContactModel(Protocol):
    """What the simulator asks of a contact model.

    A model whose class sets ``needs_contact_state = True`` is also given
    ``state=``:class:`ContactState` (a keyword argument only those models get).

    A model whose class sets ``accepts_contact_operator = True`` may be given, in place of
    the dense ``J_C``, a :class:`~diffcontact.contact.operator.ContactOperator` (its
    products with ``J_C`` and ``Mhat^-1``) with ``Mhat_inv=None``: the simulator does so
    where the dense rows would be large and mostly zeros (a long rope's,
    :class:`~diffcontact.geometry.sparse_contact.SparseContact`). Other models always
    get the dense tensors.
    """

    def resolve(
        self,
        J_C: Tensor,
        Mhat_inv: Tensor,
        v: Tensor,
        params: ContactParams,
        active: Tensor,
        d: int,
        *,
        v_C_star: Tensor | None = None,
        settings: SolverSettings | None = None,
    ) -> ImpulseResult:
        """Impulses and post-impact velocities of the active contacts.

        Args:
            J_C: ``(n, K*d, D)`` contact Jacobian, padded rows exactly zero (or a
                ``ContactOperator``, for models that accept one).
            Mhat_inv: ``(n, D, D)`` constrained inverse inertia (S.12) (``None`` with
                an operator).
            v: ``(n, D)`` pre-impact velocities.
            params: :class:`ContactParams` of the ``K`` (padded) contacts.
            active: ``(n, K)`` bool, the real contacts; padded ones must get
                exactly zero impulse.
            d: contact-space dimension (1, 2 or 3).
            v_C_star: ``(n, K*d)`` penetration-compensation target, or ``None``.
            settings: cone-QP solver settings, for models that use the solver.

        Returns:
            An :class:`~diffcontact.contact.ImpulseResult` (``v_plus: (n, D)``,
            ``f_c``, ``f_r: (n, K*d)``; a one-phase model returns its impulse as
            ``f_c`` and zeros as ``f_r``).
        """
        ...


class PoissonTwoPhase:
    """The paper's contact model: two phases, Poisson's restitution, cone QPs.

    Compression (5), then restitution (7) with ``f_r,n >= e_P f_c,n``
    (:func:`~diffcontact.contact.two_phase_impulse`).

    Args:
        regularized: ``False`` for CM (``A = J_C Mhat^-1 J_C^T``), ``True`` for
            CMr (``A + eps I``).
        eps: CMr's regulariser, fixed with the model (a number, or a tensor
            that may require grad); ``None`` takes it from the contact
            parameters (``PhysicalParams.eps``, one per trajectory if you like),
            which default to 0.01.

    It accepts a :class:`~diffcontact.contact.operator.ContactOperator` in place of the
    dense ``J_C`` (``accepts_contact_operator``).
    """

    accepts_contact_operator = True

    def __init__(self, regularized: bool = False, eps: float | Tensor | None = None) -> None:
        if eps is not None and not regularized:
            raise ValueError("eps is CMr's regulariser; CM (regularized=False) takes none")
        if isinstance(eps, (int, float)) and not eps > 0:
            raise ValueError(f"eps must be positive, got {eps!r}")
        self.regularized = bool(regularized)
        self.eps = eps

    def __repr__(self) -> str:
        if not self.regularized:
            return "PoissonTwoPhase(CM)"
        return f"PoissonTwoPhase(CMr, eps={'from params' if self.eps is None else self.eps})"

    def resolve(
        self,
        J_C: Tensor | ContactOperator,
        Mhat_inv: Tensor | None,
        v: Tensor,
        params: ContactParams,
        active: Tensor,
        d: int,
        *,
        v_C_star: Tensor | None = None,
        settings: SolverSettings | None = None,
    ) -> ImpulseResult:
        eps = None
        if self.regularized:
            eps = self.eps if self.eps is not None else params.eps
            if eps is None:
                eps = 0.01
        return two_phase_impulse(
            J_C,
            Mhat_inv,
            v,
            params.mu,
            params.cor,
            active,
            d,
            v_C_star=v_C_star,
            eps=eps,
            settings=settings,
        )


def CM() -> PoissonTwoPhase:
    """Registry factory of ``"CM"``: :class:`PoissonTwoPhase` without regulariser."""
    return PoissonTwoPhase(regularized=False)


def CMr(eps: float | Tensor | None = None) -> PoissonTwoPhase:
    """Registry factory of ``"CMr"``: :class:`PoissonTwoPhase` with ``A + eps I``.

    ``eps=None`` (default) takes the regulariser from the physical parameters
    (``PhysicalParams.eps``, 0.01 unless set).
    """
    return PoissonTwoPhase(regularized=True, eps=eps)
