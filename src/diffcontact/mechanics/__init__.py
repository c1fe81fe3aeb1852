"""Extended bodies, equality constraints, constrained dynamics and RK4.

Pure tensor functions of ``(x, v, params)``; see ``docs/conventions.md`` for
the state layout ``z: (..., 2, P, dim)`` and the point-major flattening.
"""

from diffcontact.mechanics.bodies import (
    assemble_mass_matrix,
    block_diagonal,
    body_inverse_mass_matrix,
    body_mass_matrix,
    chain_points_2d,
    disk_points_2d,
    kinetic_energy,
    kron_identity,
    quaternion_to_matrix,
    rigid_body_points_3d,
)
from diffcontact.mechanics.constraints import (
    EqualityConstraints,
    ball_joint,
    chain_constraints,
    concat_constraints,
    dot_constraints,
    linear_constraints,
    rigid_body_constraints,
)
from diffcontact.mechanics.dynamics import (
    Mhat_inv,
    gravity_potential,
    hamiltonian_flow,
    hamiltonian_vector_field,
    lagrangian_vector_field,
    potential_gradient,
)
from diffcontact.mechanics.integrate import INTEGRATORS, VectorField, rk4_38_step, rk4_step

__all__ = [
    "INTEGRATORS",
    "EqualityConstraints",
    "Mhat_inv",
    "VectorField",
    "assemble_mass_matrix",
    "ball_joint",
    "block_diagonal",
    "body_inverse_mass_matrix",
    "body_mass_matrix",
    "chain_constraints",
    "chain_points_2d",
    "concat_constraints",
    "disk_points_2d",
    "dot_constraints",
    "gravity_potential",
    "hamiltonian_flow",
    "hamiltonian_vector_field",
    "kinetic_energy",
    "kron_identity",
    "lagrangian_vector_field",
    "linear_constraints",
    "potential_gradient",
    "quaternion_to_matrix",
    "rigid_body_constraints",
    "rigid_body_points_3d",
    "rk4_38_step",
    "rk4_step",
]
