"""The position projection with equality constraints (rigid bodies, the chain pendulum).

The projection keeps the constraints' values, ``Phi(x) = Phi(x_pred)``; the velocities
must stay tangent to them as well, or the next steps drive the bodies off the
constraints (a gyroscope whose contacts were projected deformed: its constraints drifted
by 1.82 over its 100 steps, and with ``cor`` 1 it lost up to 57 % of its energy).
``projection.keep_constraint_rates`` makes the constraints' rates at the projected
positions those before (module docstring, "Constraint rates").
"""

import pytest
import torch

import diffcontact as dc
from diffcontact.systems.projection import keep_constraint_rates
from diffcontact.testing import assert_gradients_close


def _drift(system, n: int = 8) -> tuple[float, float]:
    """The largest change of the constraints' values over ``n`` rollouts, and of their
    rates ``|J_E v|``."""
    traj = system.simulate(system.sample_initial_conditions(n, seed=0))
    x, v = traj[:, :, 0].flatten(0, 1), traj[:, :, 1].flatten(0, 1)
    phi = system.constraints.phi(x).view(n, traj.shape[1], -1)
    rates = system.constraints.jacobian(x) @ v.reshape(v.shape[0], -1, 1)
    return float((phi - phi[:, :1]).abs().max()), float(rates.abs().max())


@pytest.mark.parametrize("velocities", [True, False], ids=["velocities", "positions only"])
@pytest.mark.parametrize("task", ["Gyro", "CP3"])
def test_projected_bodies_keep_their_constraints(task, velocities):
    """With the projection on, the constraints drift no more than without it (RK4's own
    drift). Before the constraint rates were kept: Gyro 1.82 (without: 1.5e-3), CP3 0.031
    (5.8e-3)."""
    free, free_rates = _drift(dc.load_system(task))
    drift, rates = _drift(
        dc.load_system(task, position_projection=10, velocity_projection=velocities)
    )
    assert drift <= 1.5 * free + 1e-6
    assert rates <= 1.5 * free_rates + 1e-6


def test_an_elastic_gyroscope_with_the_projection_keeps_its_energy():
    """``cor`` 1, ``mu`` 0: the projection's contacts bounce; the energy stays within 5 %
    (it lost up to 57 % before the constraint rates were kept, 0.14 % without the
    projection, whose bodies then sink up to 0.05 into the wall)."""
    system = dc.load_system("Gyro", cor=1.0, mu=0.0, position_projection=10)
    traj = system.simulate(system.sample_initial_conditions(16, seed=0))
    energy = system.energy(traj)
    change = (energy - energy[:, :1]) / energy[:, :1].abs()
    assert change.abs().max() < 0.05


def _states(n: int = 6, seed: int = 0):
    """Gyroscope positions ``x_pred``, a nearby ``x`` with the same constraint values to
    first order, and velocities ``v``; the system."""
    system = dc.load_system("Gyro")
    z = system.sample_initial_conditions(n, seed=seed)
    x_pred, v = z[:, 0], z[:, 1]
    g = torch.Generator().manual_seed(seed + 1)
    dx = 1e-2 * torch.randn(x_pred.shape, generator=g, dtype=x_pred.dtype)
    # the step tangent to the constraints at x_pred (as the projection's correction is)
    J = system.constraints.jacobian(x_pred)
    flat = dx.reshape(n, -1, 1)
    flat = flat - J.transpose(-1, -2) @ torch.linalg.solve(J @ J.transpose(-1, -2), J @ flat)
    return system, x_pred, x_pred + flat.reshape(x_pred.shape), v


def test_keep_constraint_rates_makes_the_rates_those_before():
    system, x_pred, x, v = _states()
    M_inv = system.inverse_mass_matrix()
    before = system.constraints.jacobian(x_pred) @ v.reshape(v.shape[0], -1, 1)
    at_x = system.constraints.jacobian(x) @ v.reshape(v.shape[0], -1, 1)
    assert (at_x - before).abs().max() > 1e-4  # the defect: the rates changed
    v_new = keep_constraint_rates(x_pred, x, v, system.constraints, M_inv)
    after = system.constraints.jacobian(x) @ v_new.reshape(v.shape[0], -1, 1)
    torch.testing.assert_close(after, before, atol=1e-12, rtol=0)
    # the smallest change in the mass metric: the kinetic energy does not rise
    kinetic = system.kinetic_energy(torch.stack([x, v], 1))
    kinetic_new = system.kinetic_energy(torch.stack([x, v_new], 1))
    assert (kinetic_new <= kinetic + 1e-12).all()
    # a state the projection did not move keeps its velocities exactly
    same = keep_constraint_rates(x_pred, x_pred, v, system.constraints, M_inv)
    assert torch.equal(same, v)


def test_keep_constraint_rates_point_masses_diagonal_equals_matrix():
    """The chain pendulum's point masses: the diagonal metric gives the matrix's result."""
    system = dc.load_system("CP3")
    z = system.sample_initial_conditions(4, seed=0)
    x_pred, v = z[:, 0], z[:, 1]
    x = x_pred + 1e-3 * torch.ones_like(x_pred)
    M_inv = system.inverse_mass_matrix()
    full = keep_constraint_rates(x_pred, x, v, system.constraints, M_inv)
    diag = keep_constraint_rates(
        x_pred, x, v, system.constraints, M_inv.diagonal(dim1=-2, dim2=-1), diagonal=True
    )
    torch.testing.assert_close(diag, full, atol=1e-13, rtol=0)


def test_keep_constraint_rates_gradients():
    system, x_pred, x, v = _states(n=2)
    M_inv = system.inverse_mass_matrix()
    weights = torch.randn(v.shape, generator=torch.Generator().manual_seed(3), dtype=v.dtype)

    def loss(x_pred, x, v):
        out = keep_constraint_rates(x_pred, x, v, system.constraints, M_inv)
        return (out * weights).sum()

    assert_gradients_close(loss, (x_pred, x, v))
