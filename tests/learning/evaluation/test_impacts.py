"""impacts.png: observed vs predicted normal velocity ratios of the test data's impacts."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

import diffcontact as dc
from diffcontact.learning.evaluation.impacts import (
    first_impacts,
    impact_ratios,
    impact_summary,
    plot_impacts,
)

F64 = torch.float64
FLOOR = {
    "type": "bouncing_masses", "masses": [1.0], "radii": [0.1], "walls": [[0.0, 1.0, 0.0]],
    "gravity": 0.0, "mu": 0.2, "cor": 0.745, "penetration_fraction": 0.0,
    "dt": 0.01, "horizon": 0.5,
}  # fmt: skip


class CM:
    """The floor system with CM as a model (``simulate(z0, steps)``)."""

    def __init__(self, system):
        self.system = system

    def simulate(self, z0, steps):
        return self.system.simulate(z0, steps, progress=False)


def _data(v_t, v_n=-1.0):
    """Balls sliding into the floor, recorded with exact Coulomb friction (textbook impacts)."""
    system = dc.load_system(FLOOR)
    n = len(v_t)
    z0 = torch.zeros(n, 2, 1, 2, dtype=F64)
    z0[:, 0, 0, 1] = 0.305  # the impact falls between samples (t = 0.205 s)
    z0[:, 1, 0, 0] = torch.tensor(v_t, dtype=F64)
    z0[:, 1, 0, 1] = v_n
    return system, system.simulate(z0, 49, contact_model="Coulomb", progress=False).numpy()


def test_cm_overshoots_the_textbook_rebound_by_its_sliding_lift(tmp_path):
    v_t = [0.0, 0.5, 1.0, 2.0]
    system, traj = _data(v_t)
    found = first_impacts(system, traj)
    assert found.trajectory.tolist() == [0, 1, 2, 3]
    assert found.step.tolist() == [20] * 4 and found.contact.tolist() == [0] * 4
    r = impact_ratios(system, CM(system), traj)
    np.testing.assert_allclose(r["u_n_pre"], -1.0, atol=1e-12)
    np.testing.assert_allclose(r["u_t_pre"], v_t, atol=1e-12)
    np.testing.assert_allclose(r["ratio_observed"], 0.745, atol=1e-9)  # Coulomb: -e v_n
    e, mu = 0.745, 0.2
    lift = (1 + e) * mu * (np.array(v_t) - mu) / (1 + mu * mu)
    lift[0] = 0.0  # head on: no lift
    np.testing.assert_allclose(r["ratio_predicted"], 0.745 + lift, atol=1e-6)
    assert r["ratio_predicted"][3] == pytest.approx(1.349038, abs=1e-6)
    summary = impact_summary(r)
    assert summary["n_found"] == summary["n_predicted"] == 4
    assert summary["ratio_observed_mean"] == pytest.approx(0.745)
    assert summary["ratio_error_mean"] == pytest.approx(lift.mean(), abs=1e-6)
    png = plot_impacts(r, tmp_path / "impacts.png", "floor: CM")
    with Image.open(png) as im:
        assert im.format == "PNG" and im.width >= 600


def test_no_impact_no_flag():
    system, traj = _data([1.0, 2.0], v_n=1.0)  # moving away from the floor
    assert first_impacts(system, traj).trajectory.size == 0
    r = impact_ratios(system, CM(system), traj)
    assert r["ratio_observed"].size == 0 and impact_summary(r)["ratio_observed_mean"] is None
    # a smooth pendulum swing far from the ground has none either
    cp = dc.load_system("CP3", walls=[[0.0, 1.0, 10.0]])
    z0 = cp.sample_initial_conditions(4, seed=0)
    assert first_impacts(cp, cp.simulate(z0, 99, progress=False).numpy()).trajectory.size == 0


def _ratios(predicted):
    """Four observed impacts (ratios 0.5 ... 0.8) and the model's ``predicted`` ratios."""
    observed = np.array([0.5, 0.6, 0.7, 0.8])
    return {
        "trajectory": np.arange(4), "step": np.full(4, 3), "contact": np.zeros(4, dtype=int),
        "u_n_pre": -np.ones(4), "u_n_post": observed, "u_n_pred": np.asarray(predicted),
        "u_t_pre": np.array([0.0, 0.5, 1.0, 2.0]), "ratio_observed": observed,
        "ratio_predicted": np.asarray(predicted, dtype=float),
    }  # fmt: skip


@pytest.mark.parametrize("n_nan", [0, 3, 4])
def test_impact_counts_are_explicit_and_the_observed_mean_is_the_models_no_matter(
    tmp_path, monkeypatch, n_nan
):
    """With diverged predictions ``n`` counted the impacts with a finite prediction (all of
    them when none was), the observed mean dropped the impacts the model failed on, and
    impacts.png said "no impact found" for impacts found."""
    import diffcontact.learning.evaluation.plots as plots

    predicted = [np.nan] * n_nan + [0.9] * (4 - n_nan)
    s = impact_summary(_ratios(predicted))
    assert s["n_found"] == 4 and s["n_predicted"] == 4 - n_nan
    assert s["ratio_observed_mean"] == pytest.approx(0.65)  # all four, whatever the model
    if n_nan == 4:
        assert s["ratio_predicted_mean"] is None and s["ratio_error_mean"] is None
    else:
        assert s["ratio_predicted_mean"] == pytest.approx(0.9)
        ok = np.array([0.5, 0.6, 0.7, 0.8])[n_nan:]
        assert s["ratio_error_mean"] == pytest.approx(float(np.mean(0.9 - ok)))
    figures = []
    monkeypatch.setattr(plots, "_save", lambda fig, path, dpi=110: figures.append(fig) or path)
    plot_impacts(_ratios(predicted), tmp_path / "impacts.png", "t")
    left = figures[0].axes[0]
    said = " ".join([left.get_title(), *(t.get_text() for t in left.texts)])
    assert "no impact found" not in said and "4 first impacts" in said
    if n_nan:
        assert f"{4 - n_nan} with a finite prediction" in said
    if n_nan == 4:
        assert "4 impacts found; the model's step diverged" in said
    # the right panel shows every observed impact
    observed = figures[0].axes[1].collections[0]
    assert len(observed.get_offsets()) == 4
