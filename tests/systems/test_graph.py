"""The body graph: bodies as nodes, constraints and candidate contacts as edges."""

from __future__ import annotations

import re

import pytest
import torch

import diffcontact as dc
from diffcontact.systems import list_tasks
from diffcontact.systems.graph import ENVIRONMENT


@pytest.mark.parametrize("task", list_tasks())
def test_graph_covers_points_and_contacts(task):
    system = dc.load_system(task)
    graph = system.body_graph()
    assert len(graph.bodies) == system.n_bodies == len(system.bodies())
    points = sorted(p for b in graph.bodies for p in b.points)
    assert points == list(range(system.n_points))  # every point in exactly one body
    assert graph.centre_points().tolist() == system.body_points
    contacts = graph.edges_of("contact")
    assert [e.contact for e in contacts] == list(range(system.n_contacts))
    assert [e.name for e in contacts] == system.contact_names
    index = graph.edge_index()
    assert index.shape == (2, len(graph.edges)) and index.dtype == torch.long
    assert int(index.max()) < system.n_bodies and int(index.min()) >= ENVIRONMENT
    for e in graph.edges:
        owners = graph.body_of_point()[list(e.points)].tolist()
        assert set(owners) <= {b for b in e.bodies if b >= 0} | set(owners)
        assert all(b in owners for b in e.bodies if b >= 0), e


@pytest.mark.parametrize("task", ["BP5", "BD5"])
def test_circle_contact_edges_match_the_geometry(task):
    """Edge (i, j) of a pair candidate: gap = |c_i - c_j| - r_i - r_j; (i, world) for walls."""
    system = dc.load_system(task)
    graph = system.body_graph()
    z = system.sample_initial_conditions(4, seed=0)
    x = z[:, 0]
    gaps = system.gaps(x)
    centres = x[:, graph.centre_points()]
    for e in graph.edges_of("contact"):
        i, j = e.bodies
        if j == ENVIRONMENT:
            assert re.fullmatch(rf"body {i} penetrates wall \d+", e.name)
            continue
        ri, rj = graph.bodies[i].radius, graph.bodies[j].radius
        expected = (centres[:, i] - centres[:, j]).norm(dim=-1) - ri - rj
        torch.testing.assert_close(gaps[:, e.contact], expected)


def test_constraint_edges():
    chain = dc.load_system("CP3").body_graph()
    assert [e.bodies for e in chain.edges_of("link")] == [(0, 1), (1, 2)]
    assert [e.bodies for e in chain.edges_of("pin")] == [(0, ENVIRONMENT)]
    rope = dc.load_system("Rope").body_graph()
    springs = rope.edges_of("spring")
    assert springs[0].bodies == (0, ENVIRONMENT) and springs[3].bodies == (3, 2)
    gyro = dc.load_system("Gyro").body_graph()
    assert gyro.bodies[0].kind == "rigid3d" and gyro.bodies[0].points == (0, 1, 2, 3)
    with pytest.raises(ValueError, match="unknown edge kind"):
        gyro.edges_of("hinge")
