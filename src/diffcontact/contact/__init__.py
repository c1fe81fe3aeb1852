"""Contact layer: the batched friction-cone QP and the two-phase impulse."""

from diffcontact.contact.cone_qp import ConeQPError, SolverSettings, SolverStatus, solve_cone_qp
from diffcontact.contact.impulse import (
    CONTACT_MODELS,
    ImpulseResult,
    penetration_target,
    two_phase_impulse,
)

__all__ = [
    "CONTACT_MODELS",
    "ConeQPError",
    "ImpulseResult",
    "SolverSettings",
    "SolverStatus",
    "penetration_target",
    "solve_cone_qp",
    "two_phase_impulse",
]
