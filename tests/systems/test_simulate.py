"""Rollouts: shapes, energy conservation, momentum, inelastic contacts, dynamics options."""

import re
import warnings

import pytest
import torch

import diffcontact as dc
from diffcontact.mechanics import potential_gradient
from diffcontact.systems import NonFiniteRolloutError, list_tasks
from diffcontact.testing import count_host_reads

F64 = torch.float64


@pytest.mark.parametrize("task", list_tasks())
def test_every_task_simulates(task):
    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(3, seed=0)
    traj = system.simulate(z0, steps=4)
    assert traj.shape == (3, 5, 2, system.n_points, system.dim)
    assert traj.dtype == F64 and bool(torch.isfinite(traj).all())
    assert torch.equal(traj[:, 0], z0)
    E = system.energy(traj)
    assert E.shape == (3, 5)
    assert system.energy(z0).shape == (3,)


def test_contract_example():
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(16, seed=0)
    assert z0.shape == (16, 2, 5, 2) and z0.dtype == F64
    traj = system.simulate(z0, steps=10, progress=True)
    assert traj.shape == (16, 11, 2, 5, 2)
    assert system.energy(traj).shape == (16, 11)
    assert system.default_steps == 99 and system.dt == 0.01 and system.horizon == 1.0


def test_bp5e_energy_is_conserved_over_the_horizon():
    """BP5-e (elastic, frictionless, no gravity): |E(t) - E(0)| <= 1e-12 E(0).

    Free flight is integrated exactly by RK4 and e_P = 1 impacts of point
    masses are exactly elastic; reached: ~5e-16 (rounding). The compensation
    target (fraction 1/8 of depth/dt) never exceeds the reflected normal speed.
    """
    system = dc.load_system("BP5-e")
    z0 = system.sample_initial_conditions(8, seed=0)
    traj = system.simulate(z0)
    assert traj.shape[1] == 100
    n_contacts = (system.gaps(traj[:, :, 0]) < 0).any(-1).sum()
    assert int(n_contacts) > 20  # many impacts happened
    E = system.energy(traj)
    assert float(((E - E[:, :1]).abs() / E[:, :1]).max()) < 1e-12


def test_cp3e_energy_is_conserved_over_the_horizon():
    """CP3-e (elastic ground, gravity): |E(t) - E(0)| <= 0.5% of the largest kinetic energy.

    Reached: ~0.13% (abs. ~7e-3 J) with seed 0. The error is RK4 truncation
    of the stiff-ish 3-link dynamics at dt = 0.01 together with the drift of
    the link constraints (the Lagrangian field S.2 does not stabilise Phi);
    halving dt shrinks it about 14-fold. Impacts themselves are exactly elastic.
    """
    system = dc.load_system("CP3-e")
    z0 = system.sample_initial_conditions(8, seed=0)
    traj = system.simulate(z0)
    assert int((system.gaps(traj[:, :, 0]) < 0).any(-1).sum()) >= 4  # ground impacts
    E = system.energy(traj)
    K = system.kinetic_energy(traj)
    drift = (E - E[:, :1]).abs().max(1).values / K.max(1).values
    assert float(drift.max()) < 5e-3


def test_lagrangian_and_hamiltonian_agree_on_consistent_states():
    """Both vector fields agree on the constraint manifold; after a few RK4
    steps the difference is truncation-level (constraint drift off-manifold)."""
    for task, tol in (("CP3-e", 1e-6), ("BD5", 1e-12), ("Gyro-e", 5e-4), ("Rope", 1e-12)):
        system = dc.load_system(task)
        z0 = system.sample_initial_conditions(4, seed=0)
        a = system.simulate(z0, steps=5)
        b = system.simulate(z0, steps=5, dynamics="hamiltonian")
        assert float((a - b).abs().max()) < tol, task
    ham = dc.load_system("CP3-e", dynamics="hamiltonian")
    z0 = ham.sample_initial_conditions(2, seed=0)
    assert torch.equal(ham.simulate(z0, steps=3), ham.simulate(z0, steps=3, dynamics="hamiltonian"))


def _drop(cor, fraction):
    system = dc.load_system(
        {
            "type": "bouncing_masses",
            "masses": [0.2],
            "radii": [0.05],
            "walls": [[0, 1, 0]],
            "gravity": 9.81,
            "mu": 0.3,
            "cor": cor,
            "dt": 0.01,
            "horizon": 0.8,
            "penetration_fraction": fraction,
        }
    )
    z0 = torch.tensor([[[[0.5, 0.3]], [[0.2, 0.0]]]], dtype=F64)
    traj = system.simulate(z0)
    height = traj[0, :, 0, 0, 1] - 0.05  # bottom of the ball above the ground
    first = int((height < 0).nonzero()[0])
    return height, first


def test_inelastic_ball_does_not_bounce():
    """cor = 0: after the impact the ball never rises more than 1.5 mm above the ground;
    penetration is removed by 1/8 of depth/dt per step so it does not pop back up
    (appendix G). At rest it sits at the scheme's steady penetration
    g dt^2 / (2 fraction) = 3.9 mm. Removing the whole depth in one step
    (fraction 1) makes it bounce visibly."""
    height, first = _drop(0.0, 0.125)
    after = height[first:]
    assert float(after.max()) < 1.5e-3
    rest = 9.81 * 0.01**2 / (2 * 0.125)
    torch.testing.assert_close(after[-20:], torch.full((20,), -rest, dtype=F64), atol=2e-4, rtol=0)
    height1, first1 = _drop(0.0, 1.0)
    assert float(height1[first1:].max()) > 5 * float(after.max())
    # an elastic ball bounces back up to (almost) its drop height
    height_e, first_e = _drop(1.0, 0.125)
    assert float(height_e[first_e:].max()) > 0.2


def test_linear_momentum_is_conserved_in_body_body_impacts():
    """No walls, no gravity: sum_b m_b v_b is constant through frictional impacts (1e-12)."""
    for kind in ("bouncing_masses", "bouncing_disks"):
        system = dc.load_system(
            {
                "type": kind,
                "masses": [0.1, 0.3, 0.2],
                "radii": [0.1, 0.15, 0.12],
                "mu": [0.5, 0.3, 0.8],
                "cor": [0.2, 0.9, 0.6],
                "dt": 0.01,
                "horizon": 0.5,
            }
        )
        if kind == "bouncing_masses":
            z0 = torch.tensor(
                [[[[0.0, 0.0], [0.5, 0.05], [1.0, -0.05]], [[1.5, 0.2], [0.0, 0.0], [-1.0, 0.4]]]],
                dtype=F64,
            )
        else:
            from diffcontact.mechanics import disk_points_2d

            centre = torch.tensor([[0.0, 0.0], [0.5, 0.05], [1.0, -0.05]], dtype=F64)
            vel = torch.tensor([[1.5, 0.2], [0.0, 0.0], [-1.0, 0.4]], dtype=F64)
            ang = torch.tensor([0.1, 1.0, 2.0], dtype=F64)
            om = torch.tensor([3.0, -2.0, 1.0], dtype=F64)
            z0 = disk_points_2d(centre, ang, vel, om).transpose(0, 1).reshape(1, 2, 9, 2)
        traj = system.simulate(z0)
        M = system.mass_matrix()
        p = (M @ traj[:, :, 1]).sum(-2)  # (N, T, 2): 1^T M v
        assert int((system.gaps(traj[:, :, 0]) < 0).any(-1).sum()) >= 2
        assert float((p - p[:, :1]).abs().max()) < 1e-12
        assert float((traj[0, -1, 1] - traj[0, 0, 1]).abs().max()) > 0.1  # they did collide


def test_a_frictional_disk_impact_changes_angular_momentum_by_gap_times_impulse():
    """No walls, no gravity: the total angular momentum sum_pq M_pq x_p x v_q of two disks
    changes only in the impact step, by exactly ``gap * f_t`` (the penetration at which
    the contact is resolved times the tangential impulse, geometry/circles.py): each disk
    takes the impulse at its own rim point. Frictionless, it is kept."""
    from diffcontact.mechanics import disk_points_2d

    centre = torch.tensor([[0.0, 0.0], [0.25, 0.05]], dtype=F64)
    vel = torch.tensor([[1.0, 0.0], [-1.0, 0.0]], dtype=F64)
    z0 = disk_points_2d(centre, torch.zeros(2, dtype=F64), vel, torch.zeros(2, dtype=F64))
    z0 = z0.transpose(0, 1).reshape(1, 2, 6, 2)
    for mu, dt in ((0.5, 0.01), (0.5, 0.001), (0.0, 0.01)):
        system = dc.load_system({"type": "bouncing_disks", "masses": [1.0, 1.0],
                                 "radii": [0.1, 0.1], "walls": [], "mu": mu, "cor": 0.5,
                                 "dt": dt, "horizon": 0.2})  # fmt: skip
        traj = system.simulate(z0)[0]
        x, p = traj[:, 0], system.mass_matrix() @ traj[:, 1]  # (T, 6, 2): x_q, (M v)_q
        L = (x[..., 0] * p[..., 1] - x[..., 1] * p[..., 0]).sum(-1)  # (T,)
        dL = L[1:] - L[:-1]
        k = int(dL.abs().argmax())  # the impact: resolved at state k + 1
        gap = float(system.gaps(x[k + 1]).min())
        n = x[k + 1, 3] - x[k + 1, 0]
        n = n / n.norm()
        f_t = float((p[k + 1, 3:] - p[k, 3:]).sum(0) @ torch.stack((-n[1], n[0])))
        assert gap < -1e-3  # resolved with penetration
        rest = torch.cat((dL[:k], dL[k + 1 :])).abs().max()
        assert float(rest) < 1e-12, (mu, dt)
        if mu == 0:
            assert abs(float(dL[k])) < 1e-12
        else:
            assert abs(f_t) > 0.05
            assert float(dL[k]) == pytest.approx(gap * f_t, rel=1e-9), (dt, float(dL[k]))


def test_constraints_hold_along_rollouts():
    """Impulses keep J_E v = 0 exactly; positions drift only by RK4 truncation."""
    for task in ("BD5", "CP3", "Gyro"):
        system = dc.load_system(task)
        z0 = system.sample_initial_conditions(4, seed=1)
        traj = system.simulate(z0, steps=30)
        x, v = traj[:, :, 0], traj[:, :, 1]
        assert float(system.constraints.phi(x).abs().max()) < 1e-3, task
        assert float(system.constraints.phi_dot(x, v).abs().max()) < 1e-2, task


def test_potential_gradient_matches_autograd():
    for task in ("Rope", "Gyro", "BD5", "CP3"):
        system = dc.load_system(task)
        x = system.sample_initial_conditions(3, seed=0)[:, 0]
        x = x + 0.01 * torch.randn(x.shape, generator=torch.Generator().manual_seed(0), dtype=F64)
        auto = potential_gradient(system.potential, x)
        torch.testing.assert_close(system.grad_potential(x), auto, rtol=1e-10, atol=1e-12)


def test_rope_energy_terms():
    system = dc.load_system("Rope")
    z = system.sample_initial_conditions(2, seed=0)
    x = z[:, 0]
    # springs at rest: only gravity and kinetic energy
    V = system.potential(x)
    torch.testing.assert_close(V, 0.1 * 9.81 * x[..., 1].sum(-1))
    x2 = x * 1.1  # every segment 10% longer (anchor at the origin)
    V2 = system.potential(x2)
    spring = 10 * 50.0 * (0.005**2)
    torch.testing.assert_close(V2, 0.1 * 9.81 * x2[..., 1].sum(-1) + spring)


def test_float32_and_cmr_run():
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(4, seed=2)
    a = system.simulate(z0, steps=15, contact_model="CMr", eps=0.01)
    assert bool(torch.isfinite(a).all())
    b = system.simulate(z0.float(), steps=15)
    assert b.dtype == torch.float32
    c = system.simulate(z0, steps=15)
    assert float((b.double() - c).abs().max()) < 1e-3


@pytest.mark.parametrize("model", ["CM", "Coulomb"])
def test_float32_rollout_follows_float64_where_the_impulse_split_is_not_unique(model):
    """BP5 state 13 of seed 3 meets four contacts at once, three on two balls: ``A`` is
    singular and the compression impulse's split among the contacts (which Poisson's bound
    uses) is the solver's canonical choice. ``A`` formed in float32 is not singular by
    rounding, and the float32 rollout took another split: 0.72 (CM) and 3.2 (exact
    Coulomb) away after 60 steps, where the other 23 states stay within 1e-3. (The LCP
    model is resolved the same way, but Lemke's solution at this state jumps under a
    1e-9 perturbation of the float64 start: no float32 check can hold there.)"""
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(24, seed=3)
    a = system.simulate(z0, 60, contact_model=model, progress=False)
    b = system.simulate(z0.float(), 60, contact_model=model, progress=False)
    assert b.dtype == torch.float32
    assert float((b.double() - a).abs().max()) < 1e-3


def test_integrator_key_picks_the_runge_kutta_rule():
    """CP3 before its first contact: rk4_38 (the 3/8 rule) and classic rk4 agree to their
    truncation error, and differ; the default is classic rk4."""
    classic = dc.load_system("CP3")
    rule38 = dc.load_system("CP3", integrator="rk4_38")
    assert classic.integrator == "rk4" and rule38.integrator == "rk4_38"
    z0 = classic.sample_initial_conditions(4, seed=0)
    a, b = classic.simulate(z0, 5), rule38.simulate(z0, 5)
    assert (classic.gaps(a[:, :, 0]) > 0).all()  # no contact yet: pure integration
    diff = (a - b).abs().max()
    assert 0 < diff < 1e-6
    # against a reference of both: the 3/8 rule with 10x smaller steps
    fine = dc.load_system("CP3", integrator="rk4_38", dt=0.001, horizon=1.0)
    ref = fine.simulate(z0, 50)[:, ::10]
    for traj in (a, b):
        assert (traj - ref).abs().max() < 1e-6


def test_a_step_too_large_is_a_clear_error_naming_the_states():
    """Gyro at dt = 0.5: RK4 stages leave the constraint manifold and J_E M^-1 J_E^T
    stops being positive definite; no raw linalg traceback, the states are named."""
    system = dc.load_system("Gyro", dt=0.5, horizon=5.0)
    z0 = system.sample_initial_conditions(4, seed=0)
    blown = r"NaN, infinite or blown-up values \(beyond 1e\+12 times the initial state's\) in"
    with pytest.raises(ValueError, match=rf"{blown} \d of 4 .*state \d at step"):
        system.simulate(z0, 9)
    # 3 steps: states of 1e38, finite, were returned with a tunnelling warning of 1e60 radii
    with pytest.raises(NonFiniteRolloutError, match=rf"{blown} 1 of 2 .*state 0 at step 2;"):
        system.simulate(system.sample_initial_conditions(2, seed=0), 3)
    # with these 8 states a blown-up state first meets the SVD of the penetration target
    # (it raised a raw LinAlgError); it is named the same way
    z0 = system.sample_initial_conditions(8, seed=0)
    with pytest.raises(ValueError, match=rf"{blown} \d of 8 .*state \d at step"):
        system.simulate(z0, 20)
    from diffcontact.fastops import spd_solve

    A = torch.stack([torch.eye(2, dtype=torch.float64), torch.zeros(2, 2, dtype=torch.float64)])
    X = spd_solve(A, torch.ones(2, 2, 1, dtype=torch.float64))
    assert torch.equal(X[0], torch.ones(2, 1, dtype=torch.float64)) and X[1].isnan().all()


def test_masses_float64_cannot_resolve_are_named_when_a_rollout_blows_up():
    """Masses 1e300 and 1 blew up at every dt, and the message only said to try a
    smaller one."""
    cfg = dict(type="bouncing_masses", masses=[1e300, 1.0], radii=[0.1, 0.1],
               walls=[[1, 0, 0], [0, 1, 0], [-1, 0, 1], [0, -1, 1]], dt=0.01, horizon=1.0,
               gravity=9.8, mu=0.5, cor=0.5)  # fmt: skip
    system = dc.load_system(cfg)
    with pytest.raises(NonFiniteRolloutError, match=r"or the masses, from 1 to 1e\+300: a "
                       r"spread or size float64 cannot resolve .*check their units"):  # fmt: skip
        system.simulate(system.sample_initial_conditions(2, seed=0))


def test_a_rollout_that_drifts_off_its_constraints_warns_naming_the_states():
    """A chain whose light inner link is whipped by a heavy outer one, at a step too large
    for it: RK4's error halved a link's length and quadrupled the energy, silently."""
    from diffcontact.systems import ConstraintDriftWarning, RolloutWarning

    cfg = dict(type="chain_pendulum", masses=[0.1, 1.0], link_lengths=[0.5, 0.5],
               radii=[0.1, 0.1], walls=[[0, 1, 1e6]], gravity=9.8, dt=0.01,
               horizon=1.0)  # fmt: skip
    system = dc.load_system(cfg)
    z0 = system.sample_initial_conditions(8, seed=3)
    drifted = (r"drifted by more than 0\.25 relative in 1 of 8 trajectories: state 7: "
               r"0\.8\d* at the last step \(above 0\.25 from step \d+\)\. The step dt = "
               r"0\.01 is too large")  # fmt: skip
    with pytest.warns(ConstraintDriftWarning, match=drifted) as rec:
        traj = system.simulate(z0)
    assert len(rec) == 1
    assert traj[7, :, 0, 0].norm(dim=-1).min() < 0.3  # (link 0: 0.5)
    energy = system.energy(traj[7])
    assert energy[-1] > 3.5 * energy[0] > 0  # (mu 0, cor 1: kept in the true motion)
    with warnings.catch_warnings():  # equal masses: no drift to speak of
        warnings.simplefilter("error", RolloutWarning)
        dc.load_system({**cfg, "masses": [1.0, 1.0]}).simulate(z0)


def test_tunnelling_warns_once_or_raises_naming_the_states():
    system = dc.load_system("BP5", dt=0.5, horizon=5.0)  # 50x the task's step
    z0 = system.sample_initial_conditions(4, seed=0)
    with pytest.warns(RuntimeWarning, match=r"tunnelled .* in \d of 4 .*state \d: body") as rec:
        system.simulate(z0, 9)
    assert len([r for r in rec if "tunnelled" in str(r.message)]) == 1
    with pytest.raises(ValueError, match=r"tunnelled .*state \d: body \d penetrates"):
        system.simulate(z0, 9, on_tunnelling="raise")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        system.simulate(z0, 9, on_tunnelling="ignore")
    with pytest.raises(ValueError, match="on_tunnelling must be one of"):
        system.simulate(z0, 9, on_tunnelling="loud")
    # velocities x 1e3 at the task's own step
    fast = dc.load_system("BP5")
    z = fast.sample_initial_conditions(2, seed=1)
    z[:, 1] *= 1e3
    with pytest.raises(ValueError, match=r"tunnelled .*too large for these speeds"):
        fast.simulate(z, 5, on_tunnelling="raise")


def test_tunnelling_under_a_learned_contact_model_names_the_model_not_the_step():
    """An untrained contact network lets the balls pass: the message blames it, not dt."""
    from diffcontact.learning.models.registry import create_model

    torch.manual_seed(0)
    system = dc.load_system("BP5")
    model = create_model("MLP-CD-CLNN", system.config, hidden=[8], contact_hidden=[8]).double()
    z0 = system.sample_initial_conditions(4, seed=0)
    with torch.no_grad(), pytest.raises(ValueError, match="learned contact model lets bodies"):
        model.simulate(z0, 60, on_tunnelling="raise")


@pytest.mark.parametrize("task", ["BP5", "BD5", "CP3", "Gyro", "Rope"])
def test_task_rollouts_do_not_tunnel(task):
    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(4, seed=2)
    system.simulate(z0, 40, on_tunnelling="raise")


def test_a_failed_contact_solve_names_the_states_and_the_cause():
    """A rollout that blows up (CP3 under a huge gravity at dt = 0.01) stops with the states
    whose contact problems failed, their speeds and the likely cause, not a bare
    solver error. Which gravity ends in a failed solve rather than in NaN (also an
    error naming the states, tested above) depends on the chaotic blow-up:
    1e6 did until the contact step took the velocities' constraint drift out, 1e4 since;
    the first of several that fails so is taken."""
    from diffcontact.contact import ConeQPError

    system = dc.load_system("CP3")
    z0 = system.sample_initial_conditions(8, seed=0)
    info = None
    for gravity in (1e4, 1e6, 1e5, 3e3, 3e4, 3e5):
        params = system.parameters().replace(gravity=gravity)
        try:
            system.simulate(z0, 20, params=params, on_tunnelling="ignore")
        except NonFiniteRolloutError:
            continue
        except ConeQPError as err:
            info = err
            break
    assert info is not None, "no gravity ended in a failed contact solve"
    message = str(info)
    assert "simulate CP3: the contact solve failed at step" in message
    assert "the motion blew up" in message and "smaller dt" in message
    assert info.status is not None
    states = [int(s) for s in re.findall(r"state (\d+) \(speed", message)]
    assert states and all(0 <= s < 8 for s in states)


def test_a_step_reads_the_device_once(monkeypatch):
    """Per step on the CPU: one read selects the states in contact (how many, and their
    largest contact count); the fused solver's flags are gathered on the device and read
    with the other checks once per call. More would each be a synchronisation per step on
    CUDA (where the selection is replaced by padding: test_padded_steps_...)."""
    monkeypatch.delenv("DIFFCONTACT_SOLVER", raising=False)  # (a property of the fused solver)
    pytest.importorskip("warp")
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(64, seed=1)
    system.simulate(z0, steps=2)
    reads = [count_host_reads(lambda k=k: system.simulate(z0, steps=k)) for k in (10, 20)]
    assert (reads[1] - reads[0]) / 10 == 1
    assert reads[0] <= 10 + 4  # the input checks, and one read of every deferred check


@pytest.mark.parametrize("task", ["BP5", "CP3"])
def test_padded_steps_read_nothing_and_give_the_same_values_and_gradients(task, monkeypatch):
    """The step-by-step rollout as it runs on CUDA (every state padded to GRAPH_CONTACTS,
    no selection), forced on the CPU: no read per step, and the trajectories and the
    gradients of the selected rollout."""
    monkeypatch.delenv("DIFFCONTACT_SOLVER", raising=False)  # (a property of the fused solver)
    pytest.importorskip("warp")
    from diffcontact.systems import rollout as rollout_module

    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(16, seed=2)
    params = system.parameters()

    def run():
        mu = params.mu.clone().requires_grad_(True)
        z = z0.clone().requires_grad_(True)
        traj = system.simulate(z, 30, params=params.replace(mu=mu))
        traj[:, -1].square().sum().backward()
        return traj.detach(), z.grad, mu.grad

    selected = run()
    monkeypatch.setattr(rollout_module, "_pads_contacts", lambda device: True)
    padded = run()
    for a, b in zip(padded, selected, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)
    reads = [count_host_reads(lambda k=k: system.simulate(z0, steps=k)) for k in (10, 20)]
    assert reads[1] == reads[0]
    # a state with more active contacts than the padding: the rollout runs again selected,
    # and the system pads to more next time
    monkeypatch.setattr(rollout_module, "GRAPH_CONTACTS", 1)
    z0 = system.sample_initial_conditions(64, seed=2)
    again = system.simulate(z0, 60)
    monkeypatch.setattr(rollout_module, "_pads_contacts", lambda device: False)
    plain = system.simulate(z0, 60)
    if task == "BP5":  # (CP3's links have one limit each)
        assert ((system.gaps(plain[:, 1:, 0].flatten(0, 1)) < 0).sum(-1) > 1).any()
        assert system._contact_padding > 1  # remembered for the next rollouts
    assert torch.equal(again, plain)


@pytest.mark.parametrize("gravity", [0.0, 9.81])
def test_constant_force_is_computed_once_with_the_same_trajectories(gravity, monkeypatch):
    """Unconstrained point masses without springs or a learned potential: the acceleration
    is computed at the first RK4 stage of a rollout and reused; the trajectories are
    bitwise those of the general vector field, which evaluates it at every stage."""
    from diffcontact.systems import system as system_module

    system = dc.load_system("BP5", gravity=gravity)
    z0 = system.sample_initial_conditions(16, seed=4)
    fast = system.simulate(z0, 40)
    monkeypatch.setattr(system_module._Context, "force_is_constant", property(lambda self: False))
    general = system.simulate(z0, 40)
    assert torch.equal(fast, general)
    assert not torch.equal(fast[:, -1], z0)  # it moved (and, with gravity, fell)


@pytest.mark.parametrize(
    "batched, dynamics", [(False, "lagrangian"), (True, "lagrangian"), (False, "hamiltonian")]
)
def test_bodies_one_at_a_time_equal_all_points_at_once(monkeypatch, batched, dynamics):
    """BD5's disks are constrained each on its own: the dynamics and the contact's Mhat^-1
    run as a batch of bodies (EqualityConstraints.split). Trajectories and gradients with
    respect to the masses and second moments equal those of all points at once."""
    from diffcontact.mechanics import EqualityConstraints

    n, steps = 4, 30
    z0 = dc.load_system("BD5").sample_initial_conditions(n, seed=3)

    def run(system, one_at_a_time):
        base = system.parameters()
        mass, s = base.mass.clone(), base.second_moments.clone()
        if batched:  # one set per trajectory
            scale = torch.linspace(0.8, 1.2, n, dtype=F64)
            mass, s = mass * scale[:, None], s * scale[:, None, None]
        mass.requires_grad_(True)
        s.requires_grad_(True)
        params = base.replace(mass=mass, second_moments=s)
        assert (system._context(z0, params, n).groups is not None) == one_at_a_time
        traj = system.simulate(z0, steps, params=params, dynamics=dynamics)
        return (traj, *torch.autograd.grad((traj * traj).sum(), [mass, s]))

    grouped = dc.load_system("BD5")
    result = run(grouped, True)
    monkeypatch.setattr(EqualityConstraints, "split", lambda self, size: None)
    dense = dc.load_system("BD5")
    expected = run(dense, False)
    assert (dense.gaps(expected[0][:, :, 0]) < 0).any(), "the rollouts have contacts"
    for got, want in zip(result, expected, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-8, atol=1e-9)


def test_a_disk_reaching_a_corner_follows_the_reference_solver():
    """BD5 scene 57 of seed 1: a disk meets two walls at once, where the compression
    impulse is not unique. The fused (Warp) solver's Newton-from-zero path used to keep a
    minimiser at a kink of the natural map, another than the torch reference's (the
    trajectories then differed by 0.3 after 80 steps); it now leaves such problems to the
    interior point, as the reference does (tests/contact/test_fused_solver.py)."""
    pytest.importorskip("warp")
    from diffcontact.contact import SolverSettings

    system = dc.load_system("BD5")
    z0 = system.sample_initial_conditions(64, seed=1)[57:58]
    runs = [
        system.simulate(z0, 80, solver_settings=SolverSettings(backend=backend))
        for backend in ("warp", "torch")
    ]
    torch.testing.assert_close(runs[0], runs[1], rtol=0, atol=1e-9)


def test_bodies_run_one_at_a_time_on_the_cpu_and_at_once_on_cuda():
    """The per-device choice of ``system._per_body``: BD5's disks split into a batch of
    bodies on the CPU; on CUDA they run over all points at once (the same values:
    ``test_bodies_one_at_a_time_equal_all_points_at_once``)."""
    from diffcontact.systems import system as system_module

    system = dc.load_system("BD5")
    assert system._static_on(torch.device("cpu"))[2] is not None
    assert system_module._per_body(torch.device("cpu"))
    assert not system_module._per_body(torch.device("cuda"))


@pytest.mark.parametrize("task", ["BP5", "BD5", "CP3", "Gyro", "Rope", "BD1-ground"])
def test_an_empty_batch_gives_empty_results(task):
    """Zero states: empty outputs from every public method (the gyroscope's rim lookup
    failed to reshape an empty batch)."""
    system = dc.load_system(task)
    z = system.sample_initial_conditions(1, seed=0)[:0]
    P, dim = system.n_points, system.dim
    assert system.simulate(z, 3).shape == (0, 4, 2, P, dim)
    assert system.step(z).shape == (0, 2, P, dim)
    assert system.gaps(z[:, 0]).shape == (0, system.n_contacts)
    assert system.resolve_contacts(z).z.shape == (0, 2, P, dim)
    assert system.project_positions(z).shape == (0, 2, P, dim)
    assert system.energy(z).shape == (0,)
