"""Constrained Lagrangian / Hamiltonian vector fields and Mhat^-1 (S.2, S.4-S.7, S.12)."""

import math

import pytest
import torch

from diffcontact.mechanics import (
    EqualityConstraints,
    Mhat_inv,
    assemble_mass_matrix,
    ball_joint,
    body_inverse_mass_matrix,
    body_mass_matrix,
    chain_constraints,
    chain_points_2d,
    concat_constraints,
    disk_points_2d,
    gravity_potential,
    hamiltonian_flow,
    hamiltonian_vector_field,
    kron_identity,
    lagrangian_vector_field,
    potential_gradient,
    rigid_body_constraints,
    rigid_body_points_3d,
)

DT = torch.float64
G = 9.81
B = 3  # batch of states per system


def _rotation(gen: torch.Generator, n: int) -> torch.Tensor:
    Q, R = torch.linalg.qr(torch.randn(n, 3, 3, generator=gen, dtype=DT))
    Q = Q * torch.sign(torch.diagonal(R, dim1=-2, dim2=-1))[..., None, :]
    det = torch.linalg.det(Q)
    return torch.cat([Q[..., :2], Q[..., 2:] * det[..., None, None]], dim=-1)


def chain3(seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    masses = torch.tensor([0.2, 0.13, 0.15], dtype=DT)
    lengths = torch.tensor([0.35, 0.4, 0.35], dtype=DT)
    q = torch.rand(B, 3, generator=gen, dtype=DT) * math.pi
    dq = torch.randn(B, 3, generator=gen, dtype=DT)
    z = chain_points_2d(q, dq, lengths)
    M = torch.diag(masses)
    gravity = torch.tensor([0.0, -G], dtype=DT)
    return z[:, 0], z[:, 1], M, torch.diag(1 / masses), chain_constraints(lengths), gravity


def disk(seed: int = 1):
    gen = torch.Generator().manual_seed(seed)
    m, s = torch.tensor(0.3, dtype=DT), torch.full((2,), 0.13**2 / 4, dtype=DT)
    z = disk_points_2d(
        torch.rand(B, 2, generator=gen, dtype=DT),
        torch.rand(B, generator=gen, dtype=DT) * 2 * math.pi,
        torch.randn(B, 2, generator=gen, dtype=DT),
        torch.randn(B, generator=gen, dtype=DT),
    )
    gravity = torch.tensor([0.0, -G], dtype=DT)
    return (
        z[:, 0],
        z[:, 1],
        body_mass_matrix(m, s),
        body_inverse_mass_matrix(m, s),
        rigid_body_constraints(0, 2),
        gravity,
    )


def gyro(seed: int = 2):
    """Gyroscope: mass 0.1, s = (0.24, 0.24, 0.04), pivot at body coords (0, 0, -0.5)."""
    gen = torch.Generator().manual_seed(seed)
    m, s = torch.tensor(0.1, dtype=DT), torch.tensor([0.24, 0.24, 0.04], dtype=DT)
    R = _rotation(gen, B)
    omega = torch.randn(B, 3, generator=gen, dtype=DT) * 3
    centre = 0.5 * R[..., 2]  # pivot at the origin = centre - 0.5 * symmetry axis
    z = rigid_body_points_3d(centre, R, torch.linalg.cross(omega, centre), omega)
    cons = concat_constraints(rigid_body_constraints(0, 3), ball_joint(0, [0, 0, -0.5], [0, 0, 0]))
    gravity = torch.tensor([0.0, 0.0, -G], dtype=DT)
    return z[:, 0], z[:, 1], body_mass_matrix(m, s), body_inverse_mass_matrix(m, s), cons, gravity


SYSTEMS = {"chain3": chain3, "disk": disk, "gyro": gyro}


def grad_V(x, M, gravity):
    return potential_gradient(lambda y: gravity_potential(y, M, gravity), x)


@pytest.mark.parametrize("name", SYSTEMS)
def test_states_are_consistent(name):
    x, v, _, _, cons, _ = SYSTEMS[name]()
    torch.testing.assert_close(cons.phi(x), torch.zeros(B, cons.num_equations, dtype=DT))
    torch.testing.assert_close(cons.phi_dot(x, v), torch.zeros(B, cons.num_equations, dtype=DT))


@pytest.mark.parametrize("name", SYSTEMS)
def test_mhat_inv_properties(name):
    x, _, M, M_inv, cons, _ = SYSTEMS[name]()
    J = cons.jacobian(x)
    Mh = Mhat_inv(M_inv, J)
    D = J.shape[-1]
    assert Mh.shape == (B, D, D)
    torch.testing.assert_close(J @ Mh, torch.zeros_like(J), atol=1e-12, rtol=0)
    torch.testing.assert_close(Mh, Mh.transpose(-1, -2), atol=1e-14, rtol=0)
    eig = torch.linalg.eigvalsh(Mh)
    assert eig.min() > -1e-12
    # rank D - E (one zero eigenvalue per independent constraint)
    assert ((eig > 1e-9).sum(-1) == D - cons.num_equations).all()
    # generalised inverse of the mass matrix on the constraint tangent space
    M_full = kron_identity(M, x.shape[-1])
    torch.testing.assert_close(Mh @ M_full @ Mh, Mh)


def test_mhat_inv_without_constraints_is_kron():
    M_inv = torch.diag(torch.tensor([1.0, 2.0, 4.0], dtype=DT))
    J = torch.zeros(2, 0, 6, dtype=DT)
    Mh = Mhat_inv(M_inv, J)
    assert Mh.shape == (2, 6, 6)
    torch.testing.assert_close(Mh[1], torch.kron(M_inv, torch.eye(2, dtype=DT)))


@pytest.mark.parametrize("name", SYSTEMS)
def test_lagrangian_and_hamiltonian_agree_and_respect_constraints(name):
    x, v, M, M_inv, cons, gravity = SYSTEMS[name]()
    gV = grad_V(x, M, gravity)
    a_L = lagrangian_vector_field(x, v, M_inv, gV, cons)
    a_H = hamiltonian_vector_field(x, v, M_inv, gV, cons)
    assert a_L.shape == x.shape
    torch.testing.assert_close(a_L, a_H, rtol=1e-10, atol=1e-10)
    # d^2 Phi / dt^2 = J a + (D(J v)) v = 0
    J = cons.jacobian(x)
    residual = (J @ a_L.reshape(B, -1, 1))[..., 0] + cons.jacobian_dot_v(x, v)
    torch.testing.assert_close(residual, torch.zeros_like(residual), atol=1e-10, rtol=0)
    # the constraint forces matter: the unconstrained answer is different
    assert (a_L + M_inv @ gV).abs().max() > 1e-2


def test_single_pendulum_matches_analytic():
    l, q, dq = 0.7, torch.tensor([0.3, 2.0], dtype=DT), torch.tensor([1.5, -0.4], dtype=DT)
    z = chain_points_2d(q[:, None], dq[:, None], torch.tensor([l], dtype=DT))
    x, v = z[:, 0], z[:, 1]
    M_inv = torch.tensor([[1 / 0.4]], dtype=DT)
    gV = torch.tensor([0.0, 0.4 * G], dtype=DT).expand(2, 1, 2)
    ddq = -G / l * torch.sin(q)
    radial = torch.stack([torch.sin(q), -torch.cos(q)], -1)
    tangent = torch.stack([torch.cos(q), torch.sin(q)], -1)
    expected = (l * ddq[:, None] * tangent - l * dq[:, None] ** 2 * radial)[:, None, :]
    cons = chain_constraints([l])
    for field in (lagrangian_vector_field, hamiltonian_vector_field):
        torch.testing.assert_close(field(x, v, M_inv, gV, cons), expected)


def test_disk_in_gravity_falls_and_spins_uniformly():
    x, v, M, M_inv, cons, gravity = disk()
    a = lagrangian_vector_field(x, v, M_inv, grad_V(x, M, gravity), cons)
    torch.testing.assert_close(a[:, 0], gravity.expand(B, 2))
    # axis points: a_cm - w^2 e_i (no angular acceleration)
    e = x[:, 1:] - x[:, :1]
    w2 = ((v[:, 1] - v[:, 0]) ** 2).sum(-1)  # |w x e_x|^2 = w^2
    torch.testing.assert_close(a[:, 1:], gravity - w2[:, None, None] * e)


def test_gyroscope_angular_momentum_balance():
    """dL/dt about the pivot equals the gravity torque x_cm x (m g)."""
    x, v, M, M_inv, cons, gravity = gyro()
    for field in (lagrangian_vector_field, hamiltonian_vector_field):
        a = field(x, v, M_inv, grad_V(x, M, gravity), cons)
        dL = torch.linalg.cross(x[:, :, None, :], a[:, None, :, :]).mul(M[..., None]).sum((1, 2))
        torch.testing.assert_close(dL, torch.linalg.cross(x[:, 0], 0.1 * gravity.expand(B, 3)))


@pytest.mark.parametrize("constraints", [None, EqualityConstraints.empty(3, 2)])
def test_unconstrained_fields(constraints):
    gen = torch.Generator().manual_seed(3)
    x, v = torch.randn(2, 4, 3, 2, generator=gen, dtype=DT)
    gV = torch.randn(4, 3, 2, generator=gen, dtype=DT)
    M_inv = torch.diag(torch.tensor([1.0, 0.5, 0.25], dtype=DT))
    for field in (lagrangian_vector_field, hamiltonian_vector_field):
        torch.testing.assert_close(field(x, v, M_inv, gV, constraints), -(M_inv @ gV))


def test_batched_mass_matrix_and_elementwise_consistency():
    x, v, M, M_inv, cons, gravity = chain3()
    gV = grad_V(x, M, gravity)
    scale = torch.tensor([1.0, 2.0, 0.5], dtype=DT)[:, None, None]
    batched = scale * M_inv  # (B, P, P): a different mass scale per state
    for field in (lagrangian_vector_field, hamiltonian_vector_field):
        a = field(x, v, batched, gV, cons)
        for b in range(B):
            torch.testing.assert_close(a[b], field(x[b], v[b], batched[b], gV[b], cons))
    assert Mhat_inv(batched, cons.jacobian(x)).shape == (B, 6, 6)


def test_potential_gradient_modes():
    x = torch.randn(2, 3, 2, dtype=DT)
    M = assemble_mass_matrix(
        [body_mass_matrix(torch.tensor(m, dtype=DT), x.new_zeros(0)) for m in (1.0, 2.0, 3.0)]
    )
    gravity = torch.tensor([0.0, -G], dtype=DT)
    expected = -M.sum(-1)[:, None] * gravity
    with torch.no_grad():
        g = potential_gradient(lambda y: gravity_potential(y, M, gravity), x)
    assert not g.requires_grad
    torch.testing.assert_close(g, expected.expand_as(x))
    # a potential that ignores x
    torch.testing.assert_close(potential_gradient(lambda y: y.new_zeros(y.shape[:-2]), x), 0 * x)
    # create_graph keeps the dependence on V's parameters (second-order path)
    k = torch.tensor(1.3, dtype=DT, requires_grad=True)
    g = potential_gradient(lambda y: k * (y**2).sum((-2, -1)), x, create_graph=True)
    (dk,) = torch.autograd.grad(g.sum(), k)
    torch.testing.assert_close(dk, 2 * x.sum())


@pytest.mark.parametrize("field", [lagrangian_vector_field, hamiltonian_vector_field])
def test_fields_gradcheck_through_potential_parameters(field):
    """Gradients wrt x, v, masses and a potential parameter (needs create_graph)."""
    x0, v0, _, _, cons, _ = chain3()
    x0, v0 = x0[:2], v0[:2]

    def accel(x, v, masses, k):
        gravity = torch.tensor([0.0, -G], dtype=DT)

        def V(y):
            return k * ((y - 0.1) ** 4).sum((-2, -1)) + gravity_potential(
                y, torch.diag(masses), gravity
            )

        gV = potential_gradient(V, x, create_graph=True)
        return field(x, v, torch.diag(1 / masses), gV, cons)

    inputs = (
        x0.clone().requires_grad_(True),
        v0.clone().requires_grad_(True),
        torch.tensor([0.2, 0.13, 0.15], dtype=DT, requires_grad=True),
        torch.tensor(0.7, dtype=DT, requires_grad=True),
    )
    assert torch.autograd.gradcheck(accel, inputs)


@pytest.mark.parametrize("name", SYSTEMS)
def test_hamiltonian_flow_projects_position_rate(name):
    x, v, M, M_inv, cons, gravity = SYSTEMS[name]()
    gV = grad_V(x, M, gravity)
    x_dot, v_dot = hamiltonian_flow(x, v, M_inv, gV, cons)
    torch.testing.assert_close(x_dot, v, rtol=1e-10, atol=1e-10)  # consistent state
    torch.testing.assert_close(v_dot, hamiltonian_vector_field(x, v, M_inv, gV, cons))
    # an inconsistent velocity is projected onto J_E x_dot = 0 (M-orthogonally)
    w = v + torch.randn(v.shape, generator=torch.Generator().manual_seed(5), dtype=DT)
    x_dot, _ = hamiltonian_flow(x, w, M_inv, gV, cons)
    J = cons.jacobian(x)
    torch.testing.assert_close(
        (J @ x_dot.reshape(B, -1, 1))[..., 0], torch.zeros(B, cons.num_equations, dtype=DT)
    )
    Mh = Mhat_inv(M_inv, J)
    M_full = kron_identity(M, x.shape[-1])
    expected = (Mh @ M_full @ w.reshape(B, -1, 1)).reshape(w.shape)
    torch.testing.assert_close(x_dot, expected)


def test_float32_and_inference_mode():
    x, v, M, M_inv, cons, gravity = gyro()
    x, v, M, M_inv, gravity = (t.float() for t in (x, v, M, M_inv, gravity))
    with torch.no_grad():
        gV = grad_V(x, M, gravity)
        a_L = lagrangian_vector_field(x, v, M_inv, gV, cons)
        a_H = hamiltonian_vector_field(x, v, M_inv, gV, cons)
    assert a_L.dtype == a_H.dtype == torch.float32
    assert not a_L.requires_grad
    torch.testing.assert_close(a_L, a_H, rtol=1e-3, atol=1e-3)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    dev = torch.device("cuda")
    for build in SYSTEMS.values():
        x, v, M, M_inv, cons, gravity = build()
        gV = grad_V(x, M, gravity)
        moved = [t.to(dev) for t in (x, v, M_inv, gV)]
        for field in (lagrangian_vector_field, hamiltonian_vector_field):
            a = field(*moved, cons)
            assert a.device.type == "cuda"
            torch.testing.assert_close(a.cpu(), field(x, v, M_inv, gV, cons))
        J = cons.jacobian(moved[0])
        torch.testing.assert_close(Mhat_inv(moved[2], J).cpu(), Mhat_inv(M_inv, J.cpu()))
        gV_dev = grad_V(moved[0], M.to(dev), gravity.to(dev))
        torch.testing.assert_close(gV_dev.cpu(), gV)
