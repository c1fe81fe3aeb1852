"""LearnedModel: the simulate contract, parameterisations, gradients, saving."""

import functools
import json
import math

import numpy as np
import pytest
import torch
from torch import nn

import diffcontact as dc
from diffcontact.learning.models.physical import LearnedModel
from diffcontact.learning.models.registry import BUILTIN_MODELS as MODELS
from diffcontact.learning.models.registry import parse_model_name
from diffcontact.learning.models.storage import load_model
from diffcontact.systems import load_config

F64 = torch.float64


class ChainGravity(nn.Module):
    """The true potential of a chain pendulum with point masses: ``g sum_i m_i y_i``."""

    def __init__(self, masses, g):
        super().__init__()
        self.register_buffer("m", torch.as_tensor(masses, dtype=F64))
        self.g = float(g)

    def forward(self, x):
        return self.g * (self.m.to(x) * x[..., 1]).sum(-1)


def _truth_model(name, model, **kw):
    """A LearnedModel with its parameters set to the system's true values."""
    truth = dc.load_system(name)
    m = LearnedModel(name, model=model, **kw).double()
    m.set_parameters(
        mass=truth.mass,
        second_moments=truth.second_moments,
        mu=truth.mu if m.heterogeneous else truth.mu[0],
        cor=truth.cor if m.heterogeneous else truth.cor[0],
    )
    return truth, m


@functools.lru_cache
def _states_before_contact(task, n, steps, seed=0, horizon=60):
    """``n`` states of true trajectories that are in contact one step later."""
    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(4 * n, seed=seed)
    traj = system.simulate(z0, steps=horizon)
    with torch.no_grad():
        contact = (system.gaps(traj[..., 0, :, :]) < 0).any(-1)  # (N, T)
    picks = []
    for i in range(traj.shape[0]):
        for s in range(traj.shape[1] - steps):
            # the contact comes in the first step, so a model's rollout meets it as well
            if not contact[i, s] and contact[i, s + 1]:
                picks.append(traj[i, s])
                break
        if len(picks) == n:
            break
    assert len(picks) == n, "not enough contact chunks in the sample"
    return torch.stack(picks)


def test_model_names_and_options():
    assert parse_model_name("CMr-CD-CHNN") == ("CMr", "hamiltonian")
    for name in MODELS:
        m = LearnedModel("CP3", model=name, hidden=(8,))
        contact, dynamics = parse_model_name(name)
        assert (m.contact_model, m.dynamics) == (contact, dynamics)
        assert m.options()["model"] == name
    with pytest.raises(ValueError, match="'MLP-CD-CLNN' is not a physical model"):
        LearnedModel("CP3", model="MLP-CD-CLNN")
    # the config key decides, not the task's name: a renamed BP5 is still per contact
    renamed = load_config("BP5").model_dump()
    renamed["name"] = "my-balls"
    assert LearnedModel(renamed, hidden=(8,)).heterogeneous
    with pytest.raises(ValueError, match="eps"):
        LearnedModel("CP3", model="CMr-CD-CLNN", eps=-1.0)
    assert LearnedModel("BP5", hidden=(8,)).heterogeneous
    assert not LearnedModel("BP5-e", hidden=(8,)).heterogeneous
    assert LearnedModel("CP3", hidden=(8,), heterogeneous=True).raw_mu.shape == (3,)
    m = LearnedModel("CP3", model="CMr-CD-CLNN", eps="learnable", hidden=(8,))
    assert {n for n, _ in m.named_parameters()} >= {
        "log_mass_scale", "log_mass_rel", "raw_mu", "raw_cor", "log_eps"
    }  # fmt: skip
    assert m.log_second_moments is None
    assert LearnedModel("BD5", hidden=(8,)).log_second_moments.shape == (5, 2)


def test_initial_values_are_neutral_not_the_truth():
    p = LearnedModel("BD5", model="CMr-CD-CLNN", eps="learnable", hidden=(8,)).learned_parameters()
    assert p["mass"] == [1.0] * 5 and p["mass_ratios"] == [1.0] * 5
    radii = [0.05, 0.1, 0.13, 0.15, 0.18]  # the known geometry: size squared, not r^2 / 4
    np.testing.assert_allclose(p["second_moments"], [[r * r, r * r] for r in radii], rtol=1e-6)
    gyro = LearnedModel("Gyro", hidden=(8,)).learned_parameters()
    np.testing.assert_allclose(gyro["second_moments"], [[0.09, 0.09, 0.09]], rtol=1e-6)
    assert p["mu"] == [0.5] * 30 and p["cor"] == [0.5] * 30
    assert p["eps"] == pytest.approx(0.01)


def test_simulate_contract_shape_dtype_device():
    m = LearnedModel("BP5", model="CMr-CD-CHNN", hidden=(16,))
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(3, seed=0)
    for dtype in (torch.float32, torch.float64):
        m.to(dtype)
        traj = m.simulate(z0.to(dtype), 3)
        assert traj.shape == (3, 4, 2, 5, 2) and traj.dtype == dtype
        assert torch.equal(traj[:, 0], z0.to(dtype))
        assert torch.isfinite(traj).all()
    # parameters in float32, rollout in float64: follows z0 (weights are cast)
    m.float()
    assert m(z0, 2).dtype == F64
    with pytest.raises(ValueError, match="contact_model"):
        m.simulate(z0, 1, contact_model="CM")
    with pytest.raises(ValueError, match="shape"):
        m.simulate(z0[:, 0], 1)


@pytest.mark.parametrize(
    ("task", "model"),
    [("CP3", "CM-CD-CLNN"), ("CP3", "CMr-CD-CHNN"), ("BD5", "CMr-CD-CLNN")],
)
def test_same_as_system_with_true_parameters(task, model):
    truth, m = _truth_model(task, model)
    if truth.type == "chain_pendulum":
        m.potential = ChainGravity(truth.mass, truth.gravity)
    else:  # no potential in the box tasks
        m.potential = None
    steps = 4
    z0 = _states_before_contact(task, 2, steps)
    contact, dynamics = parse_model_name(model)
    ref = truth.simulate(z0, steps, contact_model=contact, eps=0.01, dynamics=dynamics)
    out = m.simulate(z0, steps)
    torch.testing.assert_close(out, ref, rtol=1e-10, atol=1e-10)


def test_learned_parameters_are_plain_numbers():
    for task, model, het in (("CP3", "CMr-CD-CLNN", None), ("BP5", "CM-CD-CLNN", None)):
        m = LearnedModel(task, model=model, eps="learnable", hidden=(8,), heterogeneous=het)
        m.set_parameters(mass=[0.1, 0.2, 0.15][: m.system.n_bodies] if task == "CP3" else None)
        p = m.learned_parameters()
        json.dumps(p)  # plain data
        K, B = m.n_contacts, m.system.n_bodies
        assert set(p) == {"mass", "mass_ratios", "second_moments", "mu", "cor", "eps"}
        assert len(p["mass"]) == B and len(p["mass_ratios"]) == B
        assert len(p["mu"]) == K and len(p["cor"]) == K
        for v in [*p["mass"], *p["mass_ratios"], *p["mu"], *p["cor"]]:
            assert type(v) is float
        assert p["mass_ratios"][0] == 1.0
        if task == "CP3":
            assert p["mass_ratios"] == pytest.approx([1.0, 2.0, 1.5])
            assert type(p["eps"]) is float
            assert len(set(p["mu"])) == 1  # one shared value, expanded
        else:
            assert p["eps"] is None


def test_set_parameters_round_trip():
    m = LearnedModel("BP5", model="CMr-CD-CLNN", eps="learnable", hidden=(8,)).double()
    mu = torch.linspace(0, 1.2, 30, dtype=F64)
    cor = torch.linspace(0, 1, 30, dtype=F64)
    m.set_parameters(mass=[0.05, 0.1, 0.3, 0.4, 0.5], mu=mu, cor=cor, eps=0.1)
    p = m.learned_parameters()
    assert p["mass_ratios"] == pytest.approx([1, 2, 6, 8, 10])
    assert p["mu"] == pytest.approx(mu.tolist()) and p["cor"] == pytest.approx(cor.tolist())
    assert p["eps"] == pytest.approx(0.1)


def test_gradients_reach_every_parameter():
    system = dc.load_system("BD5")
    m = LearnedModel("BD5", model="CMr-CD-CHNN", eps="learnable", hidden=(16, 16)).double()
    m.set_parameters(mu=0.02)  # small enough that every contact slides: d/dmu is not 0
    steps = 4
    z0 = _states_before_contact("BD5", 2, steps)
    ref = system.simulate(z0, steps)
    loss = (m.simulate(z0, steps) - ref).abs().mean()
    loss.backward()
    for name, p in m.named_parameters():
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name


def test_files_of_the_old_e_p_parameterisation_are_refused(tmp_path):
    m = LearnedModel("CP3", hidden=(4,))
    data = m.checkpoint()
    data["format_version"] = 1  # e_P = hardsigmoid(raw): the same weights mean another e_P
    with pytest.raises(ValueError, match=r"format 1 .*retrain"):
        LearnedModel.from_checkpoint(data)


def test_format_2_files_load_with_the_same_masses():
    m = LearnedModel("CP3", hidden=(4,))
    m.set_parameters(mass=[0.3, 0.2, 0.1])
    data = m.checkpoint()
    state = dict(data["state_dict"])
    state["log_mass"] = (state.pop("log_mass_scale") + state.pop("log_mass_rel")).clone()
    old = {**data, "format_version": 2, "state_dict": state}
    back = LearnedModel.from_checkpoint(old)
    assert back.mass().tolist() == pytest.approx([0.3, 0.2, 0.1], rel=1e-6)
    assert back.log_mass_scale.item() == 0.0


def test_masses_split_into_a_common_scale_and_relative_logs():
    m = LearnedModel("BP5", hidden=(4,)).double()
    m.set_parameters(mass=[0.05, 0.1, 0.3, 0.4, 0.5])
    torch.testing.assert_close(m.mass(), torch.tensor([0.05, 0.1, 0.3, 0.4, 0.5]).double())
    assert m.log_mass_rel.sum().item() == pytest.approx(0.0, abs=1e-12)
    m.set_parameters(mass=0.2)  # one number for all bodies
    torch.testing.assert_close(m.mass(), torch.full((5,), 0.2).double())


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"mass": [0.1, -0.2, 0.1, 0.1, 0.1]}, "mass must be positive"),
        ({"mass": [0.1, 0.2]}, r"mass must be one number or of shape \(5,\)"),
        ({"mu": -0.1}, "mu must be >= 0"),
        ({"cor": 1.2}, r"cor \(e_P\) must be in \[0, 1\]"),
        ({"eps": 0.0}, "eps must be a positive number"),
        ({"second_moments": 1.0}, "point masses only"),
        ({"mass": 0.2, "cor": -0.5}, r"cor \(e_P\)"),  # nothing is written, not even mass
    ],
)
def test_set_parameters_rejects_bad_values(kwargs, message):
    m = LearnedModel("BP5-e", model="CMr-CD-CLNN", hidden=(4,))
    before = {k: v.clone() for k, v in m.state_dict().items()}
    with pytest.raises(ValueError, match=message):
        m.set_parameters(**kwargs)
    for k, v in m.state_dict().items():
        assert torch.equal(v, before[k]), k


def test_only_cmr_depends_on_the_common_mass_scale():
    """Without a potential the data fix mass ratios only: CM's loss is flat along the
    common scale, CMr's (``eps I`` is in units of inverse mass) falls as masses shrink."""
    system = dc.load_system("BP5-e")
    steps = 3
    z0 = _states_before_contact("BP5-e", 3, steps)
    ref = system.simulate(z0, steps)
    slopes = {}
    for name in ("CM-CD-CLNN", "CMr-CD-CLNN"):
        _, m = _truth_model("BP5-e", name, hidden=(4,))
        m.potential = None
        m.set_parameters(cor=0.9)  # off the truth, so that CM's loss is not 0 either
        loss = (m.simulate(z0, steps) - ref).abs().mean()
        (slope,) = torch.autograd.grad(loss, m.log_mass_scale)
        slopes[name] = (loss.item(), slope.item())
    cm_loss, cm_slope = slopes["CM-CD-CLNN"]
    cmr_loss, cmr_slope = slopes["CMr-CD-CLNN"]
    assert cm_loss > 1e-4 and abs(cm_slope) < 1e-9 * cm_loss, slopes
    assert cmr_slope > 1e-3 * cmr_loss, slopes  # smaller masses, smaller loss


def test_save_and_load(tmp_path):
    m = LearnedModel("CP3", model="CMr-CD-CHNN", eps="learnable", hidden=(8, 8))
    m.set_parameters(mass=[0.3, 0.2, 0.1], mu=0.3, cor=0.7, eps=0.05)
    m.save(tmp_path / "model.pt")
    back = load_model(tmp_path)
    assert back.options() == m.options()
    assert back.learned_parameters() == m.learned_parameters()
    z0 = dc.load_system("CP3").sample_initial_conditions(2, seed=3)
    torch.testing.assert_close(back.simulate(z0, 3), m.simulate(z0, 3), rtol=0, atol=0)
    with pytest.raises(ValueError, match="does not exist"):
        load_model(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="neither"):
        load_model(tmp_path / "empty")


def test_as_system_and_energy():
    truth, m = _truth_model("CP3", "CM-CD-CLNN")
    m.potential = ChainGravity(truth.mass, truth.gravity)
    z0 = truth.sample_initial_conditions(2, seed=1)
    torch.testing.assert_close(m.energy(z0), truth.energy(z0), rtol=1e-12, atol=1e-12)
    s = m.as_system()
    assert float(s.gravity) == 0.0 and not s.mass.requires_grad
    torch.testing.assert_close(s.energy(z0), truth.energy(z0), rtol=1e-12, atol=1e-12)
    assert math.isclose(float(s.mass[1] / s.mass[0]), 2.0)


@pytest.mark.parametrize("task", ["BP5", "CP3"])
def test_float32_potential_inside_a_float64_rollout(task, tmp_path):
    """potential_dtype="float32": the same loss and gradients as float64 to float32's
    accuracy in the network, the mechanics and contacts still in float64; kept on save."""
    system = dc.load_system(task)
    steps = 4
    z0 = _states_before_contact(task, 2, steps)
    ref = system.simulate(z0, steps)
    m64 = LearnedModel(task, hidden=(16, 16)).double()
    mixed = LearnedModel(task, hidden=(16, 16), potential_dtype="float32").double()
    mixed.load_state_dict(m64.state_dict())
    assert mixed.options()["potential_dtype"] == "float32"
    assert "potential_dtype" not in m64.options()
    results = []
    for m in (m64, mixed):
        m.zero_grad()
        out = m.simulate(z0, steps)
        assert out.dtype == torch.float64
        loss = (out - ref).abs().mean()
        loss.backward()
        grads = torch.cat([p.grad.flatten() for p in m.parameters() if p.grad is not None])
        results.append((loss.detach(), grads))
    (l64, g64), (lm, gm) = results
    assert float((lm - l64).abs() / l64) < 1e-6
    assert 0 < float((gm - g64).norm() / g64.norm()) < 1e-4  # differs (float32), but little
    m = LearnedModel.from_checkpoint(mixed.checkpoint())
    assert m.potential.compute_dtype == torch.float32
    with pytest.raises(ValueError, match="potential_dtype"):
        LearnedModel(task, potential_dtype="half")
    # set on a trained model (to plan or simulate faster): the same rollout as built so
    m64.potential_dtype = "float32"
    assert m64.potential.compute_dtype == torch.float32
    assert m64.options()["potential_dtype"] == "float32"
    torch.testing.assert_close(m64.simulate(z0, steps), mixed.simulate(z0, steps), rtol=0, atol=0)
    m64.potential_dtype = None
    assert m64.potential.compute_dtype is None and "potential_dtype" not in m64.options()
    with pytest.raises(ValueError, match="potential_dtype"):
        m64.potential_dtype = "half"


@pytest.mark.parametrize("compute_dtype", [None, torch.float32])
def test_potential_gradient_written_out_equals_autograd(compute_dtype):
    """PotentialMLP.gradient (what the dynamics use) is autograd's gradient of V, and so
    are its own derivatives (wrt x and the weights: what a training step differentiates),
    to float64 rounding (float32's when the network runs in float32)."""
    from diffcontact.learning.models.physical import PotentialMLP
    from diffcontact.mechanics import potential_gradient

    torch.manual_seed(0)
    net = PotentialMLP(12, hidden=(32, 24, 16), compute_dtype=compute_dtype).double()
    x = (3.0 * torch.randn(5, 6, 2, dtype=torch.float64)).requires_grad_(True)
    auto = torch.autograd.grad(net(x).sum(), x, create_graph=True)[0]
    mine = net.gradient(x)
    assert mine.shape == x.shape and mine.dtype == torch.float64
    tol = 1e-12 if compute_dtype is None else 1e-5
    scale = float(auto.detach().abs().max())
    assert float((mine - auto).detach().abs().max()) <= tol * scale
    w = torch.randn_like(x)
    inputs = [x, *net.parameters()]
    d_auto = torch.autograd.grad((auto * w).sum(), inputs)
    d_mine = torch.autograd.grad((mine * w).sum(), inputs)
    for a, b in zip(d_auto, d_mine, strict=True):
        assert float((a - b).abs().max()) <= 10 * tol * float(a.abs().max())
    # potential_gradient uses it, with a graph only when asked
    torch.testing.assert_close(potential_gradient(net, x, create_graph=True), mine)
    plain = potential_gradient(net, x)
    assert not plain.requires_grad
    torch.testing.assert_close(plain, mine.detach())


def test_a_rollout_casts_the_float32_potential_once():
    """potential_dtype="float32" in a float64 model: a rollout holds the network's
    parameters cast to float32 once (PotentialMLP.for_rollout), not at each of its grad V
    evaluations (4 RK4 stages per step), with the module's values and gradients."""
    from torch.utils._python_dispatch import TorchDispatchMode

    model = LearnedModel("BP5", hidden=(16, 16), potential_dtype="float32").double()
    z0 = _states_before_contact("BP5", 2, 3)
    net = model.potential
    ptrs = {p.data_ptr() for p in net.parameters()}

    class CountCasts(TorchDispatchMode):
        casts = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func is torch.ops.aten._to_copy.default and args[0].data_ptr() in ptrs:
                CountCasts.casts += 1
            return func(*args, **(kwargs or {}))

    with CountCasts():
        out = model.simulate(z0, 3)
    assert CountCasts.casts == len(ptrs)  # once each, not per evaluation
    # the cast potential's values and gradients are the module's
    once = net.for_rollout()
    assert once is not net
    x = z0[:, 0].clone().requires_grad_(True)
    for f in (lambda p: p(x), lambda p: p.gradient(x)):
        got, want = f(once), f(net)
        torch.testing.assert_close(got, want, rtol=0, atol=0)
        grads = [torch.autograd.grad(g.sin().sum(), [x, *net.parameters()]) for g in (got, want)]
        for a, b in zip(*grads, strict=True):
            torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    assert out.dtype == torch.float64
    # in float64 (no compute dtype), and already in float32: the module itself
    plain = LearnedModel("BP5", hidden=(8,)).double().potential
    assert plain.for_rollout() is plain
    f32 = LearnedModel("BP5", hidden=(8,), potential_dtype="float32").potential
    assert f32.for_rollout() is f32


def test_training_rollouts_keep_the_paper_s_constant_penetration_target(tmp_path):
    """A learned model's rollouts treat the compensation target as a constant of the
    gradient by default (the paper's training set-up, appendix G), as
    ``System.simulate(penetration_gradient=False)`` does; ``penetration_gradient=True``
    gives the exact derivative, ``System.simulate``'s default. The two differ through
    a contact whose target shapes the impulse (CP3's ground)."""
    truth, m = _truth_model("CP3", "CM-CD-CLNN", hidden=(8,))
    m.potential = ChainGravity(truth.mass, truth.gravity)
    _, exact = _truth_model("CP3", "CM-CD-CLNN", hidden=(8,), penetration_gradient=True)
    exact.potential = m.potential
    z0 = _states_before_contact("CP3", 2, 6)
    weights = torch.randn(2, 7, 2, 3, 2, dtype=F64, generator=torch.Generator().manual_seed(0))

    def grad(model_or_system, **kw):
        z = z0.clone().requires_grad_()
        if isinstance(model_or_system, LearnedModel):
            traj = model_or_system.simulate(z, 6)
        else:
            traj = model_or_system.simulate(z, 6, contact_model="CM", **kw)
        (traj * weights).sum().backward()
        return z.grad

    paper, derivative = grad(m), grad(exact)
    torch.testing.assert_close(paper, grad(truth, penetration_gradient=False))
    torch.testing.assert_close(derivative, grad(truth))
    assert float((paper - derivative).abs().max()) > 1e-3 * float(derivative.abs().max())
    assert "penetration_gradient" not in m.options()  # (files stay as before)
    _, saved = _truth_model("CP3", "CM-CD-CLNN", hidden=(8,), penetration_gradient=True)
    saved.save(tmp_path / "model.pt")
    assert load_model(tmp_path).penetration_gradient is True
    with pytest.raises(ValueError, match="penetration_gradient must be True or False"):
        LearnedModel("CP3", penetration_gradient="yes")


@pytest.mark.parametrize("model", ["CM-CD-CLNN", "MLP-CD-CLNN"])
def test_hidden_widths_are_checked_up_front(model, tmp_path, capsys):
    """hidden=[] built a model that failed at its first rollout (an IndexError), and the
    physical models read hidden="16" as [1, 6] and 16.7 as 16."""
    from diffcontact.cli import main
    from diffcontact.learning import create_model

    for bad in ([], [16.7], [True, 4], "16,x", 16):
        with pytest.raises(ValueError, match=r"hidden must be a non-empty list of positive"):
            create_model(model, "CP3", hidden=bad)
    assert create_model(model, "CP3", hidden="16,8").options()["hidden"] == [16, 8]
    assert create_model(model, "CP3", hidden="16").options()["hidden"] == [16]
    data = tmp_path / "data"
    assert main(["generate", "CP3", "--out", str(data), "--n-train", "2", "--n-val", "1",
                 "--n-test", "1", "--quiet"]) == 0  # fmt: skip
    run = tmp_path / "run"
    argv = ["train", str(data), "--out", str(run), "--model", model, "--model-option", "hidden=[]"]
    assert main([*argv, "--quiet"]) == 2
    assert "hidden must be a non-empty list" in capsys.readouterr().err
    assert not run.exists()  # nothing written


@pytest.mark.parametrize("model", ["CM-CD-CLNN", "MLP-CD-CLNN"])
def test_model_files_whose_contents_do_not_fit_are_named(model, tmp_path):
    """Edited model files gave multi-line RuntimeErrors and TypeErrors (exit 1 with a
    traceback from evaluate and refit), and the baselines loaded any format_version."""
    from diffcontact.learning import create_model, load_model, save_model

    path = save_model(create_model(model, "CP3", hidden=[4]), tmp_path / "model.pt")
    good = torch.load(path, weights_only=True)
    edits = {
        "a weight missing": lambda d: d["state_dict"].pop(next(iter(d["state_dict"]))),
        "options of another kind": lambda d: d["options"].update(nonsense=1),
        "options not a dict": lambda d: d.update(options=[1, 2]),
        "a newer format": lambda d: d.update(format_version=99),
        # loaded silently before: NaN learned values, or the file's other model name
        "a NaN weight": lambda d: d["state_dict"].update(
            {k: v * float("nan") for k, v in list(d["state_dict"].items())[:1]}
        ),
        "a model name the options disagree with": lambda d: d.update(
            model_name="CMr-CD-CLNN" if model == "CM-CD-CLNN" else "IN-CP-CLNN"
        ),
    }
    for what, edit in edits.items():
        data = {k: (dict(v) if isinstance(v, dict) else v) for k, v in good.items()}
        edit(data)
        torch.save(data, tmp_path / "edited.pt")
        with pytest.raises(ValueError, match=str(tmp_path / "edited.pt")) as caught:
            load_model(tmp_path / "edited.pt")
        assert "\n" not in str(caught.value), what
        if what == "a newer format":  # (a CM model's said "format 1 ...: retrain")
            assert "format 99 is not supported" in str(caught.value)
            assert "written by a newer diffcontact" in str(caught.value), model
        if what == "a NaN weight":
            assert "weights with NaN or infinite values: " in str(caught.value)
        if what == "a model name the options disagree with" and model == "CM-CD-CLNN":
            assert "disagree" in str(caught.value)  # (a baseline's options name no model)


@pytest.mark.parametrize("name", ["CMr-CD-CLNN", "LCP-CD-CLNN", "Coulomb-CD-CLNN", "CM-CD-CHNN"])
def test_as_system_rolls_out_the_model(name):
    """as_system()'s simulate is the model's rollout: its contact model (CMr's eps with it)
    and dynamics are the system's defaults (a CMr, LCP or Coulomb model's had run CM:
    0.66 apart on BP5-e), and a CM model refuses an eps instead of ignoring it."""
    options = {"eps": 0.05} if name.startswith("CMr") else {}
    model = LearnedModel("CP3", model=name, hidden=(8,), **options).double()
    z0 = model.system.sample_initial_conditions(4, seed=3)
    system = model.as_system()
    assert (system.contact_model, system.dynamics) == (model.contact_model, model.dynamics)
    with torch.no_grad():
        torch.testing.assert_close(system.simulate(z0, 30), model.simulate(z0, 30))
    if not name.startswith("CMr"):
        with pytest.raises(ValueError, match=f"{name} has no eps"):
            model.simulate(z0, 3, eps=0.1)  # (ran as without it)


@pytest.mark.parametrize("potential_dtype", [None, "float32"])
def test_as_system_keeps_the_values_of_the_moment(potential_dtype):
    """as_system's potential was the live network: training on changed the system."""
    from diffcontact.learning import create_model

    z0 = dc.load_system("CP3").sample_initial_conditions(2, seed=0)
    model = create_model("CM-CD-CLNN", "CP3", hidden=[8], potential_dtype=potential_dtype).double()
    system = model.as_system()
    before = system.simulate(z0, 10)
    torch.testing.assert_close(before, model.simulate(z0, 10).detach(), rtol=0, atol=0)
    with torch.no_grad():
        model.potential.layers[0].weight.mul_(0.5)
    assert torch.equal(system.simulate(z0, 10), before)
    if isinstance(system.potential_model, nn.Module):
        assert not any(t.requires_grad for t in system.potential_model.parameters())


def test_set_parameters_refuses_what_the_model_cannot_hold():
    """Masses its float32 parameters cannot hold were stored as 0 or inf, a string gave
    torch's TypeError, and eps on a model without a regulariser was ignored."""
    model = LearnedModel("BP5", hidden=(8,))  # float32 parameters
    before = model.learned_parameters()
    for bad, match in (([1e-50] * 5, "positive and finite in torch.float32"),
                       ([1e50] * 5, "positive and finite in torch.float32"),
                       ("abc", "mass must be numbers")):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            model.set_parameters(mass=bad)
    with pytest.raises(ValueError, match="eps is the regulariser of the CMr models; CM-CD-CLNN"):
        model.set_parameters(eps=0.05)
    assert model.learned_parameters() == before  # nothing changed
    tiny = LearnedModel("BP5", hidden=(8,)).double().set_parameters(mass=[1e-50] * 5)
    assert tiny.learned_parameters()["mass"][0] == pytest.approx(1e-50)  # float64 holds it
    learnable = LearnedModel("BP5-e", model="CMr-CD-CLNN", eps="learnable", hidden=(8,))
    for bad in (1e300, 1e-300):  # stored as inf and 0 (a later simulate: "eps must be positive")
        with pytest.raises(ValueError, match=r"eps must be positive and finite in torch\.float32"):
            learnable.set_parameters(eps=bad)
