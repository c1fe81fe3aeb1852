"""Properties of the contact step on random in-contact states of every task.

The states are drawn from each task's initial-condition distribution *without*
rejection (the rope with a wider bending range and randomly stretched
segments) and only those with an active contact are kept, so one batched
solve per task covers many contact configurations (several simultaneous
contacts included; at most 3 at once and penetrations below 0.1, as in a
simulation). Penetration compensation is switched off
(``penetration_fraction=0``) where a property concerns the bare two-phase
model; its target only adds a separating velocity.
"""

import functools

import pytest
import torch

import diffcontact as dc
from diffcontact.mechanics import Mhat_inv, chain_points_2d
from diffcontact.systems import list_tasks
from diffcontact.systems.initial_conditions import DRAWERS

FAST_TASKS = [t for t in list_tasks() if t not in ("Rope-D200", "Rope-D400")]
F64 = torch.float64


def contact_states(system, n=32, seed=0):
    """Up to ``n`` states ``(n, 2, P, dim)`` with at least one active contact.

    Rigid systems: drawn from the initial-condition distribution without
    rejection, keeping states with 1-3 active contacts and penetrations below
    0.1. Rope: pre-impulse states of a short simulation (many limits are
    active at once there, as in the paper's rope).
    """
    if system.type == "rope":
        z0 = system.sample_initial_conditions(16, seed=seed)
        z = system.integrate(system.simulate(z0, steps=8)[:, -1])
        hit = (system.gaps(z[:, 0]) < 0).any(-1)
        assert int(hit.sum()) >= 4
        return z[hit]
    gen = torch.Generator().manual_seed(seed)
    z = DRAWERS[system.type](system.config, 4000, gen)
    if not (system.gaps(z[:, 0]) < 0).any():  # BD1-ground: drawn in the air; take the landings
        traj = system.simulate(system.sample_initial_conditions(16, seed=seed), steps=60)
        z = system.integrate(traj[:, 1:].reshape(-1, *traj.shape[2:]))
    gaps = system.gaps(z[:, 0])
    n_active = (gaps < 0).sum(-1)
    hit = (n_active > 0) & (n_active <= 3) & (gaps > -0.1).all(-1)
    z = z[hit][:n]
    assert z.shape[0] >= min(n, 8), f"too few contact states for {system.name}"
    return z


@functools.cache
def resolved(task, contact_model="CM", fraction=0.0, mu=None, cor=None):
    """(system, z, ContactResult) for one task, cached across tests."""
    overrides = {k: v for k, v in (("mu", mu), ("cor", cor)) if v is not None}
    system = dc.load_system(task, **overrides)
    z = contact_states(system)
    res = system.resolve_contacts(z, contact_model=contact_model, penetration_fraction=fraction)
    return system, z, res


@pytest.mark.parametrize("model", ["CM", "CMr"])
@pytest.mark.parametrize("task", FAST_TASKS)
def test_energy_never_increases_across_an_impact(task, model):
    """Poisson two-phase impulses dissipate: K+ <= K- (to 1e-10 relative) for e_P <= 1.

    The positions do not change, so the potential is the same before and after.
    """
    system, z, res = resolved(task, model)
    assert res.batch_index.numel() == z.shape[0]
    K0 = system.kinetic_energy(z)
    K1 = system.kinetic_energy(res.z)
    assert bool((K1 <= K0 + 1e-10 * K0.abs().clamp_min(1e-3)).all()), (K1 - K0).max()
    torch.testing.assert_close(system.energy(res.z) - system.energy(z), K1 - K0)


@pytest.mark.parametrize("task", FAST_TASKS)
def test_impulses_are_physical(task):
    """Friction cones, non-negative normals, Poisson's bound, masked padding, J_E v+ = 0."""
    system, z, res = resolved(task)
    d, tol = system.d, 1e-8
    mask = res.active
    scale = res.f_c.abs().amax().clamp_min(1.0)
    mu = system.mu[res.contact_index]
    cor = system.cor[res.contact_index]
    for f in (res.f_c, res.f_r):
        assert bool((f[~mask] == 0).all()), "padded entries must be exact zeros"
        assert bool((f[..., 0] >= -tol * scale).all())
        if d > 1:
            t_norm = f[..., 1:].norm(dim=-1)
            assert bool((t_norm <= mu * f[..., 0] + tol * scale).all())
    assert bool((res.f_r[..., 0] >= cor * res.f_c[..., 0] - tol * scale).all())
    # padded rows of J_C are zeros
    J = res.J_C.unflatten(1, (-1, d))
    assert bool((J[~mask] == 0).all())
    # states without contact are untouched
    n_contact = res.batch_index.numel()
    assert n_contact == z.shape[0]
    if system.constraints is not None:
        x, v = res.z[:, 0], res.z[:, 1]
        v_scale = z[:, 1].abs().amax()
        assert float(system.constraints.phi_dot(x, v).abs().max()) < 1e-10 * v_scale


@pytest.mark.filterwarnings("ignore:rope limits with cor > 0")  # on purpose
@pytest.mark.parametrize("task", FAST_TASKS)
def test_restitution_over_compression_equals_cor(task):
    """With one frictionless contact, f_r,n = e_P f_c,n exactly (Poisson's hypothesis).

    (The rope's limits have e_P = 0; it is checked with e_P = 0.5 and random
    perturbed states, since a rope in motion rarely has a single active limit.)
    """
    if task.startswith("Rope"):
        system = dc.load_system(task, cor=0.5)
        gen = torch.Generator().manual_seed(1)
        z = system.sample_initial_conditions(64, seed=1)
        bend = 0.2 * (1.02 + 0.1 * torch.rand(64, generator=gen, dtype=F64))
        # open the first joint past the bending limit by rotating points 1.. about point 0
        seg = z[:, 0, 1:] - z[:, 0, :1]
        first = z[:, 0, 0]
        angle0 = torch.atan2(first[:, 0], -first[:, 1])
        rel = torch.atan2(seg[:, 0, 0], -seg[:, 0, 1]) - angle0
        rot = (bend - rel) * torch.sign(rel)
        c, s_ = torch.cos(rot)[:, None], torch.sin(rot)[:, None]
        seg = torch.stack(
            [c * seg[..., 0] - s_ * seg[..., 1], s_ * seg[..., 0] + c * seg[..., 1]], -1
        )
        z[:, 0, 1:] = z[:, 0, :1] + seg
        keep = (system.gaps(z[:, 0]) < 0).sum(-1) == 1
        z = z[keep]
        res = system.resolve_contacts(z, penetration_fraction=0.0)
    else:
        system, z, res = resolved(task, mu=0.0)
    single = res.active.sum(-1) == 1
    assert int(single.sum()) >= 3
    fc, fr = res.f_c[single, 0, 0], res.f_r[single, 0, 0]
    cor = system.cor[res.contact_index[single, 0]]
    hit = fc > 1e-9  # approaching contacts
    assert int(hit.sum()) >= 1
    torch.testing.assert_close(fr[hit], cor[hit] * fc[hit], rtol=1e-8, atol=1e-12)


def test_restitution_ratio_with_friction_point_masses():
    """BP5 (friction up to 1.1): a point-mass contact has a diagonal A, so f_r,n = e_P f_c,n."""
    system, _, res = resolved("BP5")
    single = res.active.sum(-1) == 1
    fc, fr = res.f_c[single, 0, 0], res.f_r[single, 0, 0]
    cor = system.cor[res.contact_index[single, 0]]
    hit = fc > 1e-9
    assert int(hit.sum()) >= 1
    torch.testing.assert_close(fr[hit], cor[hit] * fc[hit], rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("task", FAST_TASKS)
def test_penetration_target_is_reached(task):
    """With compensation on (CM), every active contact separates at least at v_C^*'s normal."""
    system, _, res = resolved(task, fraction=0.125)
    d = system.d
    v_plus = res.z[res.batch_index, 1].flatten(1)
    v_C = (res.J_C @ v_plus.unsqueeze(-1)).squeeze(-1).unflatten(-1, (-1, d))
    target = res.v_C_star.unflatten(-1, (-1, d))
    gap = (v_C[..., 0] - target[..., 0])[res.active]
    assert float(gap.min()) >= -1e-8 * max(1.0, float(target.abs().max()))


@pytest.mark.parametrize("task", ["Gyro", "CP3", "BD5"])
def test_the_impulse_acts_on_velocities_that_meet_the_constraints(task):
    """RK4 leaves ``J_E v`` of the order of its error; the contact step takes that part
    out (in the mass metric) before the impulse, so ``J_E v+ = 0`` even from drifted
    velocities, and the energy does not rise."""
    system, z, _ = resolved(task)
    x = z[:, 0]
    J_E = system.constraints.jacobian(x)  # (n, E, D)
    M_inv = torch.kron(system.inverse_mass_matrix(), torch.eye(system.dim, dtype=F64))
    y = torch.randn(J_E.shape[:2], generator=torch.Generator().manual_seed(0), dtype=F64)
    drift = (M_inv @ J_E.transpose(-1, -2) @ y[..., None]).reshape(z[:, 1].shape)
    drifted = torch.stack([x, z[:, 1] + 1e-4 * drift / drift.abs().amax()], dim=1)
    assert float(system.constraints.phi_dot(x, drifted[:, 1]).abs().max()) > 1e-6
    res = system.resolve_contacts(drifted, penetration_fraction=0.0)
    v_scale = z[:, 1].abs().amax()
    assert float(system.constraints.phi_dot(x, res.z[:, 1]).abs().max()) < 1e-10 * v_scale
    K0, K1 = system.kinetic_energy(drifted), system.kinetic_energy(res.z)
    assert bool((K1 <= K0 + 1e-10 * K0.abs().clamp_min(1e-3)).all())


def test_a_gyroscope_with_much_friction_simulates():
    """mu = 2 at the gyroscope's rim: ``A = J_C Mhat^-1 J_C^T`` is singular along a
    direction inside the cone, and RK4's ``J_E v`` gave ``b`` a part along it: the
    contact problem was unbounded and ``simulate`` stopped with ``ConeQPError`` at step
    16 (blaming ill-conditioning)."""
    system = dc.load_system("Gyro", mu=2.0)
    z0 = system.sample_initial_conditions(16, seed=11)[10:11]
    traj = system.simulate(z0, 20)
    assert bool(torch.isfinite(traj).all())


def test_only_states_in_contact_are_changed():
    system = dc.load_system("BP5")
    z = system.sample_initial_conditions(6, seed=0)
    z[[1, 4], 0, 0] = z[[1, 4], 0, 1] + 0.1  # body 0 onto body 1 in states 1 and 4
    res = system.resolve_contacts(z)
    assert res.batch_index.tolist() == [1, 4]
    keep = [0, 2, 3, 5]
    assert torch.equal(res.z[keep], z[keep])
    assert torch.equal(res.z[:, 0], z[:, 0])
    assert not torch.equal(res.z[[1, 4], 1], z[[1, 4], 1])


# Kane and Levinson's paradox: a double pendulum striking the ground at an angle,
# with friction, gains energy under Newton's hypothesis; Poisson's two-phase
# model must dissipate.
KL_CONFIG = {
    "type": "chain_pendulum",
    "masses": [1.0, 1.0],
    "link_lengths": [1.0, 1.0],
    "radii": [0.01, 0.01],
    "walls": [[0.0, 1.0, 1.5]],
    "gravity": 9.81,
    "mu": 0.5,
    "cor": 0.5,
    "dt": 0.01,
    "horizon": 1.0,
}


def newton_sliding_impulse_energy(A, v_C, mu, e):
    """Kinetic-energy change of Newton's restitution with Coulomb sliding friction.

    Newton: v_n+ = -e v_n-; friction opposes the initial slip throughout,
    P_t = -mu sign(v_t-) P_n (the classical treatment of Kane and Levinson).
    """
    vn, vt = v_C[0], v_C[1]
    s = torch.sign(vt)
    Pn = -(1 + e) * vn / (A[0, 0] - mu * s * A[0, 1])
    P = torch.stack([Pn, -mu * s * Pn])
    return P @ v_C + 0.5 * P @ A @ P


def test_kane_levinson_double_pendulum():
    system = dc.load_system(KL_CONFIG)
    q = torch.tensor([[-1.0252, -0.2399]], dtype=F64)
    qd = torch.tensor([[3.6115, -0.4168]], dtype=F64)
    z = chain_points_2d(q, qd, torch.tensor([1.0, 1.0], dtype=F64))
    gaps = system.gaps(z[:, 0])
    assert gaps[0, 0] > 0 and -1e-3 < gaps[0, 1] < 0  # the tip just touches the ground
    K0 = system.kinetic_energy(z)
    # Newton's hypothesis would create energy here
    res = system.resolve_contacts(z, penetration_fraction=0.0)
    J = res.J_C[0]
    M_inv = system.inverse_mass_matrix()
    A = J @ Mhat_inv(M_inv, system.constraints.jacobian(z[0, 0])) @ J.T
    v_C = J @ z[0, 1].flatten()
    assert float(v_C[0]) < 0 and float(v_C[1]) != 0  # approaching and sliding
    gain = newton_sliding_impulse_energy(A, v_C, 0.5, 0.5)
    assert float(gain) > 0.05 * float(K0)
    # Poisson's two-phase model dissipates, keeps the cone and the joint constraints
    K1 = system.kinetic_energy(res.z)
    assert float(K1) < float(K0)
    f = res.f_c[0, 0] + res.f_r[0, 0]
    assert float(f[1].abs()) <= 0.5 * float(f[0]) + 1e-10
    assert float(system.constraints.phi_dot(res.z[:, 0], res.z[:, 1]).abs().max()) < 1e-10
    assert float(res.f_r[0, 0, 0]) >= 0.5 * float(res.f_c[0, 0, 0]) * (1 - 1e-9)
