"""``PhysicalParams``: parameters as arguments, one set per trajectory, pure ``simulate``."""

from __future__ import annotations

import pytest
import torch

import diffcontact as dc
from diffcontact.systems import load_config
from diffcontact.testing import assert_gradients_close, count_host_reads

F64 = torch.float64

TWO_BALLS = {
    "type": "bouncing_masses",
    "masses": [0.1, 0.3],
    "radii": [0.1, 0.15],
    "walls": [[0, 1, 0]],
    "mu": [0.4, 0.3, 0.2],
    "cor": [0.7, 0.5, 0.6],
    "dt": 0.01,
    "horizon": 1.0,
}
# ball 0 hits the ground (step 5), then ball 1 off-centre (step 9)
Z_TWO_BALLS = torch.tensor([[[[0.3, 0.165], [0.55, 0.42]], [[2.0, -1.5], [-2.0, -0.5]]]], dtype=F64)


def _per_trajectory(system, n, seed=0):
    """Parameters that differ between ``n`` trajectories."""
    gen = torch.Generator().manual_seed(seed)
    base = system.parameters()
    K = system.n_contacts

    def jitter(t, low, high):
        return (t * (low + (high - low) * torch.rand(n, *t.shape, generator=gen, dtype=F64))).to(t)

    changes = {
        "mass": jitter(base.mass, 0.5, 2.0),
        "mu": (base.mu.expand(K) * torch.rand(n, K, generator=gen, dtype=F64) * 1.5),
        "cor": torch.rand(n, K, generator=gen, dtype=F64),
    }
    if base.second_moments is not None:
        changes["second_moments"] = jitter(base.second_moments, 0.7, 1.3)
    if float(base.gravity) != 0:
        changes["gravity"] = jitter(base.gravity, 0.5, 1.5)
    return base.replace(**changes)


def _row(params, i):
    out = {}
    for name, t in params.tensors().items():
        unbatched = {"mass": 1, "second_moments": 2, "mu": 1, "cor": 1}.get(name, 0)
        out[name] = t[i] if t.dim() > unbatched else t
    return params.replace(**out)


@pytest.mark.parametrize(
    ("task", "contact_model", "steps"),
    [("BP5", "CM", 40), ("BD5", "CM", 40), ("CP3", "CMr", 99), ("Gyro", "CM", 99)],
)
def test_batched_parameters_equal_the_per_trajectory_loop(task, contact_model, steps):
    system = dc.load_system(task)
    n = 3
    z0 = system.sample_initial_conditions(n, seed=4)
    params = _per_trajectory(system, n)
    if contact_model == "CMr":
        params = params.replace(eps=torch.tensor([0.001, 0.01, 0.1], dtype=F64))
    batched = system.simulate(z0, steps, params=params, contact_model=contact_model)
    for i in range(n):
        alone = system.simulate(
            z0[i : i + 1], steps, params=_row(params, i), contact_model=contact_model
        )
        torch.testing.assert_close(batched[i : i + 1], alone, rtol=0, atol=1e-12)
    # the batch had contacts, and the sets differ (the comparison would be vacuous otherwise)
    shared = system.simulate(z0, steps, contact_model=contact_model)
    assert (batched - shared).abs().max() > 1e-3
    assert (system.gaps(batched[:, :, 0]) < 0).any()


@pytest.mark.parametrize("field", ["mu", "cor"])
def test_one_contact_field_batched_alone(field):
    """A per-trajectory mu with a shared e_P (and vice versa) equals the per-trajectory loop."""
    system = dc.load_system(TWO_BALLS)
    z0 = Z_TWO_BALLS.expand(3, -1, -1, -1).clone()
    values = torch.tensor([[0.1], [0.5], [0.9]], dtype=F64)  # (N, 1): one shared value each
    batched = system.simulate(z0, 20, params=system.parameters().replace(**{field: values}))
    for i in range(3):
        alone = system.simulate(
            z0[i : i + 1], 20, params=system.parameters().replace(**{field: values[i]})
        )
        torch.testing.assert_close(batched[i : i + 1], alone, rtol=0, atol=1e-12)
    assert (batched[0, -1] - batched[2, -1]).abs().max() > 1e-3


def test_batched_energy_matches_rows():
    system = dc.load_system("BD5")
    z0 = system.sample_initial_conditions(2, seed=0)
    params = _per_trajectory(system, 2)
    traj = system.simulate(z0, 5, params=params)
    E = system.energy(traj, params=params)
    assert E.shape == (2, 6)
    for i in range(2):
        torch.testing.assert_close(E[i], system.energy(traj[i], params=_row(params, i)))


def test_gradients_of_each_set_match_finite_differences():
    system = dc.load_system(TWO_BALLS)
    z0 = torch.cat([Z_TWO_BALLS, Z_TWO_BALLS * torch.tensor([1.0, 0.9], dtype=F64)[:, None, None]])
    base = system.parameters()
    mass = torch.stack([base.mass, base.mass * 1.3])
    mu = torch.stack([base.mu, base.mu * 0.5])
    cor = torch.stack([base.cor, base.cor * 0.8])

    def rollout(mass, mu, cor):
        p = base.replace(mass=mass, mu=mu, cor=cor)
        return system.simulate(z0, 12, params=p, penetration_fraction=0.0)

    with torch.no_grad():
        traj = rollout(mass, mu, cor)
    assert (system.gaps(traj[:, :, 0]) < 0).any(dim=(1, 2)).all(), "each trajectory has an impact"
    results = assert_gradients_close(rollout, [mass, mu, cor], n_directions=3, rtol=1e-4)
    # each trajectory's set only moves its own trajectory
    mass = mass.clone().requires_grad_(True)
    traj = rollout(mass, mu, cor)
    (g,) = torch.autograd.grad(traj[0].sum(), mass)
    assert g[1].abs().max() == 0 and g[0].abs().max() > 0
    assert all(float(r.finite_difference.abs().max()) > 0 for r in results)


def test_simulate_is_pure():
    system = dc.load_system("BP5")
    before = {k: v.clone() for k, v in system.parameters().tensors().items()}
    z0 = system.sample_initial_conditions(2, seed=0)
    mu = torch.full((30,), 0.3, dtype=F64, requires_grad=True)
    traj = system.simulate(z0, 30, params=system.parameters().replace(mu=mu))
    traj.sum().backward()
    assert mu.grad is not None
    after = system.parameters().tensors()
    for name, value in before.items():
        assert torch.equal(value, after[name]) and not after[name].requires_grad, name
    assert system.parameters().potential is None


def test_replace_is_immutable_and_checks_names():
    params = dc.load_system("CP3").parameters()
    p2 = params.replace(mu=params.mu * 0.5, gravity=3.0)
    assert float(params.mu[0]) == 0.5 and float(p2.mu[0]) == 0.25
    assert p2.gravity.dtype == F64 and float(p2.gravity) == 3.0
    with pytest.raises(ValueError, match=r"no field\(s\) \['friction'\]"):
        params.replace(friction=0.1)
    with pytest.raises(AttributeError):
        params.mu = params.mu * 2  # frozen
    with pytest.raises(ValueError, match="mu must be a number or a tensor, got True"):
        params.replace(mu=True)  # (became 1.0)


def test_a_meta_tensor_parameter_is_named():
    system = dc.load_system("BP5")
    p = system.parameters()
    z0 = system.sample_initial_conditions(1, seed=0)
    with pytest.raises(ValueError, match="mass must be a dense tensor with values, got a meta"):
        system.simulate(z0, 2, params=p.replace(mass=p.mass.to("meta")))  # (.item() error)


def test_bad_parameters_are_named():
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(3, seed=0)
    p = system.parameters()
    cases = [
        (p.replace(mass=torch.ones(2, 5, dtype=F64)), r"mass must have shape \(5,\).*\(3, 5\)"),
        (p.replace(mass=-torch.ones(3, 5, dtype=F64)), r"mass must be positive"),
        (p.replace(mu=torch.full((3, 30), -0.1, dtype=F64)), r"mu must be >= 0"),
        (p.replace(cor=torch.full((3, 30), 1.5, dtype=F64)), r"cor must be in \[0, 1\]"),
        (p.replace(mu=torch.full((3, 7), 0.1, dtype=F64)), r"mu must be one number or"),
        (p.replace(mass=torch.full((5,), float("nan"), dtype=F64)), r"mass contains NaN"),
        (p.replace(second_moments=torch.ones(5, 2, dtype=F64)), r"second_moments does not apply"),
        (p.replace(eps=-1.0), r"eps must be positive"),
        (
            p.replace(mass=torch.ones(3, 5, dtype=F64), mu=torch.ones(2, 30, dtype=F64)),
            r"mu must be one number or .*\(3, 30\) \(one set per trajectory\); got shape \(2, 30\)",
        ),
    ]
    for params, pattern in cases:
        with pytest.raises(ValueError, match=pattern):
            system.simulate(z0, 1, params=params)
    with pytest.raises(ValueError, match="params must be a PhysicalParams"):
        system.simulate(z0, 1, params={"mass": p.mass})
    # batched parameters need batched states in energy
    batched = p.replace(mass=torch.ones(3, 5, dtype=F64))
    with pytest.raises(ValueError, match="need a leading batch dimension"):
        system.potential(z0[0, 0], params=batched)


@pytest.mark.parametrize(
    ("task", "field", "bad", "edge", "pattern"),
    [
        ("BP5", "gravity", -9.81, 0.0, r"gravity must be >= 0, got -9\.81"),
        ("CP3", "gravity", -1e-12, 0.0, r"gravity must be >= 0, got -1e-12"),
        ("Rope", "stiffness", -1.0, 0.0, r"stiffness must be >= 0, got -1"),
        ("Rope", "rest_length", 0.0, None, r"rest_length must be positive, got 0"),
        ("Gyro", "mu", -0.1, 0.0, r"mu must be >= 0, got -0\.1"),
        ("Gyro", "cor", 1.1, 1.0, r"cor must be in \[0, 1\], got 1\.1"),
    ],
)
def test_params_refuse_what_the_config_refuses(task, field, bad, edge, pattern):
    """A value passed through ``params`` is held to the config's range: gravity is a
    magnitude (>= 0; -9.81 made gravity point up, silently), like the config's key."""
    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(2, seed=0)
    p = system.parameters()
    with pytest.raises(ValueError, match=rf"\n  {field}: "):
        load_config(task, **{field: bad})
    for value in (
        torch.tensor(bad, dtype=F64),
        torch.tensor(bad, dtype=F64, requires_grad=True),  # a learned model's parameter
    ):
        with pytest.raises(ValueError, match=pattern):
            system.simulate(z0, 1, params=p.replace(**{field: value}))
    batched = getattr(p, field).detach().expand(2, *getattr(p, field).shape).clone()
    batched[1] = bad  # one trajectory's set
    with pytest.raises(ValueError, match=rf"{field} must be"):
        system.simulate(z0, 1, params=p.replace(**{field: batched}))
    if edge is not None:  # the bound itself is valid in both
        load_config(task, **{field: edge})
        system.simulate(z0, 1, params=p.replace(**{field: torch.tensor(edge, dtype=F64)}))


def test_valid_parameters_are_checked_with_one_read_per_device():
    """A learned model's parameters are validated in every rollout of a training step; on
    CUDA each read of a flag waits for the device, so valid parameters cost one read (a
    scalar copied to the host) for all their checks."""
    for task in ("BP5", "Gyro", "Rope"):
        system = dc.load_system(task)
        params = system.parameters()
        assert count_host_reads(lambda s=system, p=params: s._params(p, 3)) == 1, task


def test_eps_shorthand_equals_params_eps():
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(2, seed=3)
    a = system.simulate(z0, 20, contact_model="CMr", eps=0.05)
    b = system.simulate(z0, 20, contact_model="CMr", params=system.parameters().replace(eps=0.05))
    c = system.simulate(z0, 20, contact_model="CMr")
    assert torch.equal(a, b)
    assert (a - c).abs().max() > 0
