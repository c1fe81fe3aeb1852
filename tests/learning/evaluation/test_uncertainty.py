"""Parameter uncertainty: Gauss-Newton standard errors, determined / stable flags, regimes."""

from __future__ import annotations

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
