"""The body graph of a system: bodies as nodes; links, pins and contacts as edges.

Graph models (interaction networks) need a system's structure without its
geometry internals: :meth:`System.body_graph` returns a :class:`BodyGraph`
whose nodes are the bodies (with the indices of their points in the state
``z: (..., 2, P, dim)``) and whose edges are

- ``"link"``: a rigid distance constraint between two bodies (chain links);
- ``"spring"``: a spring between two bodies, or a body and the anchor (rope
  segments);
- ``"pin"``: a body pinned to the world (chain pivot, gyroscope pivot);
- ``"contact"``: a candidate contact, numbered as the system's contacts
  (``contact`` is its index, ``0 .. K-1``; ``System.contact_names[contact]``).

An edge joins ``bodies = (i, j)``; ``j = ENVIRONMENT`` (-1) for the world (a
wall, the ground, a pivot, the rope's anchor). ``points`` lists every state
point the interaction involves (a rope bending limit involves three).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["ENVIRONMENT", "Body", "BodyGraph", "Edge"]

ENVIRONMENT = -1
EDGE_KINDS = ("link", "spring", "pin", "contact")


@dataclass(frozen=True)
class Body:
    """One body.

    Attributes:
        index: its number, ``0 .. B-1`` (the order of ``mass``).
        kind: ``"point"`` (a point mass), ``"disk"`` (2D rigid body: centre of
            mass and two axis points) or ``"rigid3d"`` (centre and three axes).
        points: indices of its points in the state (the centre of mass first).
        radius: its collision radius (circles, the gyroscope's rim), or ``None``.
    """

    index: int
    kind: str
    points: tuple[int, ...]
    radius: float | None = None


@dataclass(frozen=True)
class Edge:
    """One interaction (see the module docstring)."""

    kind: str
    bodies: tuple[int, int]
    points: tuple[int, ...]
    contact: int | None = None
    name: str = ""


@dataclass(frozen=True)
class BodyGraph:
    """Bodies and their interactions.

    Attributes:
        bodies: the nodes, in body order.
        edges: the interactions: constraints first, then contacts in contact order.
        n_points: ``P``, points in the state.
    """

    bodies: tuple[Body, ...]
    edges: tuple[Edge, ...]
    n_points: int

    def edges_of(self, kind: str) -> tuple[Edge, ...]:
        """The edges of one kind (``"link"``, ``"spring"``, ``"pin"``, ``"contact"``)."""
        if kind not in EDGE_KINDS:
            raise ValueError(f"unknown edge kind {kind!r}; kinds: {', '.join(EDGE_KINDS)}")
        return tuple(e for e in self.edges if e.kind == kind)

    def edge_index(self, kind: str | None = None, device: torch.device | str = "cpu") -> Tensor:
        """``(2, E)`` long: the bodies of each edge (of ``kind``, or all), -1 for the world."""
        edges = self.edges if kind is None else self.edges_of(kind)
        pairs = [e.bodies for e in edges]
        return torch.tensor(pairs, dtype=torch.long, device=device).reshape(-1, 2).T.contiguous()

    def contact_edge_index(self, device: torch.device | str = "cpu") -> Tensor:
        """``(2, K)`` long: the bodies of every candidate contact, in contact order."""
        return self.edge_index("contact", device)

    def body_of_point(self, device: torch.device | str = "cpu") -> Tensor:
        """``(P,)`` long: the body each state point belongs to."""
        owner = [0] * self.n_points
        for body in self.bodies:
            for p in body.points:
                owner[p] = body.index
        return torch.tensor(owner, dtype=torch.long, device=device)

    def centre_points(self, device: torch.device | str = "cpu") -> Tensor:
        """``(B,)`` long: each body's first point (its centre of mass)."""
        return torch.tensor([b.points[0] for b in self.bodies], dtype=torch.long, device=device)
