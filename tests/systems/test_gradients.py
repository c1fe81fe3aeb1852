"""Gradients of short rollouts through impacts match central finite differences.

Every rollout below has at least one impact (checked), with the config's penetration
compensation (its target v_C^* depends on the penetration depths and J_C, and the
gradient follows it; the paper's appendix G did not differentiate it, and autograd and
finite differences disagreed wherever the target shaped an impulse: the chain pendulum's
and the gyroscope's checks below fail that way) and without it
(``penetration_fraction=0``). Checks are directional
(``diffcontact.testing``), relative tolerance 1e-4 (reached: at most 2e-5, mostly
~1e-8; the largest are parameters the rollout barely depends on, e.g. the
single gyroscope's mass, which scales inertia and gravity alike).
"""

import functools

import pytest
import torch

import diffcontact as dc
from diffcontact.mechanics import chain_points_2d, disk_points_2d
from diffcontact.testing import assert_gradients_close

from .test_params import TWO_BALLS, Z_TWO_BALLS

F64 = torch.float64


def check_rollout(system, names, z0, steps, **kwargs):
    assert system.penetration_fraction > 0  # (the config's compensation is checked)
    for fraction in (None, 0.0):
        results = _check_rollout(system, names, z0, steps, fraction, **kwargs)
    return results


def _check_rollout(system, names, z0, steps, fraction, **kwargs):
    base = system.parameters()
    params = [getattr(base, n).detach().clone() for n in names]

    def rollout(*tensors):
        *values, z = tensors
        p = base.replace(**dict(zip(names, values, strict=True)))
        return system.simulate(z, steps, params=p, penetration_fraction=fraction, **kwargs)

    with torch.no_grad():
        traj = rollout(*params, z0)
    gaps = system.gaps(traj[:, :, 0])
    assert bool((gaps < 0).any()), "the rollout must contain an impact"
    # finite differences need the contact set to stay put under the perturbation
    assert float(gaps.abs().min()) > 1e-5
    # coefficients at a bound of their range (mu = 0, e_P = 0 or 1) are left unperturbed
    keep = {"mu": lambda p: p > 0, "cor": lambda p: (p > 0) & (p < 1)}
    masks = {i: keep[n](p) for i, (n, p) in enumerate(zip(names, params, strict=True)) if n in keep}
    directions = {i: functools.partial(torch.mul, other=m) for i, m in masks.items()}
    results = assert_gradients_close(
        rollout, [*params, z0], n_directions=2, rtol=1e-4, directions=directions
    )
    for r in results:
        assert float(r.finite_difference.abs().max()) > 0  # every input matters
    return results


def test_gradients_bouncing_masses_with_friction():
    system = dc.load_system(TWO_BALLS)
    z0 = Z_TWO_BALLS
    check_rollout(system, ["mu", "cor", "mass"], z0, steps=12)


def test_gradients_bouncing_masses_under_gravity():
    """Point masses under gravity: the acceleration is the same at every state and is
    computed once per rollout (System._vector_field); gradients to the masses and the
    gravity still flow through every step."""
    system = dc.load_system({**TWO_BALLS, "gravity": 9.81})
    z0 = Z_TWO_BALLS
    check_rollout(system, ["mu", "cor", "mass", "gravity"], z0, steps=12)


def test_gradients_bouncing_disks_second_moments():
    system = dc.load_system({**TWO_BALLS, "type": "bouncing_disks"})
    # disk 0 hits the ground (step 5), then disk 1 (step 10)
    centre = torch.tensor([[0.3, 0.165], [0.55, 0.42]], dtype=F64)
    vel = torch.tensor([[2.0, -1.5], [-2.0, -0.5]], dtype=F64)
    angle, spin = torch.tensor([0.3, 1.2], dtype=F64), torch.tensor([4.0, -2.0], dtype=F64)
    z0 = disk_points_2d(centre, angle, vel, spin).transpose(0, 1).reshape(1, 2, 6, 2)
    check_rollout(system, ["mu", "cor", "mass", "second_moments"], z0, steps=12)


def test_gradients_chain_pendulum_cmr():
    system = dc.load_system("CP3", cor=0.4)
    z0 = chain_points_2d(  # joint 2 strikes the ground at step 11, sliding
        torch.tensor([[0.9, 0.7, 0.8]], dtype=F64),
        torch.tensor([[-1.5, -1.0, -2.0]], dtype=F64),
        torch.tensor([0.35, 0.4, 0.35], dtype=F64),
    )
    check_rollout(system, ["mu", "cor", "mass", "gravity"], z0, steps=13)
    check_rollout(system, ["cor"], z0, steps=13, contact_model="CMr")


def test_gradients_gyroscope():
    system = dc.load_system("Gyro")
    z0 = system.sample_initial_conditions(32, seed=0)[25:26]  # hits the wall at step 3
    check_rollout(system, ["mu", "cor", "second_moments", "gravity"], z0, steps=6)
    # this rollout hardly depends on the mass (autograd ~1e-11 per unit, finite differences
    # agree at a step of 1e-4, while a step of 1e-6 gives rounding noise ~1e-8 that a
    # relative check cannot judge): the gradient is checked to be that small instead
    mass = system.parameters().mass.detach().clone().requires_grad_()
    traj = system.simulate(
        z0, 6, params=system.parameters().replace(mass=mass), penetration_fraction=0.0
    )
    (grad,) = torch.autograd.grad(traj.sum(), mass)
    plus, minus = (
        system.simulate(
            z0, 6, params=system.parameters().replace(mass=mass.detach() + h),
            penetration_fraction=0.0,
        ).sum()
        for h in (1e-4, -1e-4)
    )  # fmt: skip
    assert abs(float(grad.sum())) < 1e-8 and abs(float(plus - minus) / 2e-4) < 1e-8


@pytest.mark.filterwarnings("ignore:rope limits with cor > 0")  # on purpose
def test_gradients_rope():
    system = dc.load_system("Rope", cor=0.3)
    z0 = system.sample_initial_conditions(4, seed=0)[1:3]
    # the velocity-level path; with the position projection (the rope's default) the stored
    # states sit on their limits: tests/systems/test_rope_projection.py checks that path
    check_rollout(
        system,
        ["cor", "mass", "stiffness", "rest_length", "gravity"],
        z0,
        steps=12,
        position_projection=0,
    )


def test_gradient_flows_with_requires_grad_attributes():
    """The contract's way: set requires_grad on the System's tensors, backprop a loss."""
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(4, seed=0).requires_grad_(True)
    for t in (system.mass, system.mu, system.cor):
        t.requires_grad_(True)
    traj = system.simulate(z0, steps=25)
    traj.square().sum().backward()
    for t in (system.mass, system.mu, system.cor, z0):
        assert t.grad is not None and bool(torch.isfinite(t.grad).all())
    assert float(system.mass.grad.abs().sum()) > 0 and float(system.cor.grad.abs().sum()) > 0


@pytest.mark.slow
def test_gradients_bp5_longer_rollout():
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(2, seed=0)
    check_rollout(system, ["mu", "cor", "mass"], z0, steps=40)


def test_parameters_the_rollout_does_not_use_get_a_zero_gradient():
    """Balls at rest never touch: mu and e_P take no part in the rollout. Asking for their
    gradient gave autograd's 'element 0 of tensors does not require grad'."""
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(3, seed=0)
    z0[:, 1] = 0
    params = system.parameters()
    mu = params.mu.clone().requires_grad_(True)
    cor = params.cor.clone().requires_grad_(True)
    traj = system.simulate(z0, 5, params=params.replace(mu=mu, cor=cor))
    torch.testing.assert_close(traj[:, -1], z0)  # nothing moved
    traj[:, -1, 0].sum().backward()
    assert torch.equal(mu.grad, torch.zeros_like(mu)) and torch.equal(
        cor.grad, torch.zeros_like(cor)
    )
    with torch.no_grad():  # and nothing changes without gradients
        assert not system.simulate(z0, 5, params=params.replace(mu=mu)).requires_grad
