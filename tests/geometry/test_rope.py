"""Rope bending and stretch limits."""

import math

import pytest
import torch

from diffcontact.geometry import jacobian_matvec, jacobian_rmatvec, rope_limits
from diffcontact.geometry.base import assemble_jacobian, take_rows

DT = torch.float64
L0 = 0.05


def fd_jacobian(f, x, h=1e-7):
    """Central differences of ``f: (P, dim) -> (K,)``: ``(K, P, dim)``."""
    P, dim = x.shape
    eye = torch.eye(P * dim, dtype=x.dtype).reshape(P * dim, P, dim)
    df = (f(x + h * eye) - f(x - h * eye)) / (2 * h)
    return df.T.reshape(-1, P, dim)


def chain(angles, lengths, anchor=(0.0, 0.0)):
    """Points of a chain from the anchor with absolute segment angles (from +x)."""
    seg = torch.stack((torch.cos(angles), torch.sin(angles)), -1) * lengths.unsqueeze(-1)
    return torch.tensor(anchor, dtype=DT) + seg.cumsum(-2)


def test_numbering_and_hand_gaps():
    geo = rope_limits(10)
    assert geo.d == 1 and geo.n_candidates == 19
    angles = torch.full((10,), -math.pi / 2, dtype=DT)  # hanging straight down
    angles[4:] += 0.3  # joint 3 (point 3, between segments 3 and 4) bends by +0.3
    lengths = torch.full((10,), L0, dtype=DT)
    lengths[0] = 1.3 * L0  # first segment: anchor -> point 0
    lengths[5] = 0.7 * L0
    gaps = geo.gaps(chain(angles, lengths))
    bend = torch.full((9,), 0.2, dtype=DT)
    bend[3] = 0.2 - 0.3
    stretch = torch.full((10,), 0.2 * L0, dtype=DT)
    stretch[0] = 1.2 * L0 - 1.3 * L0
    stretch[5] = 0.7 * L0 - 0.8 * L0
    torch.testing.assert_close(gaps, torch.cat((bend, stretch)))
    assert gaps[9] < 0 and gaps[14] < 0 and gaps[3] < 0  # bending 3, stretch 0 and 5
    # bending the other way gives the same gap (|theta|)
    angles[4:] -= 0.6
    torch.testing.assert_close(rope_limits(10).gaps(chain(angles, lengths))[3], bend[3])


def test_config_options():
    angles = torch.full((4,), -math.pi / 2, dtype=DT)
    angles[2:] += 0.25
    x = chain(angles, torch.full((4,), 0.1, dtype=DT), anchor=(1.0, 2.0))
    geo = rope_limits(
        4, max_angle=0.3, rest_length=0.1, min_ratio=0.5, max_ratio=1.1, anchor=(1.0, 2.0)
    )
    torch.testing.assert_close(
        geo.gaps(x), torch.tensor([0.3, 0.05, 0.3, 0.01, 0.01, 0.01, 0.01], dtype=DT)
    )
    # the anchor enters the first segment only
    moved = rope_limits(4, max_angle=0.3, rest_length=0.1, min_ratio=0.5, max_ratio=1.1)
    diff = (moved.gaps(x) - geo.gaps(x)).abs() > 1e-9
    assert diff.tolist() == [True, False, False, True, False, False, False]
    with pytest.raises(ValueError, match="rest_length"):
        rope_limits(4, rest_length=[0.1, 0.2])
    with pytest.raises(ValueError, match="at least 2"):
        rope_limits(1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rows_are_gap_gradient(seed):
    gen = torch.Generator().manual_seed(seed)
    P = 8
    rel = (torch.rand(P, generator=gen, dtype=DT) * 0.4 + 0.02) * torch.where(
        torch.rand(P, generator=gen) < 0.5, -1.0, 1.0
    ).to(DT)
    angles = -math.pi / 2 + rel.cumsum(0)
    lengths = L0 * (0.65 + 0.7 * torch.rand(P, generator=gen, dtype=DT))
    lengths = torch.where((lengths - L0).abs() < 1e-3, lengths + 2e-3, lengths)
    x = chain(angles, lengths)
    geo = rope_limits(P)
    J = geo.jacobian(x, torch.arange(geo.n_candidates))
    assert J.shape == (2 * P - 1, 1, P, 2)
    torch.testing.assert_close(J[:, 0], fd_jacobian(geo.gaps, x), atol=1e-7, rtol=1e-6)
    # both branches of each limit are exercised (bending left/right, short/long)
    assert (rel[1:] > 0).any() and (rel[1:] < 0).any()
    assert (lengths < L0).any() and (lengths > L0).any()
    # a rigid rotation about the anchor changes no gap: every row annihilates it
    v_rot = torch.stack((-x[:, 1], x[:, 0]), -1)
    torch.testing.assert_close(
        torch.einsum("kpc,pc->k", J[:, 0], v_rot), torch.zeros(2 * P - 1, dtype=DT)
    )


def test_large_rope_padded_subset_and_sparse_products():
    gen = torch.Generator().manual_seed(4)
    P, N, Ka = 200, 6, 12
    geo = rope_limits(P)
    assert geo.n_candidates == 399
    angles = -math.pi / 2 + (0.3 * torch.rand(N, P, generator=gen, dtype=DT) - 0.15).cumsum(-1)
    x = chain(angles, L0 * (0.8 + 0.4 * torch.rand(N, P, generator=gen, dtype=DT)))
    idx = torch.randint(0, 399, (N, Ka), generator=gen)
    idx[:, -3:] = 0  # padding
    idx[0, :3] = torch.tensor([198, 199, 398])  # last joint, first and last stretch
    jac = geo.jacobian_sparse(x, idx)
    J = geo.jacobian(x, idx)
    assert J.shape == (N, Ka, 1, P, 2)
    assert jac.points.shape == (N, Ka, 3)
    for n in range(N):
        full = geo.jacobian(x[n], torch.arange(399))
        torch.testing.assert_close(J[n], full[idx[n]])
    v = torch.randn(N, P, 2, generator=gen, dtype=DT)
    f = torch.randn(N, Ka, 1, generator=gen, dtype=DT)
    torch.testing.assert_close(jacobian_matvec(jac, v), torch.einsum("nkdpc,npc->nkd", J, v))
    torch.testing.assert_close(jacobian_rmatvec(jac, f, P), torch.einsum("nkdpc,nkd->npc", J, f))


@pytest.mark.parametrize("P", [2, 10, 200])
def test_rows_of_every_candidate_match_the_indexed_rows(P):
    """``jacobian_sparse_all`` (the projection's per-iteration rows) equals
    ``jacobian_sparse`` on ``arange(K)``, per part and for the whole rope, entry by entry
    once assembled, on both sides of every limit and over batch dimensions."""
    gen = torch.Generator().manual_seed(P)
    geo = rope_limits(P, anchor=(0.3, -0.1), first_point=0)
    angles = -math.pi / 2 + (0.6 * torch.rand(3, 2, P, generator=gen, dtype=DT) - 0.3).cumsum(-1)
    x = chain(angles, L0 * (0.6 + 0.8 * torch.rand(3, 2, P, generator=gen, dtype=DT)))
    x = x + torch.tensor([0.3, -0.1], dtype=DT)
    K = geo.n_candidates
    every = torch.arange(K).expand(3, 2, K)
    for part in (*geo.parts, geo):
        k = part.n_candidates
        full = part.jacobian_sparse_all(x)
        assert full.points.shape[-2] == k and full.values.shape[:-3] == (3, 2, k)
        want = part.jacobian(x, torch.arange(k).expand(3, 2, k))
        got = assemble_jacobian(full, P)
        torch.testing.assert_close(got, want, rtol=0, atol=0)
        # gaps and rows from one evaluation (the projection's): the same numbers
        gaps, both = part.gaps_and_rows_all(x)
        assert torch.equal(gaps, part.gaps(x)) and torch.equal(both.values, full.values)
        assert torch.equal(both.points.expand_as(full.points), full.points)
    # rows gathered from the full set are the indexed rows, repeated indices included
    idx = torch.randint(0, K, (3, 2, 7), generator=gen)
    rows = take_rows(geo.jacobian_sparse_all(x), idx)
    torch.testing.assert_close(assemble_jacobian(rows, P), geo.jacobian(x, idx), rtol=0, atol=0)
    torch.testing.assert_close(
        assemble_jacobian(rows, P),
        geo.jacobian(x, every).gather(-4, idx[..., None, None, None].expand(3, 2, 7, 1, P, 2)),
        rtol=0,
        atol=0,
    )
