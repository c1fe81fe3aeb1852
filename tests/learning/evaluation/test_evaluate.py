"""evaluate() end to end: an injected model, load_model, a trained run; bad input."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import diffcontact as dc
from diffcontact.learning.data.arrays import dataset_from_arrays
from diffcontact.learning.data.format import metadata_checksum
from diffcontact.learning.evaluation.evaluate import EvaluationInputError, evaluate
from diffcontact.learning.models.physical import LearnedModel
from diffcontact.learning.training.run import train

from .support import TINY, FailingTruth, SystemModel, cli, run_dir


def test_evaluate_truth_as_model(tmp_path, dataset):
    run = run_dir(tmp_path, dataset)
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
            "impacts.png",
        ]
    )
    # the truth's step from an observed pre-impact state is the observed post-impact state
    impacts = metrics["impacts"]
    assert impacts["n_found"] >= 1 and impacts["n_predicted"] == impacts["n_found"]
    assert impacts["ratio_error_abs_mean"] == pytest.approx(0, abs=1e-9)
    for name in ("rel_error.png", "energy.png", "training.png", "impacts.png"):
        with Image.open(out / name) as im:
            assert im.format == "PNG" and im.width >= 400 and im.height >= 200
        assert (out / name).stat().st_size > 10_000
    with Image.open(out / "rollout.gif") as gif:
        assert gif.format == "GIF" and gif.n_frames > 5
    with np.load(out / "rollout.npz") as f:
        assert f["pred"].shape == f["true"].shape == (3, 31, 2, 2, 2)
        np.testing.assert_array_equal(f["pred"], f["true"])


def test_evaluate_detects_a_wrong_model(tmp_path, dataset):
    run = run_dir(tmp_path, dataset, log=False)
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


def test_a_model_object_that_breaks_the_contract_is_named(tmp_path, dataset):
    """A model without simulate, one returning the wrong shape, or learned_parameters()
    returning None or strings gave AttributeError or numpy's broadcast error."""

    class NoSimulate:
        def learned_parameters(self):
            return {}

    class Short(SystemModel):
        def simulate(self, z0, steps):
            return super().simulate(z0, steps)[:, :-1]

    class Unlearned(SystemModel):
        def learned_parameters(self):
            return None

    class Words(SystemModel):
        def learned_parameters(self):
            return {"mu": "x"}

    out = tmp_path / "out"
    with pytest.raises(EvaluationInputError, match="model must have a method simulate"):
        evaluate(None, out, model=NoSimulate(), data_dir=dataset, steps=5, n_gif=0)
    assert not out.exists()  # refused before any file
    with pytest.raises(EvaluationInputError, match=r"model\.simulate returned shape \(\d+, 5,"):
        evaluate(None, out, model=Short(TINY), data_dir=dataset, steps=5, n_gif=0)
    with pytest.raises(EvaluationInputError, match=r"must return a dict .* got NoneType"):
        evaluate(None, out, model=Unlearned(TINY), data_dir=dataset, steps=5, n_gif=0)
    with pytest.raises(EvaluationInputError, match=r"\['mu'\] must hold numbers"):
        evaluate(None, out, model=Words(TINY), data_dir=dataset, steps=5, n_gif=0)


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


def test_evaluate_through_load_model(tmp_path, dataset, capsys):
    torch.manual_seed(0)
    model = LearnedModel(TINY, model="CM-CD-CLNN", heterogeneous=True, hidden=(8,))
    truth = dc.load_system(TINY)
    model.set_parameters(mass=truth.mass, mu=truth.mu, cor=truth.cor)
    with torch.no_grad():  # a constant learned potential: the truth has no gravity
        for p in model.potential.layers[-1].parameters():
            p.zero_()
    run = run_dir(tmp_path, dataset, log=False)
    model.save(run / "model.pt")
    assert cli(["evaluate", str(run), "--steps", "19", "--n-gif", "1"]) == 0
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
    """dataset_from_arrays (true parameters declared) -> train (1 epoch) -> evaluate."""
    system = dc.load_system(TINY)
    traj = system.simulate(system.sample_initial_conditions(6, seed=2))
    data = dataset_from_arrays(
        traj, TINY, tmp_path / "data", val_fraction=0.2, test_fraction=0.2, progress=False,
        true_parameters=True,  # the config's parameters are those that made the data
    )  # fmt: skip
    run = tmp_path / "run"
    train(data, run, epochs=1, batch_size=8, hidden=(8,), progress=False)
    metrics = evaluate(run, steps=10, n_gif=0)
    assert metrics["model"] == "CM-CD-CLNN" and metrics["task"] == "BP2"
    assert metrics["steps"] == 10 and metrics["n_test"] >= 1
    assert math.isfinite(metrics["rel_err_mean"]) and metrics["rel_err_mean"] > 0
    assert len(metrics["mass_ratios"]["learned"]) == 1
    assert metrics["mass_ratios"]["true"] == pytest.approx([3.0])
    assert "training.png" in metrics["files"]  # from RUN/logs/metrics.csv
    assert metrics["log_note"] is None
    # random bytes in the log made the whole evaluation fail (a UnicodeDecodeError naming
    # no file): now only its plot is left out, and said so
    log = next((run / "logs").rglob("metrics.csv"))
    log.write_bytes(bytes(range(128, 256)) * 4)
    again = evaluate(run, tmp_path / "again", steps=10, n_gif=0)
    assert "training.png not drawn" in again["log_note"] and str(log) in again["log_note"]
    assert "training.png" not in again["files"] and "rollout.npz" in again["files"]


def _other_dataset(tmp_path: Path, dataset: Path) -> Path:
    """TINY's dataset with BP5's config in its metadata: a shape mismatch."""
    folder = tmp_path / "other"
    shutil.copytree(dataset, folder)
    meta = json.loads((folder / "metadata.json").read_text())
    meta["config"] = dc.load_system("BP5").config.model_dump(mode="json")
    meta["metadata_sha256"] = metadata_checksum(meta)  # a consistent, if wrong, dataset
    (folder / "metadata.json").write_text(json.dumps(meta))
    return folder


def test_evaluate_reads_the_test_data_through_the_dataset_reader(tmp_path, dataset):
    """A corrupted test split is refused (checksums), like training's data."""
    folder = tmp_path / "corrupt"
    shutil.copytree(dataset, folder)
    raw = bytearray((folder / "test.npz").read_bytes())
    raw[-100] ^= 0xFF
    (folder / "test.npz").write_bytes(bytes(raw))
    with pytest.raises(EvaluationInputError, match=r"test\.npz does not match its sha256"):
        evaluate(None, tmp_path / "out", model=SystemModel(TINY), data_dir=folder, n_gif=0)


def test_a_failed_contact_solve_counts_as_a_diverged_rollout(tmp_path, dataset):
    """A learned model whose contact solve fails on one test trajectory: that trajectory
    is left out (NaN, ``n_nonfinite``, ``solver_failures``); the others are evaluated."""
    from diffcontact.contact import ConeQPError

    bad = 1  # the second test trajectory

    def failed_solve(states):
        err = ConeQPError("solve failed", None)
        err.states = states
        return err

    said = r"1 of 3 test rollouts diverged \(non-finite\) \(1 on a failed contact solve\)"
    with pytest.warns(RuntimeWarning, match=said):
        m = evaluate(
            None,
            tmp_path / "out",
            model=FailingTruth([bad], failed_solve),
            data_dir=dataset,
            n_gif=0,
            steps=5,
        )
    assert m["solver_failures"] == [bad]
    assert m["n_nonfinite"] == 1
    assert m["rel_err_mean"] == pytest.approx(0.0, abs=1e-9)  # the truth's own rollouts


@pytest.mark.parametrize("diverged", [[0, 2], [0, 1, 2]])
def test_a_diverged_rollout_is_left_out_and_counted(tmp_path, dataset, diverged):
    """Rollouts that reach NaN (NonFiniteRolloutError naming them) are counted in
    n_nonfinite, as documented; the evaluation stopped with the error before."""
    from diffcontact.learning.evaluation.evaluate import DivergedRolloutsWarning
    from diffcontact.systems import NonFiniteRolloutError

    def diverging(states):
        return NonFiniteRolloutError("diverged", states)

    said = rf"{len(diverged)} of 3 test rollouts diverged \(non-finite\): left out of the means"
    with pytest.warns(DivergedRolloutsWarning, match=said) as caught:
        m = evaluate(
            None,
            tmp_path / "out",
            model=FailingTruth(diverged, diverging),
            data_dir=dataset,
            n_gif=0,
            steps=5,
        )
    assert m["n_nonfinite"] == len(diverged) and m["solver_failures"] == []
    if len(diverged) < 3:
        assert m["rel_err_mean"] == pytest.approx(0.0, abs=1e-9)
    # one warning, pointing at the caller's line (not inside evaluate)
    said_here = [w for w in caught if "rollouts diverged" in str(w.message)]
    assert len(said_here) == 1 and said_here[0].filename == __file__


def test_no_diverged_warning_when_every_rollout_is_finite(tmp_path, dataset):
    """A Python caller heard nothing about diverged rollouts (only n_nonfinite and the
    command's line said so); with none diverged nothing is said."""
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        m = evaluate(None, tmp_path / "out", model=SystemModel(TINY), data_dir=dataset,
                     n_gif=0, steps=5, uncertainty=False)  # fmt: skip
    assert m["n_nonfinite"] == 0
    assert not [w for w in caught if "rollouts diverged" in str(w.message)]


def test_an_evaluation_stopped_midway_can_run_again_in_its_folder(tmp_path, dataset, monkeypatch):
    """Killed after its first files (no metrics.json yet), an evaluation was refused in
    its own folder as "another evaluation" until --force."""
    import diffcontact.learning.evaluation.evaluate as ev
    from diffcontact.systems import System, load_config

    system = System(load_config(TINY))
    out = tmp_path / "out"

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(ev, "plot_rel_error", killed)
        with pytest.raises(KeyboardInterrupt):
            ev.evaluate(None, out, model=system, data_dir=dataset, n_gif=0, steps=5)
    assert (out / "rollout.npz").is_file() and not (out / "metrics.json").exists()
    metrics = ev.evaluate(None, out, model=system, data_dir=dataset, n_gif=0, steps=5)
    assert (out / "metrics.json").is_file() and not (out / ev.STARTED).exists()
    assert metrics["n_test"] == 3
    # stopped again after rewriting rollout.npz: the earlier metrics.json, which described
    # the files before, is gone (it stayed beside the new rollout.npz)
    with monkeypatch.context() as m:
        m.setattr(ev, "plot_rel_error", killed)
        with pytest.raises(KeyboardInterrupt):
            ev.evaluate(None, out, model=system, data_dir=dataset, n_gif=0, steps=5)
    assert (out / ev.STARTED).is_file() and not (out / "metrics.json").exists()
    assert ev.evaluate(None, out, model=system, data_dir=dataset, n_gif=0, steps=5) == metrics
    # another data set in that folder is still refused (a copy of this one is this one)
    other = _resigned_copy(dataset, tmp_path / "other")
    with pytest.raises(ev.EvaluationInputError, match="of another evaluation"):
        ev.evaluate(None, out, model=system, data_dir=other, n_gif=0, steps=5)


def _resigned_copy(dataset: Path, folder: Path) -> Path:
    """A copy of ``dataset`` that is another data set: its metadata (seed) changed and
    signed again, so that its checksum differs."""
    shutil.copytree(dataset, folder)
    meta = json.loads((folder / "metadata.json").read_text())
    meta["seed"] = meta["seed"] + 1
    meta["metadata_sha256"] = metadata_checksum(meta)
    (folder / "metadata.json").write_text(json.dumps(meta))
    return folder


def test_the_error_plot_says_when_no_rollout_is_finite(tmp_path):
    """With every rollout diverged the plot had drawn the NaN errors' first steps as a
    perfect model on a 1e-16 floor."""
    import numpy as np
    from PIL import Image

    from diffcontact.learning.evaluation.plots import plot_rel_error

    out = plot_rel_error(np.zeros((0, 50)), 0.01, tmp_path / "r.png", "t", n_left_out=4)
    with Image.open(out) as im:
        assert im.format == "PNG"


@pytest.mark.parametrize("first", [True, False], ids=["first state", "before the impact"])
def test_recorded_states_that_penetrate_are_evaluated(tmp_path, first):
    """A recording with soft contacts (MuJoCo's) holds states slightly inside a wall:
    ``generate --from-arrays`` and ``train`` accepted them, and ``evaluate`` then stopped
    on the overlap check of ``simulate`` (for a test trajectory's first state, and for the
    state before its first impact), the docs' own MuJoCo example included."""
    from diffcontact.learning import create_model

    cfg = {"name": "ball", "type": "bouncing_masses", "masses": [1.0], "radii": [0.1],
           "walls": [[0.0, 1.0, 0.0]], "gravity": 0.0, "mu": 0.1, "cor": 0.8, "dt": 0.01,
           "horizon": 0.3}  # fmt: skip
    T = 30
    traj = np.zeros((6, T, 2, 1, 2))
    traj[..., 0, 0, 0] = 0.5
    if first:  # moving away from the wall from 1 mm inside it
        traj[..., 0, 0, 1] = 0.099 + 0.01 * np.arange(T)
        traj[..., 1, 0, 1] = 1.0
    else:  # approaching, 1 mm inside at step 10, bouncing off
        t = np.arange(T)
        traj[..., 0, 0, 1] = np.where(t <= 10, 0.199 - 0.01 * t, 0.099 + 0.008 * (t - 10))
        traj[..., 1, 0, 1] = np.where(t <= 10, -1.0, 0.8)
    data = dataset_from_arrays(traj, cfg, tmp_path / "data", val_fraction=0.2, test_fraction=0.2)
    metrics = evaluate(None, tmp_path / "ev", model=create_model("CM-CD-CLNN", cfg),
                       data_dir=data, n_gif=0)  # fmt: skip
    assert metrics["n_nonfinite"] == 0 and np.isfinite(metrics["rel_err_mean"])


@pytest.mark.parametrize("cut", ["truncated header", "no plottable column"])
def test_a_log_with_nothing_to_draw_is_said(tmp_path, dataset, cut):
    """A truncated logs/metrics.csv (``head -c 100``) dropped training.png without a word
    (log_note null), while an unreadable one was said."""
    run = run_dir(tmp_path, dataset)
    log = next((run / "logs").rglob("metrics.csv"))
    if cut == "truncated header":
        log.write_bytes(log.read_bytes()[:50])  # part of the header, no row
        what = "holds no row"
    else:
        log.write_text("epoch,step\n0,0\n1,5\n")
        what = "holds no loss or learned parameter per epoch"
    m = evaluate(run, model=SystemModel(TINY), steps=5, n_gif=0, uncertainty=False)
    assert "training.png" not in m["files"]
    assert m["log_note"] == f"training.png not drawn: {log} {what} (truncated or empty?)"
