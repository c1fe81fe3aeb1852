"""Circle-circle and circle-line contacts in 2D."""

import math

import pytest
import torch

from diffcontact.geometry import CirclePairs, CircleWalls, Geometry, circles_2d

DT = torch.float64
BOX = [[1, 0, 0], [0, 1, 0], [-1, 0, 1], [0, -1, 1]]


def fd_jacobian(f, x, h=1e-6):
    """Central differences of ``f: (P, dim) -> (K,)``: ``(K, P, dim)``."""
    P, dim = x.shape
    eye = torch.eye(P * dim, dtype=x.dtype).reshape(P * dim, P, dim)
    df = (f(x + h * eye) - f(x - h * eye)) / (2 * h)  # (P*dim, K)
    return df.T.reshape(-1, P, dim)


def perp(a):
    return torch.stack((-a[..., 1], a[..., 0]), dim=-1)


def rigid_state(kinds, gen, spread=1.0):
    """Random positions and rigid velocities; returns x, v, centres, v_centres, omegas."""
    xs, vs, cs, vcs, oms = [], [], [], [], []
    for kind in kinds:
        c = torch.rand(2, generator=gen, dtype=DT) * spread
        vc = torch.randn(2, generator=gen, dtype=DT)
        cs.append(c)
        vcs.append(vc)
        if kind == "point":
            xs.append(c[None])
            vs.append(vc[None])
            oms.append(0.0)
        else:
            phi = float(torch.rand(1, generator=gen)) * 2 * math.pi
            om = float(torch.randn(1, generator=gen)) * 3
            ex = torch.tensor([math.cos(phi), math.sin(phi)], dtype=DT)
            pts = torch.stack((c, c + ex, c + perp(ex)))
            xs.append(pts)
            vs.append(vc + om * perp(pts - c))
            oms.append(om)
    return torch.cat(xs), torch.cat(vs), cs, vcs, oms


def test_is_a_geometry_and_sizes():
    g = circles_2d(["point"] * 5, [0.1] * 5, BOX)
    assert isinstance(g, Geometry)
    assert g.d == 2
    assert g.n_candidates == 10 + 20
    assert circles_2d(["point"] * 3, [0.1] * 3, [[0, 1, 1]], pairs=False).n_candidates == 3


def test_gaps_hand_computed():
    g = circles_2d(["point", "point"], [0.1, 0.2], [*BOX, [0, 2, 2]])
    x = torch.tensor([[0.2, 0.3], [0.5, 0.7]], dtype=DT)
    gaps = g.gaps(x)
    # pair: |(0.3, 0.4)| - 0.3; walls of body 0: x, y, 1-x, 1-y, y+1 minus 0.1
    expected = [0.2, 0.1, 0.2, 0.7, 0.6, 1.2, 0.3, 0.5, 0.3, 0.1, 1.5]
    torch.testing.assert_close(gaps, torch.tensor(expected, dtype=DT))


def test_bp5_numbering_specific_indices():
    radii = [0.05, 0.1, 0.13, 0.15, 0.18]
    x = torch.tensor([[0.1, 0.1], [0.3, 0.2], [0.5, 0.61], [0.8, 0.33], [0.6, 0.9]], dtype=DT)
    gaps = circles_2d(["point"] * 5, radii, BOX).gaps(x)
    # pairs (0,1),(0,2),(0,3),(0,4),(1,2),(1,3): index 5 is (1, 3)
    torch.testing.assert_close(gaps[5], (x[3] - x[1]).norm() - radii[1] - radii[3])
    # body 2 against wall 3 (y = 1 from below): 10 + 4 * 2 + 3 = 21
    torch.testing.assert_close(gaps[21], 1 - x[2, 1] - radii[2])
    # body 4 against wall 0 (x = 0): 10 + 16 + 0
    torch.testing.assert_close(gaps[26], x[4, 0] - radii[4])


def test_cp3_ground_only():
    lengths, radii = [0.35, 0.4, 0.35], [0.05, 0.15, 0.1]
    q = [0.3, 1.2, 2.5]
    pos, x = torch.zeros(2, dtype=DT), []
    for length, qi in zip(lengths, q, strict=True):
        pos = pos + length * torch.tensor([math.sin(qi), -math.cos(qi)], dtype=DT)
        x.append(pos)
    x = torch.stack(x)
    g = circles_2d(["point"] * 3, radii, [[0, 1, 1]], pairs=False)
    gaps = g.gaps(x)
    torch.testing.assert_close(gaps, x[:, 1] + 1 - torch.tensor(radii, dtype=DT))
    J = g.jacobian(x, torch.tensor([2]))
    expected = torch.zeros(1, 2, 3, 2, dtype=DT)
    expected[0, 0, 2] = torch.tensor([0.0, 1.0])  # normal: up, on point 2
    expected[0, 1, 2] = torch.tensor([-1.0, 0.0])  # tangent (-n_y, n_x)
    torch.testing.assert_close(J, expected)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_normal_rows_are_gap_gradient_with_rotating_disks(seed):
    gen = torch.Generator().manual_seed(seed)
    kinds = ["disk", "point", "disk", "disk", "point"]
    radii = [0.2, 0.1, 0.25, 0.15, 0.3]
    g = circles_2d(kinds, radii, [*BOX, [1, 2, -0.5]])
    x, _, _, _, _ = rigid_state(kinds, gen)
    # also off the rigid manifold: the normal row must be D_x gap for any x
    x_off = x + 0.05 * torch.randn(x.shape, generator=gen, dtype=DT)
    for xx in (x, x_off):
        J = g.jacobian(xx, torch.arange(g.n_candidates))
        torch.testing.assert_close(J[:, 0], fd_jacobian(g.gaps, xx), atol=1e-8, rtol=1e-6)
        xg = xx.clone().requires_grad_(True)
        auto = torch.autograd.functional.jacobian(g.gaps, xg)
        torch.testing.assert_close(J[:, 0], auto)


@pytest.mark.parametrize("seed", [3, 4])
def test_contact_velocity_of_spinning_disks(seed):
    gen = torch.Generator().manual_seed(seed)
    kinds = ["disk", "point", "disk", "disk"]
    radii = [0.2, 0.1, 0.25, 0.15]
    walls = [*BOX, [0.3, 1.0, 0.2]]
    g = circles_2d(kinds, radii, walls)
    x, v, cs, vcs, oms = rigid_state(kinds, gen)
    vC = torch.einsum("kdpc,pc->kd", g.jacobian(x, torch.arange(g.n_candidates)), v)

    def rim_velocity(b, p):
        return vcs[b] + oms[b] * perp(p - cs[b])

    expected = []
    for i in range(len(kinds)):
        for j in range(i + 1, len(kinds)):
            n = (cs[j] - cs[i]) / (cs[j] - cs[i]).norm()
            rel = rim_velocity(j, cs[j] - radii[j] * n) - rim_velocity(i, cs[i] + radii[i] * n)
            expected.append(torch.stack((rel @ n, rel @ perp(n))))
    for i in range(len(kinds)):
        for wall in walls:
            n = torch.tensor(wall[:2], dtype=DT)
            n = n / n.norm()
            vel = rim_velocity(i, cs[i] - radii[i] * n)
            expected.append(torch.stack((vel @ n, vel @ perp(n))))
    expected = torch.stack(expected)
    assert any(abs(o) > 0.5 for o in oms)  # the check involves real spin
    torch.testing.assert_close(vC, expected)
    # and the spin matters for the tangent: dropping it changes the answer
    v_nospin = torch.cat(
        [vc[None].expand(3 if k == "disk" else 1, 2) for k, vc in zip(kinds, vcs, strict=True)]
    )
    vC_nospin = torch.einsum("kdpc,pc->kd", g.jacobian(x, torch.arange(g.n_candidates)), v_nospin)
    assert (vC_nospin[:, 1] - expected[:, 1]).abs().max() > 1e-2


def test_batched_and_padded_rows():
    gen = torch.Generator().manual_seed(5)
    kinds = ["disk", "point", "disk"]
    g = circles_2d(kinds, [0.2, 0.1, 0.25], BOX)
    N, T, K = 3, 4, g.n_candidates
    x = torch.stack([torch.stack([rigid_state(kinds, gen)[0] for _ in range(T)]) for _ in range(N)])
    idx = torch.randint(0, K, (N, T, 6), generator=gen)
    idx[..., -2:] = 0  # padding with a valid index
    idx[0, 0, :3] = torch.tensor([1, 3, 14])  # one pair and two walls
    gaps = g.gaps(x)
    J = g.jacobian(x, idx)
    assert gaps.shape == (N, T, K)
    assert J.shape == (N, T, 6, 2, x.shape[-2], 2)
    for n in range(N):
        for t in range(T):
            torch.testing.assert_close(gaps[n, t], g.gaps(x[n, t]))
            full = g.jacobian(x[n, t], torch.arange(K))
            torch.testing.assert_close(J[n, t], full[idx[n, t]])
    # an index vector without batch dims broadcasts over the batch
    J_b = g.jacobian(x, torch.tensor([2, 7]))
    torch.testing.assert_close(J_b, g.jacobian(x, torch.tensor([2, 7]).expand(N, T, 2)))


def test_parts_can_be_used_alone_and_dtype_follows_input():
    pairs = CirclePairs.build(["point", "disk"], [0.1, 0.2])
    walls = CircleWalls.build(["point", "disk"], [0.1, 0.2], BOX)
    x = torch.tensor([[0.5, 0.5], [0.2, 0.5], [1.2, 0.5], [0.2, 1.5]], dtype=torch.float32)
    assert pairs.n_candidates == 1 and walls.n_candidates == 8
    assert pairs.gaps(x).dtype == torch.float32
    torch.testing.assert_close(pairs.gaps(x), torch.tensor([0.0]))
    # the disk's rim point touching wall 0 (x = 0) is its centre - 0.2 * (1, 0):
    # body coordinates (-0.2, 0) -> weights (1.2, -0.2, 0)
    J = walls.jacobian(x, torch.tensor([4]))
    assert J.dtype == torch.float32
    torch.testing.assert_close(J[0, 1, 1:, 1], torch.tensor([1.2, -0.2, 0.0]))


def test_bad_config_messages():
    with pytest.raises(ValueError, match="kind"):
        circles_2d(["ball"], [0.1], BOX)
    with pytest.raises(ValueError, match="radii"):
        circles_2d(["point", "point"], [0.1], BOX)
    with pytest.raises(ValueError, match="wall"):
        circles_2d(["point"], [0.1], [[0, 0, 1]])
    with pytest.raises(ValueError, match="no candidate"):
        circles_2d(["point"], [0.1], [])


@pytest.mark.parametrize("task", ["BP5", "CP3", "BD5"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_separable_dense_rows_equal_the_sparse_assembly(task, dtype):
    """Point-mass geometries build dense rows as frame rows times point weights
    (ContactGeometry.jacobian): bitwise the values of the sparse entries' assembly, the
    same gradient to rounding; disks (BD5) are not separable and take the sparse path."""
    import diffcontact as dc
    from diffcontact.geometry.base import GeometryBase

    system = dc.load_system(task)
    geometry = system.geometry
    assert geometry.separable == (task != "BD5")
    gen = torch.Generator().manual_seed(5)
    z = system.sample_initial_conditions(32, seed=5)
    x = (z[:, 0] + 0.05 * torch.randn(z[:, 0].shape, generator=gen, dtype=z.dtype)).to(dtype)
    idx = torch.randint(0, geometry.n_candidates, (32, 4), generator=gen)
    x = x.requires_grad_()
    dense = geometry.jacobian(x, idx)
    sparse = GeometryBase.jacobian(geometry, x, idx)
    assert dense.shape == sparse.shape == (32, 4, 2, *x.shape[-2:])
    assert torch.equal(dense, sparse)
    if dense.requires_grad:  # pairs: the rows turn with the bodies
        w = torch.randn(dense.shape, generator=gen, dtype=z.dtype).to(dtype)
        (g_dense,) = torch.autograd.grad((dense * w).sum(), x)
        (g_sparse,) = torch.autograd.grad((sparse * w).sum(), x)
        tol = 1e-12 if dtype == torch.float64 else 1e-5
        scale = float(g_sparse.abs().max())
        torch.testing.assert_close(g_dense, g_sparse, rtol=0, atol=tol * scale)
