"""Evaluation (diffcontact.learning.evaluate): metric functions, evaluate() end to end, CLI."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import diffcontact as dc
from diffcontact.learning.evaluate import (
    EvaluationInputError,
    energy_rel_drift,
    energy_scale,
    evaluate,
    find_training_log,
    mean_ci95,
    read_training_log,
    register_cli,
    relative_error,
    rollout_steps,
    t_quantile_975,
    true_parameters,
)

BOX = [[1, 0, 0], [0, 1, 0], [-1, 0, 1], [0, -1, 1]]
# two point masses in the unit box: heterogeneous restitution, 1 pair + 8 wall contacts
TINY = {
    "type": "bouncing_masses",
    "name": "BP2",
    "masses": [0.1, 0.3],
    "radii": [0.1, 0.15],
    "walls": BOX,
    "mu": 0.2,
    "cor": [0.9, 0.8, 0.8, 0.8, 0.8, 0.7, 0.7, 0.7, 0.7],
    "dt": 0.01,
    "horizon": 0.2,  # 20 states: shorter than the 100-state evaluation rollout
}


# ---------------------------------------------------------------------------
# metric functions on synthetic arrays
# ---------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------
# training log
# ---------------------------------------------------------------------------


def _write_log(run: Path, epochs: int = 12) -> Path:
    """A Lightning-style metrics.csv: step rows and epoch rows with empty cells."""
    folder = run / "logs" / "lightning_logs" / "version_0"
    folder.mkdir(parents=True)
    rows = ["epoch,step,train_loss_step,train_loss_epoch,val_loss,mass_ratio_0,mass_ratio_1,mu,cor"]
    for e in range(epochs):
        a = math.exp(-e / 3)
        rows.append(f"{e},{3 * e},{1.2 * a},,,,,,")
        rows.append(f"{e},{3 * e + 2},,{a},,1.0,{3 - 2 * a},{0.2 + 0.3 * a},{0.8 - 0.3 * a}")
        rows.append(f"{e},{3 * e + 2},,,{1.1 * a},,,,")
    path = folder / "metrics.csv"
    path.write_text("\n".join(rows) + "\n")
    return path


def test_read_training_log_groups_rows_by_epoch(tmp_path):
    path = _write_log(tmp_path, epochs=5)
    assert find_training_log(tmp_path) == path
    log = read_training_log(path)
    np.testing.assert_array_equal(log["epoch"], np.arange(5.0))
    assert set(log) >= {"train_loss_epoch", "val_loss", "mass_ratio_1", "mu", "cor"}
    assert "step" not in log
    np.testing.assert_allclose(log["val_loss"], 1.1 * np.exp(-np.arange(5) / 3))
    assert find_training_log(tmp_path / "nothing") is None


# ---------------------------------------------------------------------------
# evaluate() end to end with an injected model
# ---------------------------------------------------------------------------


class SystemModel:
    """The model contract, backed by a ground-truth System (optionally with other masses)."""

    def __init__(self, config, **overrides):
        self.system = dc.load_system(config, **overrides)
        self.config = self.system.config
        self.model_name = "truth" if not overrides else "perturbed"

    def simulate(self, z0, steps):
        return self.system.simulate(z0, steps)

    def learned_parameters(self):
        m, K = self.system.mass, self.system.n_contacts
        return {
            "mass_ratios": (m / m[0]).tolist(),  # includes the first body, like LearnedModel
            "mu": self.system.mu.expand(K).tolist(),
            "cor": self.system.cor.expand(K).tolist(),
            "eps": None,
        }


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A dataset folder with metadata.json and test.npz (3 trajectories of 20 states)."""
    folder = tmp_path_factory.mktemp("data")
    system = dc.load_system(TINY)
    traj = system.simulate(system.sample_initial_conditions(3, seed=1))
    np.savez(folder / "test.npz", traj=traj.numpy())
    meta = {"config": system.config.model_dump(mode="json"), "task": "BP2", "dt": system.dt}
    (folder / "metadata.json").write_text(json.dumps(meta))
    return folder


def _run_dir(root: Path, data: Path, log: bool = True) -> Path:
    run = root / "run"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"data_dir": str(data), "model": "CM-CD-CLNN"}))
    if log:
        _write_log(run)
    return run


def test_evaluate_truth_as_model(tmp_path, dataset):
    run = _run_dir(tmp_path, dataset)
    metrics = evaluate(run, model=SystemModel(TINY), steps=30, n_gif=2, gif_frames=12)
    out = run / "evaluation"
    on_disk = json.loads((out / "metrics.json").read_text())
    assert on_disk == metrics
    for key in (
        "rel_err_mean", "rel_err_ci95", "mass_ratios", "mu", "cor", "energy_rel_drift",
        "n_test", "steps", "model", "task",
    ):  # fmt: skip
        assert key in metrics, key
    assert metrics["n_test"] == 3 and metrics["steps"] == 30
    assert metrics["task"] == "BP2" and metrics["model"] == "truth"
    # the test trajectories hold 20 states: the 31-state ground truth was simulated
    assert metrics["ground_truth"].startswith("simulated")
    assert metrics["rel_err_mean"] == pytest.approx(0.0, abs=1e-12)
    assert metrics["rel_err_ci95"] == pytest.approx(0.0, abs=1e-12)
    assert metrics["n_nonfinite"] == 0
    drift = metrics["energy_rel_drift"]
    assert drift["pred"] == pytest.approx(drift["true"], abs=1e-12)
    assert metrics["mass_ratios"]["learned"] == pytest.approx([3.0])
    assert metrics["mass_ratios"]["true"] == pytest.approx([3.0])
    for key in ("mu", "cor"):
        assert metrics[key]["learned"] == pytest.approx(metrics[key]["true"])
        assert metrics[key]["max_abs_error"] == pytest.approx(0.0)
    assert metrics["cor"]["true"] == pytest.approx(TINY["cor"])
    assert sorted(metrics["files"]) == sorted(
        [
            "metrics.json",
            "rollout.npz",
            "rel_error.png",
            "energy.png",
            "training.png",
            "rollout.gif",
        ]
    )
    for name in ("rel_error.png", "energy.png", "training.png"):
        with Image.open(out / name) as im:
            assert im.format == "PNG" and im.width >= 400 and im.height >= 200
        assert (out / name).stat().st_size > 10_000
    with Image.open(out / "rollout.gif") as gif:
        assert gif.format == "GIF" and gif.n_frames > 5
    with np.load(out / "rollout.npz") as f:
        assert f["pred"].shape == f["true"].shape == (3, 31, 2, 2, 2)
        np.testing.assert_array_equal(f["pred"], f["true"])


def test_evaluate_detects_a_wrong_model(tmp_path, dataset):
    run = _run_dir(tmp_path, dataset, log=False)
    wrong = SystemModel(TINY, masses=[0.1, 0.15], gravity=9.81)
    out = tmp_path / "eval"
    metrics = evaluate(run, out, model=wrong, steps=19, n_gif=0)
    assert metrics["ground_truth"] == "test set"  # 20 stored states suffice
    assert metrics["rel_err_mean"] > 1e-3
    assert metrics["rel_err_ci95"] > 0
    assert metrics["mass_ratios"]["learned"] == pytest.approx([1.5])
    assert metrics["mass_ratios"]["max_rel_error"] == pytest.approx(0.5)
    assert "training.png" not in metrics["files"] and "rollout.gif" not in metrics["files"]
    assert (out / "rel_error.png").is_file()


def test_evaluate_without_run_dir(tmp_path, dataset):
    metrics = evaluate(
        None, tmp_path / "out", model=SystemModel(TINY), data_dir=dataset, steps=5, n_gif=0
    )
    assert metrics["run_dir"] is None and metrics["rel_err_mean"] == 0.0
    with pytest.raises(EvaluationInputError, match="out_dir"):
        evaluate(None, model=SystemModel(TINY), data_dir=dataset, steps=5, n_gif=0)


def test_evaluate_bad_input(tmp_path, dataset):
    with pytest.raises(EvaluationInputError, match="does not exist"):
        evaluate(tmp_path / "missing")
    run = tmp_path / "run"
    run.mkdir()
    with pytest.raises(EvaluationInputError, match=r"no run\.json"):
        evaluate(run)
    (run / "run.json").write_text(json.dumps({"data_dir": str(dataset)}))
    with pytest.raises(EvaluationInputError, match="no trained model"):
        evaluate(run)
    (run / "run.json").write_text(json.dumps({"data_dir": str(tmp_path / "nodata")}))
    with pytest.raises(EvaluationInputError, match="test data not found"):
        evaluate(run, model=SystemModel(TINY))
    other = _other_dataset(tmp_path, dataset)
    with pytest.raises(EvaluationInputError, match="states have shape"):
        evaluate(None, tmp_path / "o", model=SystemModel("BP5"), data_dir=other)
    with pytest.raises(EvaluationInputError, match="n_gif"):
        evaluate(run, model=SystemModel(TINY), data_dir=dataset, n_gif=-1)


def _other_dataset(tmp_path: Path, dataset: Path) -> Path:
    """TINY's test states with BP5's config: a shape mismatch."""
    folder = tmp_path / "other"
    folder.mkdir()
    (folder / "test.npz").write_bytes((dataset / "test.npz").read_bytes())
    cfg = dc.load_system("BP5").config.model_dump(mode="json")
    (folder / "metadata.json").write_text(json.dumps({"config": cfg}))
    return folder


# ---------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------


def _cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="diffcontact")
    sub = parser.add_subparsers(dest="command")
    register_cli(sub)
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, dataset, capsys):
    run = tmp_path / "run"
    assert _cli(["evaluate", str(run)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("diffcontact evaluate: error:") and "does not exist" in err
    assert err.count("\n") == 1
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"data_dir": str(dataset)}))
    assert _cli(["evaluate", str(run)]) == 2
    assert "no trained model" in capsys.readouterr().err
    (run / "model.pt").write_bytes(b"")
    assert _cli(["evaluate", str(run), "--data", str(tmp_path / "nodata")]) == 2
    err = capsys.readouterr().err
    assert "test data not found" in err and err.count("\n") == 1
    with pytest.raises(SystemExit) as exc:
        _cli(["evaluate", str(run), "--n-gif", "-1"])
    assert exc.value.code == 2


# ---------------------------------------------------------------------------
# through load_model (the real LearnedModel saved in a run directory)
# ---------------------------------------------------------------------------


def test_evaluate_through_load_model(tmp_path, dataset, capsys):
    model_mod = pytest.importorskip("diffcontact.learning.model")
    torch.manual_seed(0)
    model = model_mod.LearnedModel(TINY, model="CM-CD-CLNN", heterogeneous=True, hidden=(8,))
    truth = dc.load_system(TINY)
    model.set_parameters(mass=truth.mass, mu=truth.mu, cor=truth.cor)
    with torch.no_grad():  # a constant learned potential: the truth has no gravity
        for p in model.potential.layers[-1].parameters():
            p.zero_()
    run = _run_dir(tmp_path, dataset, log=False)
    model.save(run / "model.pt")
    assert _cli(["evaluate", str(run), "--steps", "19", "--n-gif", "1"]) == 0
    printed = capsys.readouterr().out
    assert "relative error" in printed and "m2/m1" in printed
    metrics = json.loads((run / "evaluation" / "metrics.json").read_text())
    assert metrics["model"] == "CM-CD-CLNN"
    # float32 parameters, float64 rollout: the truth up to float32 rounding
    assert metrics["rel_err_mean"] < 1e-4
    assert metrics["mass_ratios"]["learned"] == pytest.approx([3.0], rel=1e-6)
    assert metrics["cor"]["learned"] == pytest.approx(TINY["cor"], abs=1e-6)
    assert "rollout.gif" in metrics["files"]


def test_evaluate_a_trained_run(tmp_path):
    """data.dataset_from_arrays -> train.train (1 epoch) -> evaluate, on the real files."""
    data_mod = pytest.importorskip("diffcontact.learning.data")
    train_mod = pytest.importorskip("diffcontact.learning.train")
    system = dc.load_system(TINY)
    traj = system.simulate(system.sample_initial_conditions(6, seed=2))
    data = data_mod.dataset_from_arrays(
        traj, TINY, tmp_path / "data", val_fraction=0.2, test_fraction=0.2, progress=False
    )
    run = tmp_path / "run"
    train_mod.train(data, run, epochs=1, batch_size=8, hidden=(8,), progress=False)
    metrics = evaluate(run, steps=10, n_gif=0)
    assert metrics["model"] == "CM-CD-CLNN" and metrics["task"] == "BP2"
    assert metrics["steps"] == 10 and metrics["n_test"] >= 1
    assert math.isfinite(metrics["rel_err_mean"]) and metrics["rel_err_mean"] > 0
    assert len(metrics["mass_ratios"]["learned"]) == 1
    assert metrics["mass_ratios"]["true"] == pytest.approx([3.0])
    assert "training.png" in metrics["files"]  # from RUN/logs/metrics.csv
