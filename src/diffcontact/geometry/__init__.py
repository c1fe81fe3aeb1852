"""Collision detection and contact Jacobians.

Each geometry holds static candidate contacts and offers ``gaps(x) -> (..., K)``
for all candidates and ``jacobian(x, idx) -> (..., Ka, d, P, dim)`` (or
``jacobian_sparse``) for a padded subset; see :mod:`.base`.
"""

from .base import (
    ContactGeometry,
    Geometry,
    GeometryBase,
    SparseJacobian,
    assemble_jacobian,
    gather_points,
    jacobian_matvec,
    jacobian_rmatvec,
)
from .circles import CirclePairs, CircleWalls, circles_2d
from .frames import contact_frame, material_point_weights, tangent_basis
from .rim import RimPlane, closest_rim_point
from .rope import RopeBending, RopeStretch, rope_limits

__all__ = [
    "CirclePairs",
    "CircleWalls",
    "ContactGeometry",
    "Geometry",
    "GeometryBase",
    "RimPlane",
    "RopeBending",
    "RopeStretch",
    "SparseJacobian",
    "assemble_jacobian",
    "circles_2d",
    "closest_rim_point",
    "contact_frame",
    "gather_points",
    "jacobian_matvec",
    "jacobian_rmatvec",
    "material_point_weights",
    "rope_limits",
    "tangent_basis",
]
