"""The baselines MLP-CD-CLNN, IN-CP-CLNN and IN-SP-CP (learning/models/baselines.py)."""

from __future__ import annotations

import json
import math

import pytest
import torch

from diffcontact.contact import PoissonTwoPhase
from diffcontact.contact.models import ContactParams, ContactState
from diffcontact.learning.models.baselines import (
    INCPCLNN,
    INSPCP,
    MLPCDCLNN,
    ContactIN,
    ContactMLP,
    _GraphTables,
)
from diffcontact.learning.models.protocol import DynamicsModel, OptimizerSettings
from diffcontact.learning.models.registry import (
    BASELINE_MODELS,
    create_model,
    is_physical_model,
    model_names,
)
from diffcontact.learning.models.storage import load_model, save_model
from diffcontact.systems import list_tasks, load_system
from diffcontact.testing import assert_gradients_close, run_cli

from ..training.support import write_dataset

pytestmark = [
    pytest.mark.filterwarnings("ignore::RuntimeWarning"),  # random networks may tunnel
    pytest.mark.filterwarnings("ignore:.*LeafSpec"),
]

TASKS = list_tasks()
# small networks: the tests check the plumbing, not what the networks learn
SMALL = {
    "MLP-CD-CLNN": {"hidden": [8, 8], "contact_hidden": [8], "embedding": 3},
    "IN-CP-CLNN": {"hidden": [8, 8], "latent": 6, "contact_hidden": [8], "message_steps": 2},
    "IN-SP-CP": {"hidden": [8], "latent": 6, "message_steps": 2},
}
CLASSES = {"MLP-CD-CLNN": MLPCDCLNN, "IN-CP-CLNN": INCPCLNN, "IN-SP-CP": INSPCP}
_CACHE: dict[str, torch.Tensor] = {}


def contact_states(task: str) -> torch.Tensor:
    """``(n, 2, P, dim)`` true states whose next step has a contact (one per trajectory
    of 3 that has one), cached per task."""
    if task not in _CACHE:
        system = load_system(task)
        traj = system.simulate(system.sample_initial_conditions(3, seed=0), on_tunnelling="ignore")
        N, T = traj.shape[:2]
        flat = traj[:, :-1].reshape(-1, *system.state_shape)
        hit = (system.gaps(system.integrate(flat)[:, 0]) < 0).any(-1).reshape(N, T - 1)
        rows = hit.any(-1).nonzero().flatten()
        first = hit.to(torch.int8).argmax(-1)[rows]
        _CACHE[task] = traj[rows, first]
    return _CACHE[task]


def build(name: str, task: str, seed: int = 0, **options):
    torch.manual_seed(seed)
    return create_model(name, task, **{**SMALL[name], **options})


def test_registered_as_built_ins():
    names = model_names()
    for name in BASELINE_MODELS:
        assert name in names and not is_physical_model(name)
        model = build(name, "CP3")
        assert isinstance(model, CLASSES[name]) and isinstance(model, DynamicsModel)
        assert model.model_name == name
        assert model.state_shape == (2, 3, 2) and model.dt == 0.01 and model.default_steps == 99


@pytest.mark.parametrize("task", TASKS)
@pytest.mark.parametrize("name", BASELINE_MODELS)
def test_every_task_rolls_out_with_the_state_layout(name, task):
    z0 = contact_states(task)
    assert len(z0) > 0
    model = build(name, task)
    traj = model.simulate(z0, 2, check_overlap=False)
    assert traj.shape == (len(z0), 3, *load_system(task).state_shape)
    assert traj.dtype == torch.float64 and torch.isfinite(traj).all()
    assert torch.equal(traj[:, 0], z0)
    model32 = model.to(torch.float32)
    traj32 = model32.simulate(z0[:1].float(), 1, check_overlap=False)
    assert traj32.dtype == torch.float32 and traj32.shape == (1, 2, *z0.shape[1:])


@pytest.mark.parametrize("name", BASELINE_MODELS)
def test_a_rollout_too_large_is_refused_up_front(name):
    """simulate(z0, 10**12) stepped until the memory was full."""
    model = build(name, "BP5")
    z0 = load_system("BP5").sample_initial_conditions(2, seed=0)
    with pytest.raises(ValueError, match=r"simulate BP5: steps=1000000000000: at most"):
        model.simulate(z0, 10**12)


@pytest.mark.parametrize("task", ["BP5", "BD5", "CP3", "Gyro", "Rope"])
@pytest.mark.parametrize("name", BASELINE_MODELS)
def test_gradients_reach_every_parameter(name, task):
    model = build(name, task)
    z0 = contact_states(task).clone().requires_grad_(True)
    traj = model.simulate(z0, 2, check_overlap=False)
    traj[:, 1:].square().sum().backward()
    assert torch.isfinite(z0.grad).all() and z0.grad.abs().sum() > 0
    for pname, p in model.named_parameters():
        assert p.grad is not None, pname
        assert torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, pname
    groups = model.param_groups(OptimizerSettings(lr=1e-3, weight_decay=0.0, physics_lr=1e-2))
    grouped = [id(p) for g in groups for p in g["params"]]
    assert sorted(grouped) == sorted(id(p) for p in model.parameters())  # each exactly once
    assert all("name" in g for g in groups)


@pytest.mark.parametrize("name", BASELINE_MODELS)
def test_gradients_match_finite_differences(name):
    """Through a rollout with a contact: a network weight and the initial state."""
    model = build(name, "BP5").double()
    z0 = contact_states("BP5")[:2]
    pname = {
        "MLP-CD-CLNN": "contact_net.net.layers.0.weight",
        "IN-CP-CLNN": "contact_net.decoder.layers.0.weight",
        "IN-SP-CP": "network.edge_encoder.layers.0.weight",
    }[name]
    weight = dict(model.named_parameters())[pname]

    def rollout(w, z):
        return torch.func.functional_call(model, {pname: w}, (z, 2), {"check_overlap": False})

    assert_gradients_close(rollout, (weight.detach(), z0), rtol=1e-5, eps=1e-6)


@pytest.mark.parametrize("name", BASELINE_MODELS)
def test_a_rollout_alone_equals_the_same_rollout_in_a_batch(name):
    """Padding (contacts, edges) and batching change nothing."""
    z = torch.cat([contact_states("BP5"), contact_states("BP5")[:1] * 0.9 + 0.05])
    model = build(name, "BP5")
    with torch.no_grad():
        batch = model.simulate(z, 3, check_overlap=False)
        alone = torch.cat(
            [model.simulate(z[i : i + 1], 3, check_overlap=False) for i in range(len(z))]
        )
    torch.testing.assert_close(batch, alone, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("net_cls", [ContactMLP, ContactIN])
def test_padded_contacts_change_nothing(net_cls):
    """``resolve`` with an extra inactive (padded) contact gives the same velocities."""
    system = load_system("BP5")
    tables = _GraphTables(system)
    torch.manual_seed(0)
    net = ContactMLP(tables, [8], 2) if net_cls is ContactMLP else ContactIN(tables, 6, [8], 1)
    z = contact_states("BP5")[:1]
    x = system.integrate(z)[:, 0]
    gaps = system.gaps(x)
    active_ids = (gaps[0] < 0).nonzero().flatten()
    inactive = (gaps[0] >= 0).nonzero().flatten()[:1]
    v = z[:, 1].reshape(1, -1)
    Mh = torch.diag(torch.rand(v.shape[-1], dtype=torch.float64) + 0.5)[None]
    outs = []
    for ids, mask in [
        (active_ids, torch.ones(len(active_ids), dtype=torch.bool)),
        (torch.cat([active_ids, inactive]), torch.arange(len(active_ids) + 1) < len(active_ids)),
    ]:
        idx, active = ids[None], mask[None]
        J = system.geometry.jacobian(x, idx) * active[..., None, None, None]
        J = J.reshape(1, -1, v.shape[-1])
        params = ContactParams(mu=torch.zeros(1, len(ids)), cor=torch.zeros(1, len(ids)))
        state = ContactState(x, gaps.gather(-1, idx), idx, torch.zeros(1, dtype=torch.long),
                             system.geometry)  # fmt: skip
        res = net.resolve(J, Mh, v, params, active, system.d, state=state)
        outs.append(res)
    torch.testing.assert_close(outs[1].v_plus, outs[0].v_plus, rtol=0, atol=1e-15)
    assert not torch.equal(outs[0].v_plus, v)  # the network did act
    assert torch.all(outs[1].f_c.reshape(1, -1, system.d)[:, -1] == 0)


@pytest.mark.parametrize("task", TASKS)
def test_contact_jacobians_live_on_the_contact_points(task):
    """The graph tables lose no Jacobian entry: J_C restricted to each contact's
    points (dense and from the sparse rows) holds all of it."""
    system = load_system(task)
    tables = _GraphTables(system)
    x = contact_states(task)[:, 0]
    K = system.n_contacts
    idx = torch.arange(K).expand(len(x), K)
    J = system.geometry.jacobian(x, idx)  # (n, K, d, P, dim)
    J_e = tables.restrict(J, idx)
    jac = system.geometry.jacobian_sparse(x, idx)
    torch.testing.assert_close(tables.restrict_sparse(jac.points, jac.values, idx), J_e)
    assert torch.allclose(J_e.abs().sum((-1, -2)), J.abs().sum((-1, -2)), rtol=1e-12, atol=0)


def test_learned_contact_models_get_the_contact_state_and_others_do_not():
    """The protocol extension: ``state=`` only for models that ask for it."""
    system = load_system("BP5")
    z0 = contact_states("BP5")
    seen = []

    class Spy:
        needs_contact_state = True

        def __init__(self):
            self.inner = PoissonTwoPhase()

        def resolve(self, J_C, Mhat_inv, v, params, active, d, *, state, **kwargs):
            seen.append(state)
            return self.inner.resolve(J_C, Mhat_inv, v, params, active, d, **kwargs)

    class Plain:  # the pre-existing protocol: no state keyword
        def __init__(self):
            self.inner = PoissonTwoPhase()

        def resolve(self, J_C, Mhat_inv, v, params, active, d, *, v_C_star=None, settings=None):
            return self.inner.resolve(J_C, Mhat_inv, v, params, active, d, v_C_star=v_C_star,
                                      settings=settings)  # fmt: skip

    ref = system.simulate(z0, 1, contact_model="CM")
    torch.testing.assert_close(system.simulate(z0, 1, contact_model=Spy()), ref)
    torch.testing.assert_close(system.simulate(z0, 1, contact_model=Plain()), ref)
    (state,) = seen
    n, Ka = state.contact_index.shape
    assert state.x.shape == (n, 5, 2) and state.gaps.shape == (n, Ka) and n == len(z0)
    x1 = system.integrate(z0)[:, 0]
    torch.testing.assert_close(state.x, x1[state.batch_index])
    torch.testing.assert_close(state.gaps, system.gaps(x1)[state.batch_index].gather(-1,
                               state.contact_index))  # fmt: skip
    assert (state.gaps[:, 0] < 0).all()


@pytest.mark.parametrize("name", BASELINE_MODELS)
def test_save_and_load_round_trip(name, tmp_path):
    model = build(name, "BD5")
    options = model.options()
    assert json.loads(json.dumps(options)) == options  # plain data
    path = save_model(model, tmp_path / "model.pt")
    loaded = load_model(path)
    assert type(loaded) is type(model) and loaded.options() == options
    z0 = contact_states("BD5")
    with torch.no_grad():
        torch.testing.assert_close(
            loaded.simulate(z0, 2, check_overlap=False), model.simulate(z0, 2, check_overlap=False),
            rtol=0, atol=0,
        )  # fmt: skip
    # a float32 model stays float32
    save_model(model.to(torch.float32), tmp_path / "m32.pt")
    assert next(load_model(tmp_path / "m32.pt").parameters()).dtype == torch.float32


def test_clnn_baselines_report_masses_and_no_contact_parameters():
    model = build("IN-CP-CLNN", "BD5")
    learned = model.learned_parameters()
    assert learned["mass"] == pytest.approx([1.0] * 5) and learned["mu"] is None
    assert len(learned["second_moments"]) == 5
    assert set(model.metrics()) == {"param/mass_0"} | {f"param/mass_ratio_{i}" for i in range(1, 5)}
    assert build("IN-SP-CP", "BD5").metrics() == {}


@pytest.mark.parametrize(
    ("name", "options", "needle"),
    [
        ("MLP-CD-CLNN", {"contact_hidden": [8, 0]}, "contact_hidden"),
        ("MLP-CD-CLNN", {"embedding": -1}, "embedding"),
        ("MLP-CD-CLNN", {"hidden": "a,b"}, "hidden"),
        ("MLP-CD-CLNN", {"latent": 8}, "latent"),  # an option of the INs only
        ("IN-CP-CLNN", {"latent": 0}, "latent"),
        ("IN-CP-CLNN", {"message_steps": 1.5}, "message_steps"),
        ("IN-SP-CP", {"hidden": 64}, "hidden"),
        ("IN-SP-CP", {"eps": 0.1}, "eps"),
    ],
)
def test_bad_options_are_named(name, options, needle):
    with pytest.raises(ValueError, match=needle):
        create_model(name, "CP3", **options)


def test_an_unknown_option_is_named_without_the_class_internals():
    """``--model-option foo=1`` showed the options dict and ``LearnedModel.__init__()``."""
    for name in ("CM-CD-CLNN", "IN-SP-CP"):
        with pytest.raises(ValueError, match=rf"^model '{name}' has no option 'foo'$"):
            create_model(name, "CP3", foo=1)


def test_eps_is_refused_and_hidden_given_twice_is_refused(cp3_data, tmp_path, capsys):
    for extra, needle in [
        (["--eps", "0.1"], "eps"),
        (["--model-option", "hidden=[4]"], "twice"),
        # (it said "model 'IN-SP-CP' has no option 'potential_dtype'", an internal name)
        (["--potential-dtype", "float32"], "--potential-dtype applies to the physical models"),
    ]:
        code, _, err = run_cli(
            capsys, "train", str(cp3_data), "--out", str(tmp_path / "r"), "--model", "IN-SP-CP",
            "--hidden", "8", *extra, "--quiet",
        )  # fmt: skip
        assert code == 2 and needle in err and err.count("\n") == 1, err


def test_string_widths_are_read():
    model = create_model("IN-SP-CP", "CP3", hidden="12,10", latent=4)
    assert model.options()["hidden"] == [12, 10]


@pytest.fixture(scope="module")
def cp3_data(tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("cp3"), "CP3", n=(8, 2, 2), steps=12)


@pytest.mark.parametrize("name", BASELINE_MODELS)
def test_train_and_evaluate_through_the_cli(name, cp3_data, tmp_path, capsys):
    run, ev = tmp_path / "run", tmp_path / "eval"
    others = {k: v for k, v in SMALL[name].items() if k != "hidden"}
    opts = [a for k, v in others.items() for a in ("--model-option", f"{k}={json.dumps(v)}")]
    hidden = ",".join(map(str, SMALL[name]["hidden"]))  # --hidden applies to the baselines
    code, out, err = run_cli(
        capsys, "train", str(cp3_data), "--out", str(run), "--model", name, "--epochs", "1",
        "--batch-size", "4", "--hidden", hidden, *opts, "--quiet",
    )  # fmt: skip
    assert code == 0, err
    learned = json.loads((run / "learned.json").read_text())
    assert learned["finished"] and learned["global_step"] == 2
    assert json.loads((run / "run.json").read_text())["options"] == SMALL[name]
    code, out, err = run_cli(capsys, "evaluate", str(run), "--out", str(ev), "--steps", "10",
                             "--n-gif", "0")  # fmt: skip
    assert code == 0, err
    metrics = json.loads((ev / "metrics.json").read_text())
    assert metrics["model"] == name and metrics["steps"] == 10
    assert math.isfinite(metrics["rel_err_mean"]) and metrics["rel_err_mean"] > 0
    assert metrics["mu"]["learned"] is None and metrics["cor"]["learned"] is None
    assert "(not learned)" in out
    if name == "IN-SP-CP":
        assert metrics["mass_ratios"]["learned"] is None
    else:
        assert len(metrics["mass_ratios"]["learned"]) == 2
        assert "m2/m1" in out


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("name", BASELINE_MODELS)
def test_cuda_rollout_matches_cpu(name):
    """The same weights roll out on CUDA as on the CPU (float64), gradients included."""
    model = build(name, "BD5").double()
    z0 = contact_states("BD5")
    cpu = model.simulate(z0, 3, check_overlap=False)
    cuda_model = build(name, "BD5").double().cuda()
    cuda_model.load_state_dict(model.state_dict())
    gpu = cuda_model.simulate(z0.cuda(), 3, check_overlap=False)
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-9, atol=1e-10)
    gpu.square().sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in cuda_model.parameters())
