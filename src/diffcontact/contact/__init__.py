"""Contact layer: the batched friction-cone QP, the two-phase impulse, contact models.

- :func:`solve_cone_qp`: the batched, differentiable friction-cone QP;
- :func:`two_phase_impulse`: the paper's compression / restitution impulse, on the dense
  ``J_C`` or a :class:`ContactOperator` of it (:class:`DenseContact`, or a long rope's
  sparse rows);
- :func:`solve_coulomb`, :func:`coulomb_two_phase_impulse`: the same with exact
  Coulomb friction (De Saxcé's NCP), contact model ``"Coulomb"``;
- contact models (:class:`ContactModel` protocol, :class:`PoissonTwoPhase` as
  ``"CM"``/``"CMr"``, :class:`NewtonLCP` as ``"LCP"`` with its batched differentiable
  LCP solver :func:`solve_lcp`) and their registry (:func:`register_contact_model`,
  :func:`contact_models`).

Names are imported lazily: ``import diffcontact.contact`` and the registry
load no torch, so the CLI can list contact models cheaply.
"""

from __future__ import annotations

import importlib
from typing import Any

from diffcontact.contact.registry import (
    contact_models,
    create_contact_model,
    register_contact_model,
    unregister_contact_model,
)

_EXPORTS: dict[str, str] = {
    "ConeQPError": "diffcontact.contact.cone_qp",
    "SolverSettings": "diffcontact.contact.cone_qp",
    "SolverStatus": "diffcontact.contact.cone_qp",
    "solve_cone_qp": "diffcontact.contact.cone_qp",
    "ImpulseResult": "diffcontact.contact.impulse",
    "ContactOperator": "diffcontact.contact.operator",
    "DenseContact": "diffcontact.contact.operator",
    "as_operator": "diffcontact.contact.operator",
    "penetration_target": "diffcontact.contact.impulse",
    "two_phase_impulse": "diffcontact.contact.impulse",
    "CoulombSettings": "diffcontact.contact.coulomb",
    "ExactCoulomb": "diffcontact.contact.coulomb",
    "coulomb_two_phase_impulse": "diffcontact.contact.coulomb",
    "solve_coulomb": "diffcontact.contact.coulomb",
    "CM": "diffcontact.contact.models",
    "CMr": "diffcontact.contact.models",
    "ContactModel": "diffcontact.contact.models",
    "ContactParams": "diffcontact.contact.models",
    "ContactState": "diffcontact.contact.models",
    "PoissonTwoPhase": "diffcontact.contact.models",
    "LCP": "diffcontact.contact.lcp",
    "LCPError": "diffcontact.contact.lcp",
    "NewtonLCP": "diffcontact.contact.lcp",
    "lcp_impulse": "diffcontact.contact.lcp",
    "solve_lcp": "diffcontact.contact.lcp",
}

__all__ = [
    "CM",
    "LCP",
    "CMr",
    "ConeQPError",
    "ContactModel",
    "ContactOperator",
    "ContactParams",
    "ContactState",
    "CoulombSettings",
    "DenseContact",
    "ExactCoulomb",
    "ImpulseResult",
    "LCPError",
    "NewtonLCP",
    "PoissonTwoPhase",
    "SolverSettings",
    "SolverStatus",
    "as_operator",
    "contact_models",
    "coulomb_two_phase_impulse",
    "create_contact_model",
    "lcp_impulse",
    "penetration_target",
    "register_contact_model",
    "solve_cone_qp",
    "solve_coulomb",
    "solve_lcp",
    "two_phase_impulse",
    "unregister_contact_model",
]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'diffcontact.contact' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
