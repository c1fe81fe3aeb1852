"""Extended-body mass matrices and state builders."""

import math

import pytest
import torch

from diffcontact.mechanics import (
    assemble_mass_matrix,
    body_inverse_mass_matrix,
    body_mass_matrix,
    chain_constraints,
    chain_points_2d,
    disk_points_2d,
    kinetic_energy,
    kron_identity,
    rigid_body_constraints,
    rigid_body_points_3d,
)

DT = torch.float64


def random_rotation(gen: torch.Generator, *batch: int) -> torch.Tensor:
    """Random proper rotations ``(*batch, 3, 3)``."""
    Q, R = torch.linalg.qr(torch.randn(*batch, 3, 3, generator=gen, dtype=DT))
    Q = Q * torch.sign(torch.diagonal(R, dim1=-2, dim2=-1))[..., None, :]
    det = torch.linalg.det(Q)
    return torch.cat([Q[..., :2], Q[..., 2:] * det[..., None, None]], dim=-1)


def skew(w: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(w[..., 0])
    return torch.stack(
        [
            torch.stack([z, -w[..., 2], w[..., 1]], -1),
            torch.stack([w[..., 2], z, -w[..., 0]], -1),
            torch.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def test_body_mass_matrix_values_and_point_mass():
    m = torch.tensor(2.0, dtype=DT)
    s = torch.tensor([0.1, 0.3], dtype=DT)
    expected = 2.0 * torch.tensor([[1.4, -0.1, -0.3], [-0.1, 0.1, 0.0], [-0.3, 0.0, 0.3]], dtype=DT)
    torch.testing.assert_close(body_mass_matrix(m, s), expected)
    point = body_mass_matrix(m, torch.zeros(0, dtype=DT))
    torch.testing.assert_close(point, torch.tensor([[2.0]], dtype=DT))


def test_body_inverse_matches_inverse_batched():
    gen = torch.Generator().manual_seed(0)
    m = torch.rand(4, generator=gen, dtype=DT) + 0.1
    s = torch.rand(4, 3, generator=gen, dtype=DT) + 0.05
    M = body_mass_matrix(m, s)
    assert M.shape == (4, 4, 4)
    eye = torch.eye(4, dtype=DT).expand(4, 4, 4)
    torch.testing.assert_close(M @ body_inverse_mass_matrix(m, s), eye)


def test_assemble_block_diagonal_and_kron():
    m1 = body_mass_matrix(torch.tensor(1.0, dtype=DT), torch.zeros(0, dtype=DT))
    m2 = body_mass_matrix(torch.tensor([2.0, 3.0], dtype=DT), torch.full((2, 2), 0.5, dtype=DT))
    M = assemble_mass_matrix([m1, m2])
    assert M.shape == (2, 4, 4)
    torch.testing.assert_close(M[1], torch.block_diag(m1, m2[1]))
    K = kron_identity(M, 3)
    torch.testing.assert_close(K[0], torch.kron(M[0], torch.eye(3, dtype=DT)))


def test_disk_points_rigid_and_time_derivative():
    gen = torch.Generator().manual_seed(1)
    c = torch.randn(5, 2, generator=gen, dtype=DT)
    a = torch.randn(5, generator=gen, dtype=DT)
    vel = torch.randn(5, 2, generator=gen, dtype=DT)
    w = torch.randn(5, generator=gen, dtype=DT)
    z = disk_points_2d(c, a, vel, w)
    assert z.shape == (5, 2, 3, 2)
    cons = rigid_body_constraints(0, 2)
    torch.testing.assert_close(cons.phi(z[:, 0]), torch.zeros(5, 3, dtype=DT))
    torch.testing.assert_close(cons.phi_dot(z[:, 0], z[:, 1]), torch.zeros(5, 3, dtype=DT))
    h = 1e-6  # central difference of the rigid motion in time
    fd = (
        disk_points_2d(c + h * vel, a + h * w, vel, w)[:, 0]
        - disk_points_2d(c - h * vel, a - h * w, vel, w)[:, 0]
    ) / (2 * h)
    torch.testing.assert_close(z[:, 1], fd, atol=1e-8, rtol=1e-8)


def test_disk_kinetic_energy_uses_second_moments():
    # uniform disk: s = r^2/4 per axis -> inertia m r^2 / 2
    m, r = 0.3, 0.13
    z = disk_points_2d(
        torch.tensor([0.2, 0.4], dtype=DT),
        torch.tensor(0.7, dtype=DT),
        torch.tensor([1.0, -2.0], dtype=DT),
        torch.tensor(3.0, dtype=DT),
    )
    M = body_mass_matrix(torch.tensor(m, dtype=DT), torch.full((2,), r * r / 4, dtype=DT))
    expected = 0.5 * m * 5.0 + 0.5 * (m * r * r / 2) * 9.0
    assert kinetic_energy(z[1], M).item() == pytest.approx(expected, rel=1e-12)


def test_rigid_body_3d_points_energy_and_velocity():
    gen = torch.Generator().manual_seed(2)
    R = random_rotation(gen, 3)
    c = torch.randn(3, 3, generator=gen, dtype=DT)
    vel = torch.randn(3, 3, generator=gen, dtype=DT)
    omega = torch.randn(3, 3, generator=gen, dtype=DT)
    z = rigid_body_points_3d(c, R, vel, omega)
    assert z.shape == (3, 2, 4, 3)
    cons = rigid_body_constraints(0, 3)
    assert cons.num_equations == 6
    torch.testing.assert_close(cons.phi(z[:, 0]), torch.zeros(3, 6, dtype=DT))
    torch.testing.assert_close(cons.phi_dot(z[:, 0], z[:, 1]), torch.zeros(3, 6, dtype=DT))
    # velocity: d/dt of (c + t vel, expm(t [omega]x) R) at t = 0
    h = 1e-6
    plus = rigid_body_points_3d(c + h * vel, torch.matrix_exp(h * skew(omega)) @ R, vel, omega)
    minus = rigid_body_points_3d(c - h * vel, torch.matrix_exp(-h * skew(omega)) @ R, vel, omega)
    torch.testing.assert_close(z[:, 1], (plus[:, 0] - minus[:, 0]) / (2 * h), atol=1e-8, rtol=0)
    # kinetic energy = translational + body-frame rotational with I_1 = m (s_2 + s_3) etc.
    m = torch.tensor(0.1, dtype=DT)
    s = torch.tensor([0.24, 0.24, 0.04], dtype=DT)
    M = body_mass_matrix(m, s)
    I_body = m * torch.stack([s[1] + s[2], s[0] + s[2], s[0] + s[1]])
    omega_body = (R.transpose(-1, -2) @ omega[..., None])[..., 0]
    expected = 0.5 * m * (vel**2).sum(-1) + 0.5 * (I_body * omega_body**2).sum(-1)
    torch.testing.assert_close(kinetic_energy(z[:, 1], M), expected)


def test_chain_points_2d_satisfy_chain_constraints():
    q = torch.tensor([[0.3, -1.2, 2.0], [math.pi / 2, 0.0, 0.1]], dtype=DT)
    dq = torch.tensor([[1.0, -0.5, 0.2], [0.0, 2.0, -1.0]], dtype=DT)
    lengths = torch.tensor([0.35, 0.4, 0.35], dtype=DT)
    z = chain_points_2d(q, dq, lengths)
    assert z.shape == (2, 2, 3, 2)
    torch.testing.assert_close(z[1, 0, 0], torch.tensor([0.35, 0.0], dtype=DT))
    cons = chain_constraints(lengths)
    torch.testing.assert_close(cons.phi(z[:, 0]), torch.zeros(2, 3, dtype=DT))
    torch.testing.assert_close(cons.phi_dot(z[:, 0], z[:, 1]), torch.zeros(2, 3, dtype=DT))


def test_block_diagonal_places_each_block_on_the_diagonal():
    from diffcontact.mechanics import block_diagonal

    gen = torch.Generator().manual_seed(0)
    blocks = torch.randn(2, 4, 3, 5, generator=gen, dtype=DT)  # 2 stacks of 4 blocks 3 x 5
    out = block_diagonal(blocks)
    assert out.shape == (2, 12, 20)
    for i in range(2):
        torch.testing.assert_close(out[i], torch.block_diag(*blocks[i]))
