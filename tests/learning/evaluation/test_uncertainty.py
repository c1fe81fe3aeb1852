"""Parameter uncertainty: Gauss-Newton standard errors, determined / stable flags, regimes."""

from __future__ import annotations

import json
import math

import pytest
import torch

from diffcontact.learning.evaluation.uncertainty import (
    UncertaintySettings,
    contact_regimes,
    parameter_uncertainty,
)
from diffcontact.learning.models.physical import LearnedModel
from diffcontact.systems import System, load_config


@pytest.fixture(scope="module")
def bp5():
    """Exact BP5 chunks (truth, no potential) and a model holding the true values."""
    system = System(load_config("BP5"))
    z0 = system.sample_initial_conditions(24, seed=3)
    traj = system.simulate(z0, 30)
    chunks = traj.unfold(1, 5, 5).permute(0, 1, 5, 2, 3, 4).reshape(-1, 5, *traj.shape[2:])
    truth = system.parameters()
    return chunks, truth


def _model(truth, **changes):
    model = LearnedModel("BP5", model="CM-CD-CLNN").double()
    model.potential = None  # BP5 has no potential: the exact model
    values = {"mass": truth.mass, "mu": truth.mu, "cor": truth.cor} | changes
    return model.set_parameters(**values)


def test_exact_model_flags_only_unexercised_contacts(bp5):
    chunks, truth = bp5
    model = _model(truth)
    u = parameter_uncertainty(model, chunks)
    regimes = contact_regimes(model, chunks)
    assert u["residual_mean_abs"] < 1e-9  # the solver's accuracy
    assert u["n_parameters"] == 4 + 30 + 30
    assert all(u["mass_ratios"]["determined"])
    assert u["mass_ratios"]["value"] == pytest.approx([2, 6, 8, 10], rel=1e-12)
    for k in range(30):
        if regimes["impacts"][k] == 0:  # the data never see it: the loss is flat along it
            assert u["cor"]["std_error"][k] is None and not u["cor"]["determined"][k]
            assert "flat" in u["cor"]["reason"][k]
        if regimes["sliding"][k] == 0:  # mu only matters in sliding impacts
            assert not u["mu"]["determined"][k], k
        else:
            assert u["mu"]["determined"][k], (k, u["mu"]["reason"][k])
    assert sum(regimes["impacts"]) > 0 and sum(regimes["sliding"]) > 0
    # the counts add up
    for k in range(30):
        parts = regimes["sliding"][k] + regimes["sticking"][k] + regimes["separating"][k]
        assert parts == regimes["impacts"][k]


def test_gauss_newton_step_points_back_to_the_truth(bp5):
    """A wrong mu / e_P of an exercised contact is flagged unstable; the step undoes it."""
    chunks, truth = bp5
    regimes = contact_regimes(_model(truth), chunks)
    k = max(range(30), key=lambda i: regimes["sliding"][i])
    j = max(range(30), key=lambda i: regimes["impacts"][i])
    mu, cor = truth.mu.clone(), truth.cor.clone()
    # small errors: the step is the linearised correction, exact only near the optimum
    mu[k] += 0.02
    cor[j] = cor[j] - 0.02 if cor[j] > 0.5 else cor[j] + 0.02
    settings = UncertaintySettings(mu_tol=0.01, cor_tol=0.01)
    u = parameter_uncertainty(_model(truth, mu=mu, cor=cor), chunks, settings=settings)
    assert not u["mu"]["determined"][k] and "not stable" in u["mu"]["reason"][k]
    assert u["mu"]["step"][k] == pytest.approx(-0.02, rel=0.2)
    assert not u["cor"]["determined"][j] and "not stable" in u["cor"]["reason"][j]
    assert u["cor"]["step"][j] == pytest.approx(float(truth.cor[j] - cor[j]), rel=0.2)
    lo, hi = u["mu"]["ci95"][k]
    assert lo <= u["mu"]["value"][k] <= hi


def test_standard_errors_scale_with_the_noise(bp5):
    """With noisy data the errors follow the residual scale: b^2 (J^T J)^-1, b = mean |r|."""
    chunks, truth = bp5
    model = _model(truth)
    gen = torch.Generator().manual_seed(0)
    errors = []
    for std in (1e-5, 1e-4):
        noisy = chunks.clone()
        noisy[:, 1:] += std * torch.randn(noisy[:, 1:].shape, generator=gen, dtype=noisy.dtype)
        u = parameter_uncertainty(model, noisy)
        assert u["residual_mean_abs"] == pytest.approx(std * (2 / math.pi) ** 0.5, rel=0.1)
        errors.append(u["mass_ratios"]["std_error"][0])
    assert errors[1] / errors[0] == pytest.approx(10, rel=0.15)


def test_bad_input_is_named(bp5):
    chunks, truth = bp5
    model = _model(truth)
    with pytest.raises(ValueError, match="chunks must have shape"):
        parameter_uncertainty(model, chunks[:, :, :, :2])
    with pytest.raises(ValueError, match="no training chunk is finite"):
        parameter_uncertainty(model, torch.full_like(chunks[:2], math.nan))
    with pytest.raises(ValueError, match="no physical parameters"):
        parameter_uncertainty(torch.nn.Linear(2, 2), chunks)
    with pytest.raises(ValueError, match="step must be a positive number"):
        UncertaintySettings(step=0)


def test_flags_on_a_synthetic_loss():
    """Kinks are one-sided, clamped values the data would move are unstable."""
    from diffcontact.learning.evaluation.uncertainty import _assess, _Layout

    gen = torch.Generator().manual_seed(1)
    layout = _Layout(n_mass=1, n_moments=0, n_mu=2, n_cor=1)
    A = torch.randn(400, 4, generator=gen, dtype=torch.float64)
    noise = 1e-4 * torch.randn(400, generator=gen, dtype=torch.float64)
    value = torch.tensor([0.5, 0.2, 0.3, 1.0], dtype=torch.float64)  # log ratio, mu, mu, e_P
    target = value.clone()
    target[3] = 0.97  # the data want e_P = 0.97; the clamp holds it at 1

    def residuals(theta):
        smooth = theta.clone()
        smooth[2] = (theta[2] - 0.3).clamp_min(0)  # mu[1] matters above 0.3 only
        ref = target.clone()
        ref[2] = 0.0
        return A @ (smooth - ref) + noise

    h = 1e-5
    plus = torch.tensor([h, h, h, 0.0], dtype=torch.float64)  # e_P = 1: no step up
    minus = -torch.full((4,), h, dtype=torch.float64)
    rows = [residuals(value)]
    rows += [residuals(value + torch.eye(4, dtype=torch.float64)[i] * plus[i]) for i in range(4)]
    rows += [residuals(value + torch.eye(4, dtype=torch.float64)[i] * minus[i]) for i in range(4)]
    u = _assess(torch.stack(rows), plus, minus, value, layout, UncertaintySettings())
    assert u["mass_ratios"]["determined"] == [True], u["mass_ratios"]["reason"]
    assert u["mass_ratios"]["value"][0] == pytest.approx(math.exp(0.5))
    assert u["mu"]["determined"] == [True, False]
    assert "one-sided" in u["mu"]["reason"][1]
    assert u["cor"]["determined"] == [False] and "not stable" in u["cor"]["reason"][0]
    assert u["cor"]["step"][0] == pytest.approx(-0.03, rel=0.05)
    se = u["mu"]["std_error"][0]
    assert 0 < se < 3e-3  # about b / |A column|: 0.03 * 0.8 / 20


def test_evaluate_writes_and_prints_the_uncertainty(tmp_path, dataset, capsys):
    """``diffcontact evaluate`` assesses a physical model; --no-uncertainty skips it."""
    import json

    from .support import TINY, cli, run_dir

    run = run_dir(tmp_path, dataset, log=False)
    LearnedModel(TINY, hidden=(4,)).double().save(run / "model.pt")
    out = tmp_path / "evaluation"
    argv = ["evaluate", str(run), "--steps", "3", "--n-gif", "0", "--out", str(out)]
    assert cli(argv) == 0
    printed = capsys.readouterr().out
    m = json.loads((out / "metrics.json").read_text())
    u = m["uncertainty"]
    assert set(u) >= {"mass_ratios", "mu", "cor", "regimes", "residual_mean_abs"}
    assert len(u["mu"]["determined"]) == len(u["mu"]["value"])
    assert "95 % interval" in printed
    reasons = [r for k in ("mass_ratios", "mu", "cor") for r, ok in
               zip(u[k]["reason"], u[k]["determined"], strict=True) if not ok]  # fmt: skip
    assert reasons  # (the untrained model leaves some undetermined)
    for reason in reasons:  # printed with the reason, not only "not determined"
        assert f"? {reason}" in printed, (reason, printed)
    assert cli([*argv, "--no-uncertainty"]) == 0
    assert json.loads((out / "metrics.json").read_text())["uncertainty"] is None


def test_evaluate_reports_an_uncertainty_it_cannot_assess(tmp_path, dataset, monkeypatch):
    """A failure of the assessment is recorded in metrics.json, not a crashed evaluation."""
    from diffcontact.learning.evaluation import evaluate as evaluate_module

    def failing(model, chunks):
        raise ValueError("the learned model's rollouts of the training chunks are not finite")

    monkeypatch.setattr(
        "diffcontact.learning.evaluation.uncertainty.parameter_uncertainty", failing
    )
    from .support import TINY

    model = LearnedModel(TINY, hidden=(4,)).double()
    m = evaluate_module.evaluate(
        None, tmp_path / "out", model=model, data_dir=dataset, n_gif=0, steps=3
    )
    assert m["uncertainty"]["error"].startswith("parameter uncertainty not assessed: ")


# ---------------------------------------------------------------- experiments/uncertainty.py


@pytest.fixture
def script(monkeypatch):
    """experiments/uncertainty.py with its training and assessment replaced (no data, no
    training): each assessment has a new mean residual, so a part shows which run made it."""
    import importlib.util
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[3] / "experiments" / "uncertainty.py"
    spec = importlib.util.spec_from_file_location("_uncertainty_script", path)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "_uncertainty_script", module)
    spec.loader.exec_module(module)
    made: list[dict] = []

    def assess(task, data, run):
        def entry(value):
            return {"value": [value], "ci95": [[value - 0.01, value + 0.01]],
                    "determined": [True], "reason": [""]}  # fmt: skip

        r = {
            "task": task,
            "uncertainty": {
                "tolerances": {"mass_ratio_relative": 0.005, "mu": 0.01, "cor": 0.02},
                "mass_ratios": entry(1.0), "mu": entry(0.5), "cor": entry(0.0),
                "residual_mean_abs": 1.25e-3 * (len(made) + 1), "n_residuals": 10,
                "n_parameters": 3,
            },
            "regimes": {"impacts": [4], "sliding": [1], "sticking": [2], "separating": [1]},
            "seconds": 1.0, "contact_names": ["ground"],
            "truth": {"mass_ratios": [1.0], "mu": [0.5], "cor": [0.0]},
        }  # fmt: skip
        made.append(r)
        return r

    monkeypatch.setattr(module, "train_model", lambda task, out, epochs: (out, out, 0.0))
    monkeypatch.setattr(module, "assess", assess)
    module.made = made
    return module


def _part(doc, module, task: str) -> str:
    text = doc.read_text()
    assert text.count(module.BEGIN) == 1 and text.count(module.END) == 1
    return text.split(f"### {task}\n", 1)[1].split("###", 1)[0]


def test_uncertainty_script_keeps_the_other_tasks(script, tmp_path, capsys):
    """``--tasks BP5`` rewrote the section (and uncertainty.json) with BP5 alone, dropping
    BD5's results; now it replaces BP5's and keeps BD5's, and names both commands."""
    out, doc = tmp_path / "out", tmp_path / "results.md"
    doc.write_text("# results\n\nkept text\n")
    commands = []
    for task in ("BP5", "BD5", "BP5"):
        argv = ["--tasks", task, "--out", str(out), "--doc", str(doc)]
        assert script.main(argv) == 0
        commands.append("python experiments/uncertainty.py " + " ".join(argv))
    first_bp5, bd5, bp5 = script.made
    section = doc.read_text().split(script.BEGIN, 1)[1]
    assert "kept text" in doc.read_text()
    assert "### BD5" in section and "### BP5" in section
    assert section.index("### BD5") < section.index("### BP5")  # TASKS' order
    assert "(BD5, BP5)" in section
    assert f"{bd5['uncertainty']['residual_mean_abs']:.2e}" in _part(doc, script, "BD5")
    assert f"{bp5['uncertainty']['residual_mean_abs']:.2e}" in _part(doc, script, "BP5")
    assert f"{first_bp5['uncertainty']['residual_mean_abs']:.2e}" not in section
    assert f"`{commands[1]}` (BD5; " in section and f"`{commands[2]}` (BP5; " in section
    assert section.count("--tasks BP5") == 1  # the first BP5 run made nothing shown
    stored = json.loads((out / "uncertainty.json").read_text())
    assert [r["task"] for r in stored["results"]] == ["BD5", "BP5"]
    assert (out / "uncertainty.md").read_text() == script.BEGIN + section
    capsys.readouterr()


def test_uncertainty_script_drops_results_of_another_setup(script, tmp_path, capsys):
    """A stored result made with other epochs (or sizes, scan, model) is not reported
    beside today's; one stored before results recorded their set-up is the file's."""
    out = tmp_path / "out"
    assert script.main(["--tasks", "BD5", "--out", str(out)]) == 0
    file = out / "uncertainty.json"
    stored = json.loads(file.read_text())
    stored["results"][0]["setup"]["epochs"] = 5
    file.write_text(json.dumps(stored))
    assert script.main(["--tasks", "BP5", "--out", str(out)]) == 0
    assert [r["task"] for r in json.loads(file.read_text())["results"]] == ["BP5"]
    # a file of before: no command, set-up or producer per result
    stored = json.loads(file.read_text())
    legacy = {k: stored["meta"][k] for k in ("date", "torch", "machine")}
    for r in stored["results"]:
        del r["setup"], r["produced"]
    file.write_text(json.dumps({"meta": legacy, "results": stored["results"]}))
    assert script.main(["--tasks", "BD5", "--out", str(out)]) == 0
    text = (out / "uncertainty.md").read_text()
    assert "### BD5" in text and "### BP5" in text
    assert f"`{script.DEFAULT_COMMAND}` (BP5; " in text
    capsys.readouterr()


def test_uncertainty_script_refuses_a_bad_results_file(script, tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "uncertainty.json").write_text('{"results": []}')

    def no_work(*args):
        raise AssertionError("work started")

    monkeypatch.setattr(script, "train_model", no_work)
    with pytest.raises(SystemExit) as exc:
        script.main(["--out", str(out)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "uncertainty.json is not a results file of uncertainty.py" in err and "--out" in err
