"""RK4 on free fall, convergence order, chain-pendulum invariants, rollout gradients."""

import math

import pytest
import torch

from diffcontact.mechanics import (
    INTEGRATORS,
    chain_constraints,
    chain_points_2d,
    gravity_potential,
    hamiltonian_flow,
    hamiltonian_vector_field,
    kinetic_energy,
    lagrangian_vector_field,
    potential_gradient,
    rk4_38_step,
    rk4_step,
)

DT = torch.float64
GRAVITY = torch.tensor([0.0, -9.81], dtype=DT)


def make_field(field, masses, constraints, create_graph=False):
    M = torch.diag(masses)
    M_inv = torch.diag(1 / masses)

    def V(x):
        return gravity_potential(x, M, GRAVITY)

    def vector_field(x, v):
        gV = potential_gradient(V, x, create_graph=create_graph)
        return v, field(x, v, M_inv, gV, constraints)

    return vector_field, V


def test_free_fall_is_exact():
    masses = torch.tensor([0.1, 2.0], dtype=DT)
    vf, _ = make_field(lagrangian_vector_field, masses, None)
    x0 = torch.tensor([[0.2, 0.9], [0.5, 0.1]], dtype=DT)
    v0 = torch.tensor([[1.0, 3.0], [-0.5, 0.0]], dtype=DT)
    x, v = x0, v0
    dt, n = 0.01, 50
    for _ in range(n):
        x, v = rk4_step(vf, x, v, dt)
    t = dt * n
    torch.testing.assert_close(x, x0 + v0 * t + 0.5 * GRAVITY * t**2, rtol=0, atol=1e-14)
    torch.testing.assert_close(v, v0 + GRAVITY * t, rtol=0, atol=1e-13)


def test_fourth_order_convergence_and_tensor_dt():
    """Harmonic oscillator x'' = -x: halving dt divides the error by ~16."""

    def vf(x, v):
        return v, -x

    def error(dt, n):
        x, v = torch.ones(1, 1, dtype=DT), torch.zeros(1, 1, dtype=DT)
        for _ in range(n):
            x, v = rk4_step(vf, x, v, dt)
        return abs(x.item() - math.cos(dt * n))

    ratio = error(0.2, 10) / error(0.1, 20)
    assert 14.0 < ratio < 18.0
    # a per-element step: element b uses dt[b]
    dts = torch.tensor([0.1, 0.2], dtype=DT)
    x, _ = rk4_step(vf, torch.ones(2, 1, 1, dtype=DT), torch.zeros(2, 1, 1, dtype=DT), dts)
    x1, _ = rk4_step(vf, torch.ones(1, 1, dtype=DT), torch.zeros(1, 1, dtype=DT), 0.2)
    torch.testing.assert_close(x[1], x1)


def chain_rollout(mode: str, dt: float, steps: int):
    """CP3-e chain from 4 task-like initial states; returns start and end states."""
    masses = torch.tensor([0.2, 0.13, 0.15], dtype=DT)
    lengths = torch.tensor([0.35, 0.4, 0.35], dtype=DT)
    cons = chain_constraints(lengths)
    field = lagrangian_vector_field if mode == "lagrangian" else hamiltonian_vector_field
    vf, V = make_field(field, masses, cons)
    if mode == "hamiltonian_flow":  # integrate S.7's projected x_dot as well

        def vf(x, v):
            gV = potential_gradient(V, x)
            return hamiltonian_flow(x, v, torch.diag(1 / masses), gV, cons)

    gen = torch.Generator().manual_seed(0)
    q = torch.rand(4, 3, generator=gen, dtype=DT) * math.pi  # as the CP3 tasks sample
    dq = torch.randn(4, 3, generator=gen, dtype=DT)
    z = chain_points_2d(q, dq, lengths)
    x, v = z[:, 0], z[:, 1]
    for _ in range(steps):
        x, v = rk4_step(vf, x, v, dt)
    M = torch.diag(masses)
    drift = (kinetic_energy(v, M) + V(x) - kinetic_energy(z[:, 1], M) - V(z[:, 0])).abs()
    return z, x, v, cons, drift


# tolerances over 1 s (100 steps of 0.01) from task-like states with |E| ~ 2 J and
# joint speeds up to ~5 m/s: the error is RK4's truncation error (see the next test)
TOLERANCES = {  # mode: (energy drift [J], |Phi| [m^2], |Phi_dot| [m^2/s])
    "lagrangian": (2.5e-2, 2e-3, 5e-3),
    "hamiltonian": (1e-2, 2e-3, 5e-3),
    "hamiltonian_flow": (1e-2, 5e-5, 3e-3),
}


@pytest.mark.parametrize("mode", TOLERANCES)
def test_chain_pendulum_conserves_energy_and_constraints(mode):
    z, x, v, cons, drift = chain_rollout(mode, 0.01, 100)
    tol_e, tol_phi, tol_phi_dot = TOLERANCES[mode]
    assert drift.max() < tol_e
    assert cons.phi(x).abs().max() < tol_phi  # squared link lengths ~ 0.12 m^2
    assert cons.phi_dot(x, v).abs().max() < tol_phi_dot
    assert (x - z[:, 0]).abs().max() > 0.1  # it moved


def test_chain_pendulum_energy_error_is_truncation_error():
    """Halving dt shrinks the energy drift by > 8x (RK4 order 4 gives ~16)."""
    *_, coarse = chain_rollout("lagrangian", 0.01, 100)
    *_, fine = chain_rollout("lagrangian", 0.005, 200)
    assert (coarse / fine).min() > 8.0


@pytest.mark.parametrize("field", [lagrangian_vector_field, hamiltonian_vector_field])
def test_rollout_gradients_match_finite_differences(field):
    lengths = torch.tensor([0.35, 0.4], dtype=DT)
    cons = chain_constraints(lengths)

    def rollout(masses, q, dq):
        vf, _ = make_field(field, masses, cons, create_graph=True)
        z = chain_points_2d(q, dq, lengths)
        x, v = z[..., 0, :, :], z[..., 1, :, :]
        for _ in range(3):
            x, v = rk4_step(vf, x, v, 0.05)
        return torch.stack([x, v], dim=-3)

    inputs = (
        torch.tensor([0.2, 0.13], dtype=DT, requires_grad=True),
        torch.tensor([[0.4, 1.3], [2.0, -0.5]], dtype=DT, requires_grad=True),
        torch.tensor([[1.0, -0.3], [0.2, 0.8]], dtype=DT, requires_grad=True),
    )
    assert torch.autograd.gradcheck(rollout, inputs)
    # the mass gradient is not trivially zero (it flows through the constraint forces)
    out = rollout(*inputs)
    (g_mass,) = torch.autograd.grad(out[..., 1, :, :].pow(2).sum(), inputs[0])
    assert g_mass.abs().max() > 1e-3


def _oscillator_error(step, dt, n):
    def vf(x, v):
        return v, -x

    x, v = torch.ones(1, 1, dtype=DT), torch.zeros(1, 1, dtype=DT)
    for _ in range(n):
        x, v = step(vf, x, v, dt)
    return abs(x.item() - math.cos(dt * n))


def test_rk4_38_is_fourth_order_and_differs_from_classic_rk4():
    ratio = _oscillator_error(rk4_38_step, 0.2, 10) / _oscillator_error(rk4_38_step, 0.1, 20)
    assert 14.0 < ratio < 18.0
    # the same order, another rule: the two differ by about their truncation errors
    e_classic, e_38 = _oscillator_error(rk4_step, 0.1, 20), _oscillator_error(rk4_38_step, 0.1, 20)
    assert e_classic != e_38 and 0.1 < e_38 / e_classic < 10

    # one step on a nonlinear field, by hand: k1 = f(y), k2 = f(y + dt k1/3), ...
    def vf(x, v):
        return v, -torch.sin(x)

    x0, v0, dt = torch.tensor([[0.7]], dtype=DT), torch.tensor([[0.3]], dtype=DT), 0.1
    y0 = torch.stack([x0, v0])

    def f(y):
        return torch.stack(vf(y[0], y[1]))

    k1 = f(y0)
    k2 = f(y0 + dt * k1 / 3)
    k3 = f(y0 + dt * (k2 - k1 / 3))
    k4 = f(y0 + dt * (k1 - k2 + k3))
    expected = y0 + dt * (k1 + 3 * k2 + 3 * k3 + k4) / 8
    x1, v1 = rk4_38_step(vf, x0, v0, dt)
    torch.testing.assert_close(torch.stack([x1, v1]), expected, rtol=1e-15, atol=1e-15)
    assert INTEGRATORS == {"rk4": rk4_step, "rk4_38": rk4_38_step}


def test_rk4_38_matches_torchdiffeq_rk4():
    torchdiffeq = pytest.importorskip("torchdiffeq")

    def vf(x, v):
        return v, -torch.sin(x) - 0.1 * v

    y0 = torch.tensor([[0.7, 0.3], [-1.2, 2.0]], dtype=DT)
    t = torch.linspace(0, 1, 11, dtype=DT)
    ref = torchdiffeq.odeint(lambda _, y: torch.stack(vf(y[0], y[1])), y0, t, method="rk4")
    x, v = y0[0], y0[1]
    for _ in range(10):
        x, v = rk4_38_step(vf, x, v, 0.1)
    torch.testing.assert_close(torch.stack([x, v]), ref[-1], rtol=0, atol=1e-15)
