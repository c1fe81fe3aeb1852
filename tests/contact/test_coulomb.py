"""The exact-Coulomb contact model: closed forms, agreement with CM, gradients, failures."""

import json
import math

import pytest
import torch

import diffcontact as dc
from diffcontact.cli import main
from diffcontact.contact import (
    ConeQPError,
    CoulombSettings,
    ExactCoulomb,
    coulomb_two_phase_impulse,
    create_contact_model,
    solve_cone_qp,
    solve_coulomb,
    two_phase_impulse,
)
from diffcontact.testing import assert_gradients_close

F64 = torch.float64
pytestmark = pytest.mark.filterwarnings("ignore:.*LeafSpec")


def random_problems(B, K, d, seed, lower=True, singular=False):
    g = torch.Generator().manual_seed(seed)
    D = K * d - 2 if singular else K * d + 1
    J = torch.randn(B, K * d, D, generator=g, dtype=F64)
    A = J @ J.transpose(-1, -2) + (0 if singular else 0.05) * torch.eye(K * d, dtype=F64)
    b = torch.randn(B, K * d, generator=g, dtype=F64)
    mu = 0.1 + 0.7 * torch.rand(B, K, generator=g, dtype=F64)
    lo = 0.3 * torch.rand(B, K, generator=g, dtype=F64) if lower else torch.zeros(B, K, dtype=F64)
    return A, b, mu, lo


def point_mass(v, mu, e, m=2.0):
    """One point mass against one wall (contact frame = world frame): J_C = I."""
    n, d = v.shape
    J = torch.eye(d, dtype=F64).expand(n, d, d)
    Mi = torch.eye(d, dtype=F64).expand(n, d, d) / m
    full = torch.full((n, 1), 1.0, dtype=F64)
    return J, Mi, v, mu * full, e * full, torch.ones(n, 1, dtype=torch.bool), d


def sliding_impacts(d, n=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    vn = -(0.2 + torch.rand(n, 1, generator=g, dtype=F64))
    vt = 0.4 * torch.randn(n, d - 1, generator=g, dtype=F64)
    return torch.cat([vn, vt], -1)


def closed_form(v, mu, e):
    """Textbook point-mass impact: v_n -> -e v_n, |v_t| reduced by mu (1 + e)|v_n| or to 0."""
    vn, vt = v[:, :1], v[:, 1:]
    speed = vt.norm(dim=-1, keepdim=True)
    new = (speed - mu * (1 + e) * vn.abs()).clamp_min(0)
    return torch.cat([-e * vn, torch.where(speed > 0, vt * new / speed, vt)], -1)


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("e", [0.0, 0.7])
def test_sliding_impact_of_a_point_mass_matches_the_closed_form(d, e):
    mu = 0.3
    v = sliding_impacts(d)
    res = coulomb_two_phase_impulse(*point_mass(v, mu, e))
    want = closed_form(v, mu, e)
    assert torch.allclose(res.v_plus, want, atol=1e-9)
    speed = v[:, 1:].norm(dim=-1)
    sliding = speed > mu * (1 + e) * v[:, 0].abs()
    assert 10 < int(sliding.sum()) < 60  # both regimes are exercised
    # CM (maximum dissipation) lifts the mass off: its normal separation velocity is at
    # least mu |v_t+| (the dual cone), more than the rebound e |v_n| when sliding
    cm = two_phase_impulse(*point_mass(v, mu, e)).v_plus
    cm_t = cm[:, 1:].norm(dim=-1)
    assert bool((cm[:, 0] >= mu * cm_t - 1e-9).all())
    lift = cm[:, 0] - want[:, 0]
    assert bool((lift[sliding] > 0.5 * mu * cm_t[sliding]).all())
    slides_in_compression = speed > mu * v[:, 0].abs()
    assert bool((lift[slides_in_compression] > 1e-3).all())
    assert float(lift[~slides_in_compression].abs().max()) < 1e-9  # sticking impacts agree


def test_frictionless_and_head_on_problems_agree_with_cm():
    A, b, mu, lo = random_problems(8, 3, 2, seed=1)
    zero = torch.zeros_like(mu)
    f_qp = solve_cone_qp(A, b, zero, 2, lo)
    f, st = solve_coulomb(A, b, zero, 2, lo)
    assert st.all_converged and torch.allclose(f, f_qp, atol=1e-10)
    # head-on impacts: no tangential velocity, any mu
    v = sliding_impacts(3) * torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    ours = coulomb_two_phase_impulse(*point_mass(v, 0.8, 0.6))
    cm = two_phase_impulse(*point_mass(v, 0.8, 0.6))
    assert torch.allclose(ours.v_plus, cm.v_plus, atol=1e-12)
    assert torch.allclose(ours.f_c, cm.f_c, atol=1e-12)


def test_trajectories_agree_with_cm_without_friction_and_head_on():
    system = dc.load_system("BP5", mu=0.0)
    z0 = system.sample_initial_conditions(4, seed=0)
    cm = system.simulate(z0, 40)
    ours = system.simulate(z0, 40, contact_model="Coulomb")
    assert torch.allclose(ours, cm, atol=1e-9)
    ball = {
        "type": "bouncing_masses", "masses": [0.3], "radii": [0.1], "walls": [[0, 1, 0]],
        "gravity": 9.8, "mu": 0.8, "cor": 0.7, "dt": 0.01, "horizon": 1.0,
    }  # fmt: skip
    system = dc.load_system(ball)
    z0 = torch.zeros(3, 2, 1, 2, dtype=F64)
    z0[:, 0, 0, 1] = torch.tensor([0.3, 0.5, 0.8], dtype=F64)  # dropped: head-on impacts
    cm = system.simulate(z0, 60)
    ours = system.simulate(z0, 60, contact_model="Coulomb")
    assert torch.allclose(ours, cm, atol=1e-9)


def test_a_sliding_ball_rebounds_at_e_with_coulomb_and_lifts_off_with_cm():
    """One ball thrown at the ground: after the bounce, Coulomb's normal speed is
    e |v_n| exactly; CM's is larger (the relaxation's lift-off)."""
    ball = {
        "type": "bouncing_masses", "masses": [0.3], "radii": [0.1], "walls": [[0, 1, 0]],
        "gravity": 0.0, "mu": 0.3, "cor": 0.5, "dt": 0.01, "horizon": 1.0,
        "penetration_fraction": 0.0,
    }  # fmt: skip
    system = dc.load_system(ball)
    z0 = torch.tensor([[[[0.0, 0.13]], [[2.0, -1.0]]]], dtype=F64)
    ours = system.simulate(z0, 10, contact_model="Coulomb")[0, -1, 1, 0]
    cm = system.simulate(z0, 10)[0, -1, 1, 0]
    assert ours.tolist() == pytest.approx([2.0 - 0.3 * 1.5, 0.5], abs=1e-10)
    assert float(cm[1]) > 0.5 + 0.3  # lifts off by about mu |v_t|


@pytest.mark.parametrize("d", [2, 3])
def test_gradients_match_finite_differences(d):
    A, b, mu, lo = random_problems(5, 2, d, seed=d)
    _, st = solve_coulomb(A, b, mu, d, lo)
    assert st.all_converged

    def fn(A, b, mu, lo):
        return solve_coulomb(A, b, mu, d, lo)[0]

    sym = {0: lambda x: x + x.transpose(-1, -2)}
    assert_gradients_close(fn, (A, b, mu, lo), directions=sym, rtol=1e-4)
    # and through the two-phase impulse (v, mu, e_P), sliding and sticking impacts
    v = sliding_impacts(d, n=8, seed=3)

    def impulse(v, mu, e):
        J, Mi, v, _, _, act, dd = point_mass(v, 0.0, 0.0)
        return coulomb_two_phase_impulse(J, Mi, v, mu.expand(8, 1), e.expand(8, 1), act, dd).v_plus

    params = (v, torch.tensor([0.3], dtype=F64), torch.tensor([0.6], dtype=F64))
    assert_gradients_close(impulse, params, rtol=1e-5)


def test_gradients_are_finite_at_degenerate_points():
    # head-on (no slip: the shift is not differentiable), exactly sticking and mu = 0
    v = torch.tensor([[-1.0, 0.0], [-1.0, 0.3 * 1.6], [-1.0, 0.7]], dtype=F64)
    mu = torch.tensor([[0.3], [0.3], [0.0]], dtype=F64, requires_grad=True)
    e = torch.full((3, 1), 0.6, dtype=F64, requires_grad=True)
    v.requires_grad_(True)
    J, Mi, _, _, _, act, d = point_mass(v.detach(), 0.3, 0.6)
    out = coulomb_two_phase_impulse(J, Mi, v, mu, e, act, d).v_plus
    grads = torch.autograd.grad(out.sum(), (v, mu, e))
    assert all(bool(torch.isfinite(g).all()) for g in grads)


def test_padding_batch_dims_and_float32():
    A, b, mu, lo = random_problems(6, 3, 2, seed=5)
    active = torch.tensor([True, False, True]).expand(6, 3)
    keep = torch.tensor([1, 1, 0, 0, 1, 1], dtype=torch.bool)
    f, st = solve_coulomb(A, b, mu, 2, lo, active)
    sub = keep[:, None] & keep[None, :]
    A2 = A[:, sub].reshape(6, 4, 4)
    f2, _ = solve_coulomb(A2, b[:, keep], mu[:, [0, 2]], 2, lo[:, [0, 2]])
    assert st.all_converged and bool((f[:, 2:4] == 0).all())
    assert torch.allclose(f[:, keep], f2, atol=1e-9)
    f0, _ = solve_coulomb(A, b, mu, 2, lo)
    f3, st3 = solve_coulomb(A.reshape(2, 3, 6, 6), b.reshape(2, 3, 6), mu.reshape(2, 3, 3), 2,
                            lo.reshape(2, 3, 3))  # fmt: skip
    assert st3.converged.shape == (2, 3) and torch.allclose(f3.reshape(6, 6), f0, atol=1e-10)
    f32, st32 = solve_coulomb(A.float(), b.float(), mu.float(), 2, lo.float())
    assert f32.dtype == torch.float32 and st32.all_converged
    assert torch.allclose(f32.double(), f0, atol=1e-4)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    A, b, mu, lo = random_problems(6, 3, 3, seed=7)
    f, _ = solve_coulomb(A, b, mu, 3, lo)
    fc, st = solve_coulomb(*(x.cuda() for x in (A, b, mu)), 3, lo.cuda())
    assert st.all_converged and torch.allclose(fc.cpu(), f, atol=1e-9)


def test_non_convergence_is_reported_never_silent():
    v = sliding_impacts(2, n=4) * torch.tensor([1.0, 10.0], dtype=F64)  # all sliding
    capped = CoulombSettings(max_iter=0, newton_steps=0)
    J, Mi, v, mu, e, act, d = point_mass(v, 0.5, 0.5)
    A = J @ Mi @ J.transpose(-1, -2)
    _, st = solve_coulomb(A, v, mu, d, None, act, coulomb=capped)
    assert not bool(st.converged.any()) and bool((st.residual > 1e-3).all())
    with pytest.raises(ConeQPError, match="did not converge") as err:
        coulomb_two_phase_impulse(J, Mi, v, mu, e, act, d, coulomb=capped)
    assert err.value.status.converged.shape == (4,)
    warn = CoulombSettings(max_iter=0, newton_steps=0, on_failure="warn")
    with pytest.warns(RuntimeWarning, match="4 of 4 contact problems did not converge"):
        res = coulomb_two_phase_impulse(J, Mi, v, mu, e, act, d, coulomb=warn)
    # the fallback is the last fixed-point iterate: CM's admissible impulse here
    cm = two_phase_impulse(J, Mi, v, mu, e, act, d)
    assert torch.allclose(res.v_plus, cm.v_plus, atol=1e-9)
    # through simulate: the error names the trajectories and the step
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(3, seed=0)
    with pytest.raises(ConeQPError, match=r"trajectories: state \d"):
        system.simulate(z0, 60, contact_model=ExactCoulomb(max_iter=0, newton_steps=0))
    with pytest.raises(ValueError, match="on_failure"):
        create_contact_model("Coulomb", on_failure="ignore")


def test_generate_and_train_through_the_cli(tmp_path, capsys):
    data, run = tmp_path / "data", tmp_path / "run"
    code = main(
        ["generate", "BP5", "--out", str(data), "--n-train", "6", "--n-val", "2", "--n-test",
         "2", "--contact-model", "Coulomb", "--seed", "1", "--quiet"]
    )  # fmt: skip
    assert code == 0
    assert json.loads((data / "metadata.json").read_text())["contact_model"] == "Coulomb"
    code = main(
        ["train", str(data), "--out", str(run), "--model", "Coulomb-CD-CLNN", "--epochs", "1",
         "--batch-size", "4", "--hidden", "8", "--quiet"]
    )  # fmt: skip
    assert code == 0
    learned = json.loads((run / "learned.json").read_text())
    assert learned["finished"] and learned["global_step"] == 2
    assert all(math.isfinite(x) for x in learned["learned"]["mu"])


def test_high_friction_two_contact_problem_converges():
    """A BD5 contact problem (two disk contacts, mu 1.4 and 0.9, the active block of A
    positive definite; recorded by ``benchmarks/run.py contact_models`` from a CM rollout)
    on which Newton's point fed back into the fixed point stalled at a residual of 0.15:
    the fixed point on its own iterate converges."""
    from pathlib import Path

    data = torch.load(Path(__file__).parent / "data" / "coulomb_bd5_hard.pt", weights_only=True)
    params = dc.contact.ContactParams(mu=data["mu"], cor=data["cor"])
    model = dc.contact.create_contact_model("Coulomb")  # raises if it does not converge
    out = model.resolve(
        data["J"], data["M"], data["v"], params, data["active"], 2, v_C_star=data["vs"]
    )
    assert torch.isfinite(out.v_plus).all()
    # the restitution impulse meets Poisson's bound, the impulses are in the cones
    f_c, f_r = out.f_c.reshape(-1, 2), out.f_r.reshape(-1, 2)
    act = data["active"].reshape(-1)
    mu = data["mu"].reshape(-1)
    for f in (f_c, f_r):
        assert bool((f[act, 1].abs() <= mu[act] * f[act, 0] + 1e-9).all())
    assert bool((f_r[act, 0] >= data["cor"].reshape(-1)[act] * f_c[act, 0] - 1e-9).all())


def test_the_default_cap_finishes_generated_billiards():
    """``max_iter`` 30 stopped one of BP5's 64 trajectories (seed 0) at step 59, so
    ``diffcontact generate BP5 --contact-model Coulomb`` failed; the default finishes it,
    and the state needs more than the old cap."""
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(64, seed=0)
    traj = system.simulate(z0, contact_model="Coulomb")
    assert bool(torch.isfinite(traj).all())
    with pytest.raises(
        ConeQPError, match="failed at step 59 for 1 of 64 trajectories: state 3"
    ) as err:
        system.simulate(z0, contact_model=create_contact_model("Coulomb", max_iter=30))
    # the cause named is Coulomb's (it was CM's cone QP's "ill-conditioned")
    assert "the exact Coulomb iteration did not converge" in str(err.value)
