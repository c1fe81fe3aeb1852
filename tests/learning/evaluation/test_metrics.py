"""Metric functions on synthetic arrays: relative error, confidence intervals, energy drift."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import diffcontact as dc
from diffcontact.learning.evaluation.metrics import (
    energy_rel_drift,
    energy_scale,
    mean_ci95,
    relative_error,
    rollout_steps,
    t_quantile_975,
    true_parameters,
)

from .support import TINY


def _random_traj(N=4, T=6, P=3, d=2, seed=0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(N, T, 2, P, d))


def test_relative_error_is_zero_for_identical_trajectories():
    z = _random_traj()
    err = relative_error(z, z.copy())
    assert err.shape == (4, 6)
    assert np.all(err == 0.0)
    # torch input too
    assert np.all(relative_error(torch.as_tensor(z), torch.as_tensor(z)) == 0.0)


def test_relative_error_known_constant():
    z = _random_traj(seed=1)
    np.testing.assert_allclose(relative_error(1.03 * z, z), 0.03, rtol=1e-12)
    np.testing.assert_allclose(relative_error(0.5 * z, z), 0.5, rtol=1e-12)
    # one coordinate of a unit state: ||(1, 0) + (0, 3)|| vs ||(1, 0)|| -> 3
    true = np.zeros((1, 1, 2, 1, 2))
    true[..., 0, 0, 0] = 1.0
    pred = true.copy()
    pred[..., 1, 0, 1] = 3.0
    np.testing.assert_allclose(relative_error(pred, true), [[3.0]])


def test_relative_error_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="same shape"):
        relative_error(np.zeros((2, 3, 2, 1, 2)), np.zeros((2, 4, 2, 1, 2)))


def test_mean_ci95_known_values():
    mean, half = mean_ci95([1.0, 2.0, 3.0])
    assert mean == pytest.approx(2.0)
    assert half == pytest.approx(4.302653 * 1.0 / math.sqrt(3), rel=1e-6)
    # constant samples: zero width
    assert mean_ci95(np.full(10, 0.25)) == (pytest.approx(0.25), pytest.approx(0.0))
    # one sample: undefined width
    m1, h1 = mean_ci95([0.7])
    assert m1 == pytest.approx(0.7) and math.isnan(h1)


def test_mean_ci95_shrinks_with_more_samples_and_works_per_step():
    rng = np.random.default_rng(0)
    widths = [mean_ci95(rng.normal(1.0, 0.3, n))[1] for n in (10, 100, 1000)]
    assert widths[0] > widths[1] > widths[2] > 0
    x = rng.normal(size=(50, 7))
    mean, half = mean_ci95(x, axis=0)
    assert mean.shape == half.shape == (7,)
    np.testing.assert_allclose(mean, x.mean(0))
    np.testing.assert_allclose(half, t_quantile_975(49) * x.std(0, ddof=1) / math.sqrt(50))


def test_t_quantile_matches_scipy():
    stats = pytest.importorskip("scipy.stats")
    for df in (1, 2, 5, 29, 30, 31, 99, 500):
        assert t_quantile_975(df) == pytest.approx(stats.t.ppf(0.975, df), rel=1e-6)


def _free_flight():
    """One point mass in a large box, far from the walls: no contact for 10 steps."""
    system = dc.load_system(
        {
            "type": "bouncing_masses",
            "masses": [0.5],
            "radii": [0.1],
            "walls": [[1, 0, 5], [0, 1, 5], [-1, 0, 5], [0, -1, 5]],
            "dt": 0.01,
            "horizon": 0.1,
        }
    )
    z0 = torch.tensor([[[[0.0, 0.0]], [[0.8, -0.6]]]], dtype=torch.float64).repeat(3, 1, 1, 1)
    z0[:, 1] *= torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)[:, None, None]
    return system, system.simulate(z0, steps=9)


def test_energy_drift_zero_for_the_true_system_and_known_for_scaled_velocities():
    system, true = _free_flight()
    drift = energy_rel_drift(system, true, true)
    assert drift["true"] == pytest.approx(0.0, abs=1e-12)
    assert drift["pred"] == drift["true"]
    # velocities times sqrt(2): kinetic (= total, no gravity) energy doubles -> drift exactly 1
    pred = true.clone()
    pred[:, :, 1] *= math.sqrt(2.0)
    drift = energy_rel_drift(system, pred, true)
    assert drift["pred"] == pytest.approx(1.0, rel=1e-12)
    assert drift["true"] == pytest.approx(0.0, abs=1e-12)


def test_energy_drift_does_not_depend_on_the_potentials_zero():
    """The unit is the mean kinetic energy, not |E(0)| (which a datum shift changes)."""
    system, true = _free_flight()
    pred = true.clone()
    pred[:, :, 1] *= 1.1
    base = energy_rel_drift(system, pred, true)

    class Shifted:  # the same system with its potential's zero moved by 100 J
        def energy(self, z):
            return system.energy(z) + 100.0

        def kinetic_energy(self, z):
            return system.kinetic_energy(z)

    shifted = energy_rel_drift(Shifted(), pred, true)
    assert shifted["pred"] == pytest.approx(base["pred"], rel=1e-9)
    assert base["pred"] == pytest.approx(0.21, rel=1e-9)  # no potential: (1.1^2 - 1) T / mean T
    T = system.kinetic_energy(true).mean()
    assert energy_scale(system, true) == pytest.approx(float(T), rel=1e-12)


def test_true_parameters_follow_the_papers_tables():
    p = true_parameters("BP5")
    np.testing.assert_allclose(p["mass_ratios"], [2.0, 6.0, 8.0, 10.0])  # Table S.2
    assert len(p["mu"]) == len(p["cor"]) == 10 + 5 * 4
    assert p["mu"][:3] == pytest.approx([0.5, 0.4, 0.6])  # pairs (0,1), (0,2), (0,3)
    assert p["cor"][9] == pytest.approx(1.0) and p["cor"][10:] == pytest.approx([0.8] * 20)
    # the energy-conserving pendulum is the one with ratios 0.65, 0.75 (paper-facts.md)
    np.testing.assert_allclose(true_parameters("CP3-e")["mass_ratios"], [0.65, 0.75])
    assert true_parameters("Gyro")["mass_ratios"] == []


def test_rollout_steps_is_max_of_horizon_and_100_dt():
    assert rollout_steps(dc.load_system("BP5")) == 99  # horizon 1 s = 100 dt
    assert rollout_steps(dc.load_system("Rope")) == 99  # horizon 20 dt < 100 dt
    assert rollout_steps(dc.load_system(TINY, horizon=2.0)) == 199


def test_energy_drift_of_model_and_truth_over_the_same_trajectories():
    """A diverged prediction left its trajectory out of the model's mean only: the truth's
    was over all trajectories, the two compared over different sets."""
    system, true = _free_flight()
    pred = true.clone()
    pred[:, :, 1] *= math.sqrt(2.0)  # drift exactly 1 where finite
    pred[0, 5:] = float("nan")  # the first rollout diverges
    lossy = true.clone()
    lossy[:, :, 1] *= torch.linspace(1.0, 0.5, true.shape[1], dtype=torch.float64)[:, None, None]
    lossy[1:, :, 1] = true[1:, :, 1]  # only the first true trajectory loses energy
    drift = energy_rel_drift(system, pred, lossy)
    assert drift["n"] == 2
    assert drift["true"] == pytest.approx(0.0, abs=1e-12)  # the lossy one is left out
