"""Evaluation never invents a ground truth: recorded data is scored against its states only."""

from __future__ import annotations

import json

import numpy as np
import pytest

import diffcontact as dc
from diffcontact.learning.data.arrays import dataset_from_arrays
from diffcontact.learning.data.format import load_dataset
from diffcontact.learning.evaluation.evaluate import EvaluationInputError, evaluate
from diffcontact.learning.evaluation.log import read_training_log
from diffcontact.learning.evaluation.plots import _training_series

from .support import TINY, SystemModel, cli, run_dir


def _no_simulation(monkeypatch):
    """Make any simulation of the dataset's true system fail (the model's still runs)."""
    from diffcontact.learning.data.format import Dataset

    real = Dataset.system.func

    def system(self):
        sys = real(self)

        def refuse(*args, **kwargs):
            raise AssertionError("evaluate simulated a ground truth")

        sys.simulate = refuse
        return sys

    monkeypatch.setattr(Dataset, "system", property(system))


def test_recorded_data_without_declared_truth(tmp_path, recorded_dataset, monkeypatch):
    _no_simulation(monkeypatch)
    run = run_dir(tmp_path, recorded_dataset)
    model = SystemModel(TINY, masses=[0.1, 0.2])  # what was learned; the truth is unknown
    metrics = evaluate(run, model=model, n_gif=1, gif_frames=5)
    test = load_dataset(recorded_dataset).split("test").traj.numpy()
    T = test.shape[1]
    # the rollout follows the recorded data: T - 1 steps, not the protocol's 99
    assert metrics["steps"] == T - 1 == 19
    assert metrics["ground_truth"] == "recorded test set"
    assert "follows the recorded data: 20 states" in metrics["rollout_note"]
    with np.load(run / "evaluation" / "rollout.npz") as f:
        np.testing.assert_array_equal(f["true"], test)  # the recorded states, nothing else
        assert "energy_true" not in f.files
    assert metrics["rel_err_mean"] > 0
    # no invented truth: null values and a field explaining why
    assert metrics["parameters_known"] is False
    errors = {"mass_ratios": "max_rel_error", "mu": "max_abs_error", "cor": "max_abs_error"}
    for key, err in errors.items():
        assert metrics[key]["true"] is None and metrics[key][err] is None
        assert metrics[key]["learned"] is not None
    assert metrics["mass_ratios"]["learned"] == pytest.approx([2.0])
    assert metrics["energy_rel_drift"] == {"pred": None, "true": None, "n": None}
    assert metrics["energy_rel_error"] is None
    assert "placeholders" in metrics["unknown"]["parameters"]
    assert "true masses" in metrics["unknown"]["energy"]
    assert "energy.png" not in metrics["files"] and not (run / "evaluation" / "energy.png").exists()
    assert "training.png" in metrics["files"]
    # the training plot draws no true value
    log = read_training_log(next((run / "logs").rglob("metrics.csv")))
    panels = _training_series(log, None, 2)
    assert panels and all(ref is None for series in panels.values() for _, _, ref, _ in series)
    # more steps than recorded: refused, nothing simulated
    with pytest.raises(EvaluationInputError, match=r"hold 20 states, so at most 19 steps"):
        evaluate(run, model=model, steps=30, n_gif=0)


def test_recorded_data_with_declared_truth(tmp_path, monkeypatch):
    _no_simulation(monkeypatch)
    system = dc.load_system(TINY)
    traj = system.simulate(system.sample_initial_conditions(5, seed=1))
    data = dataset_from_arrays(
        traj, TINY, tmp_path / "data", val_fraction=0.2, test_fraction=0.6,
        true_parameters=True, progress=False,
    )  # fmt: skip
    assert load_dataset(data).parameters_known
    metrics = evaluate(None, tmp_path / "out", model=SystemModel(TINY), data_dir=data, n_gif=0)
    assert metrics["parameters_known"] is True and metrics["unknown"] == {}
    assert metrics["steps"] == 19 and metrics["ground_truth"] == "recorded test set"
    assert metrics["rel_err_mean"] == pytest.approx(0.0, abs=1e-12)
    assert metrics["mass_ratios"]["true"] == pytest.approx([3.0])
    assert metrics["mass_ratios"]["max_rel_error"] == pytest.approx(0.0, abs=1e-12)
    assert metrics["energy_rel_drift"]["pred"] == pytest.approx(metrics["energy_rel_drift"]["true"])
    assert "energy.png" in metrics["files"]


def test_generated_data_keeps_its_simulated_truth(tmp_path, dataset, monkeypatch):
    metrics = evaluate(None, tmp_path / "o", model=SystemModel(TINY), data_dir=dataset,
                       steps=30, n_gif=0)  # fmt: skip
    assert metrics["ground_truth"].startswith("simulated") and metrics["rollout_note"] is None
    assert metrics["parameters_known"] is True
    assert metrics["mass_ratios"]["true"] == pytest.approx([3.0])
    # (the guard of the tests above does catch a simulated ground truth)
    _no_simulation(monkeypatch)
    with pytest.raises(AssertionError, match="simulated a ground truth"):
        evaluate(None, tmp_path / "o", model=SystemModel(TINY), data_dir=dataset, steps=30,
                 n_gif=0)  # fmt: skip


def test_cli_says_unknown(tmp_path, recorded_dataset, capsys):
    model = dc.learning.LearnedModel(TINY, model="CM-CD-CLNN", hidden=(8,))
    run = run_dir(tmp_path, recorded_dataset)
    model.save(run / "model.pt")
    assert cli(["evaluate", str(run), "--n-gif", "0"]) == 0
    out = capsys.readouterr().out
    assert "ground truth: recorded test set" in out
    assert "note: the rollout follows the recorded data: 20 states" in out
    assert "energy drift     unknown" in out
    assert "m2/m1" in out and "unknown" in out.split("m2/m1")[1].splitlines()[0]
    metrics = json.loads((run / "evaluation" / "metrics.json").read_text())
    assert metrics["mass_ratios"]["true"] is None
    assert cli(["evaluate", str(run), "--n-gif", "0", "--steps", "50"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "at most 19 steps" in err[0]
