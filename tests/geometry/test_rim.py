"""Disk rim against a plane in 3D (gyroscope)."""

import math

import torch

from diffcontact.geometry import RimPlane, closest_rim_point

DT = torch.float64
R = 0.3


def fd_jacobian(f, x, h=1e-6):
    """Central differences of ``f: (P, dim) -> (K,)``: ``(K, P, dim)``."""
    P, dim = x.shape
    eye = torch.eye(P * dim, dtype=x.dtype).reshape(P * dim, P, dim)
    df = (f(x + h * eye) - f(x - h * eye)) / (2 * h)
    return df.T.reshape(-1, P, dim)


def random_rotations(n, gen):
    q, r = torch.linalg.qr(torch.randn(n, 3, 3, generator=gen, dtype=DT))
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1)).unsqueeze(-2)
    return q * torch.det(q)[:, None, None]  # det +1


def body(x0, rot):
    """Points (..., 4, 3): x0 and x0 + each column of rot."""
    return torch.cat((x0.unsqueeze(-2), x0.unsqueeze(-2) + rot.transpose(-1, -2)), dim=-2)


def test_gap_hand_computed_upright_and_tilted():
    geo = RimPlane.build()  # R = 0.3, wall y = -0.33
    x0 = torch.tensor([0.0, 0.0, 0.5], dtype=DT)
    torch.testing.assert_close(
        geo.gaps(body(x0, torch.eye(3, dtype=DT))), torch.tensor([0.03], dtype=DT)
    )
    alpha = 0.4  # rotate about the x axis: e2 = (0, cos, sin), e3 = (0, -sin, cos)
    c, s = math.cos(alpha), math.sin(alpha)
    rot = torch.tensor([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=DT)
    x = body(torch.tensor([0.1, 0.05, 0.5], dtype=DT), rot)
    torch.testing.assert_close(geo.gaps(x), torch.tensor([0.05 + 0.33 - R * c], dtype=DT))
    p, _, _, _ = closest_rim_point(
        x, torch.tensor(R, dtype=DT), torch.tensor([0.0, 1, 0], dtype=DT)
    )
    torch.testing.assert_close(p, x[0] - R * rot[:, 1])


def test_closest_point_minimises_over_dense_rim_sampling():
    gen = torch.Generator().manual_seed(0)
    n_bodies = 64
    rot = random_rotations(n_bodies, gen)
    x0 = torch.randn(n_bodies, 3, generator=gen, dtype=DT)
    planes = [[0, 1, 0, 0.33], [1, -2, 0.5, 0.1]]
    geo = RimPlane.build(planes=planes)
    x = body(x0, rot)
    gaps = geo.gaps(x)  # (N, 2)
    theta = torch.linspace(0, 2 * math.pi, 20001, dtype=DT)[:-1]
    e1, e2 = rot[:, None, :, 0], rot[:, None, :, 1]
    rim = x0[:, None] + R * (torch.cos(theta)[:, None] * e1 + torch.sin(theta)[:, None] * e2)
    for j, pl in enumerate(planes):
        n = torch.tensor(pl[:3], dtype=DT)
        sampled = (rim @ n + pl[3]) / n.norm()  # (N, S)
        assert (gaps[:, j] <= sampled.min(-1).values + 1e-12).all()
        assert (gaps[:, j] >= sampled.min(-1).values - 1e-8).all()
    # and the point is on the rim
    p, _, _, _ = closest_rim_point(
        x, torch.tensor(R, dtype=DT), torch.tensor([0.0, 1, 0], dtype=DT)
    )
    torch.testing.assert_close((p - x0).norm(dim=-1), torch.full((n_bodies,), R, dtype=DT))
    torch.testing.assert_close(((p - x0) * rot[..., 2]).sum(-1), torch.zeros(n_bodies, dtype=DT))


def test_normal_rows_are_gap_gradient():
    gen = torch.Generator().manual_seed(1)
    geo = RimPlane.build(first_points=(1,), planes=[[0, 1, 0, 0.33], [0.2, 0.3, -1, 0.0]])
    for rot, x0 in zip(
        random_rotations(4, gen), torch.randn(4, 3, generator=gen, dtype=DT), strict=True
    ):
        x = torch.cat(
            (torch.randn(1, 3, generator=gen, dtype=DT), body(x0, rot))
        )  # point 0 unrelated
        J = geo.jacobian(x, torch.arange(2))
        assert J.shape == (2, 3, 5, 3)
        torch.testing.assert_close(J[:, 0], fd_jacobian(geo.gaps, x), atol=1e-8, rtol=1e-6)
        assert (J[:, :, 0] == 0).all()
        assert J[:, 0, 4].abs().max() > 1e-3  # the tilt of the axis matters


def test_contact_velocity_of_spinning_body():
    gen = torch.Generator().manual_seed(2)
    geo = RimPlane.build(planes=[[0, 1, 0, 0.33], [1, 1, 1, 0.2]])
    rot = random_rotations(8, gen)
    x0 = torch.randn(8, 3, generator=gen, dtype=DT)
    x = body(x0, rot)
    v0 = torch.randn(8, 3, generator=gen, dtype=DT)
    omega = 5 * torch.randn(8, 3, generator=gen, dtype=DT)
    v = v0[:, None] + torch.linalg.cross(omega[:, None].expand(-1, 4, -1), x - x0[:, None])
    J = geo.jacobian(x, torch.arange(2).expand(8, 2))
    vC = torch.einsum("nkdpc,npc->nkd", J, v)
    for j, pl in enumerate([[0, 1, 0, 0.33], [1, 1, 1, 0.2]]):
        n = torch.tensor(pl[:3], dtype=DT)
        n = (n / n.norm()).expand(8, 3)
        p, _, _, _ = closest_rim_point(x, torch.tensor(R, dtype=DT), n)
        vp = v0 + torch.linalg.cross(omega, p - x0)
        # frame from the J_C rows: tangent rows sum (over points) to t since weights sum to 1
        frame = J[:, j].sum(-2)  # (8, 3, 3)
        torch.testing.assert_close(frame[:, 0], n)
        torch.testing.assert_close(torch.linalg.cross(frame[:, 1], frame[:, 2]), n)
        torch.testing.assert_close(
            frame @ frame.transpose(-1, -2), torch.eye(3, dtype=DT).expand(8, 3, 3)
        )
        torch.testing.assert_close(vC[:, j], (frame @ vp.unsqueeze(-1)).squeeze(-1))


def test_parallel_disk_is_finite():
    geo = RimPlane.build()
    # symmetry axis e3 along -y: the disk is parallel to the wall y = -0.33
    rot = torch.tensor([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=DT)
    x0 = torch.tensor([0.0, -0.2, 0.4], dtype=DT)
    x = body(x0, rot).requires_grad_(True)
    gap = geo.gaps(x)
    torch.testing.assert_close(gap.detach(), torch.tensor([0.13], dtype=DT))
    (grad,) = torch.autograd.grad(gap.sum(), x)
    J = geo.jacobian(x, torch.tensor([0]))
    assert torch.isfinite(grad).all() and torch.isfinite(J).all()
    torch.testing.assert_close(J[0, 0].sum(0), torch.tensor([0.0, 1.0, 0.0], dtype=DT))
    # continuity: a tiny tilt changes the gap by about R * tilt
    tilt = 1e-9
    c, s = math.cos(tilt), math.sin(tilt)
    rot_t = rot @ torch.tensor([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=DT)
    torch.testing.assert_close(geo.gaps(body(x0, rot_t)), gap.detach(), atol=1e-9, rtol=0)


def test_batched_and_padded_rows():
    gen = torch.Generator().manual_seed(3)
    geo = RimPlane.build(planes=[[0, 1, 0, 0.33], [0, 0, 1, 0], [1, 0, 0, 0.5]])
    N, T = 2, 5
    x = body(
        torch.randn(N, T, 3, generator=gen, dtype=DT),
        random_rotations(N * T, gen).reshape(N, T, 3, 3),
    )
    idx = torch.randint(0, 3, (N, T, 4), generator=gen)
    gaps, J = geo.gaps(x), geo.jacobian(x, idx)
    assert gaps.shape == (N, T, 3) and J.shape == (N, T, 4, 3, 4, 3)
    for n in range(N):
        for t in range(T):
            torch.testing.assert_close(gaps[n, t], geo.gaps(x[n, t]))
            torch.testing.assert_close(J[n, t], geo.jacobian(x[n, t], torch.arange(3))[idx[n, t]])
