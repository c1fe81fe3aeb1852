"""``diffcontact evaluate``: bad input gives one line on stderr and exit status 2."""

from __future__ import annotations

import json
import os
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from diffcontact.cli import main
from diffcontact.learning.models.physical import LearnedModel

from .support import TINY, FailingTruth, cli, run_dir


def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, dataset, capsys):
    run = tmp_path / "run"
    assert cli(["evaluate", str(run)]) == 2
    out, err = capsys.readouterr()
    assert err.startswith("diffcontact evaluate: error:") and "does not exist" in err
    assert err.count("\n") == 1 and out == ""  # (the uncertainty banner came first)
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"data_dir": str(dataset)}))
    assert cli(["evaluate", str(run)]) == 2
    assert "no trained model" in capsys.readouterr().err
    (run / "model.pt").write_bytes(b"")
    assert cli(["evaluate", str(run), "--data", str(tmp_path / "nodata")]) == 2
    err = capsys.readouterr().err
    assert "test data not found" in err and "--data" in err and err.count("\n") == 1
    with pytest.raises(SystemExit) as exc:
        cli(["evaluate", str(run), "--n-gif", "-1"])
    assert exc.value.code == 2


def _run_with_model(root, dataset):
    root.mkdir()
    run = run_dir(root, dataset, log=False)
    LearnedModel(TINY, hidden=(4,)).save(run / "model.pt")
    return run


def _error_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("diffcontact evaluate: error:"), err
    return lines[0]


def test_another_evaluation_is_not_replaced_without_force(tmp_path, dataset, capsys):
    run_a = _run_with_model(tmp_path / "a", dataset)
    run_b = _run_with_model(tmp_path / "b", dataset)
    out = tmp_path / "evaluation"
    argv = ["--steps", "5", "--n-gif", "0", "--out", str(out)]
    assert cli(["evaluate", str(run_a), *argv]) == 0
    assert cli(["evaluate", str(run_a), *argv]) == 0  # the same evaluation again
    capsys.readouterr()
    assert cli(["evaluate", str(run_b), *argv]) == 2
    line = _error_line(capsys)
    assert "already holds" in line and "metrics.json" in line and "--force" in line
    assert json.loads((out / "metrics.json").read_text())["run_dir"] == str(run_a)
    assert cli(["evaluate", str(run_b), *argv, "--force"]) == 0
    assert json.loads((out / "metrics.json").read_text())["run_dir"] == str(run_b)


def test_a_changed_test_set_is_refused(tmp_path, dataset, capsys):
    run = _run_with_model(tmp_path / "r", dataset)
    data = shutil.copytree(dataset, tmp_path / "data")
    argv = ["evaluate", str(run), "--data", str(data), "--steps", "5", "--n-gif", "0"]
    meta = json.loads((data / "metadata.json").read_text())
    meta["config"]["dt"] = meta["dt"] = 0.02  # an edited time step
    (data / "metadata.json").write_text(json.dumps(meta))
    assert cli(argv) == 2
    line = _error_line(capsys)
    assert "metadata.json does not match its checksum" in line
    shutil.copy(dataset / "metadata.json", data / "metadata.json")
    raw = (data / "test.npz").read_bytes()
    (data / "test.npz").write_bytes(raw[: len(raw) // 2])  # a truncated test set
    assert cli(argv) == 2
    assert "test.npz does not match its sha256" in _error_line(capsys)
    assert not (run / "evaluation").exists()


def test_data_of_another_system_is_refused_up_front(tmp_path, dataset, capsys):
    """A model of three balls evaluated on two balls' data: one line, exit 2 (a raw
    ValueError from the rollout, exit 1, before)."""
    root = tmp_path / "r"
    root.mkdir()
    run = run_dir(root, dataset, log=False)
    LearnedModel({**TINY, "masses": [0.1, 0.2, 0.3], "radii": [0.1] * 3, "cor": 0.8},
                 hidden=(4,)).save(run / "model.pt")  # fmt: skip
    assert cli(["evaluate", str(run), "--n-gif", "0", "--out", str(tmp_path / "ev")]) == 2
    line = _error_line(capsys)
    assert (
        "(2, 2, 2) (BP2), the model's (2, 3, 2) (CM-CD-CLNN)" in line and "another system" in line
    )
    assert not (tmp_path / "ev").exists()  # (it held .evaluation-started.json)
    # a model file given for its run directory: said so (it said the directory did not exist)
    assert cli(["evaluate", str(run / "model.pt"), "--n-gif", "0"]) == 2
    assert "model.pt is a file: give the run directory that holds it" in _error_line(capsys)


@pytest.mark.parametrize(
    ("change", "said"),
    [
        ({"dt": 0.02, "horizon": 0.4}, "steps at dt = 0.02 s, the data are sampled every 0.01 s"),
        ({"radii": [0.12, 0.15]}, "the contact geometry differs (walls, radii or limits)"),
    ],
)  # fmt: skip
def test_a_model_of_another_step_or_geometry_is_refused(tmp_path, dataset, capsys, change, said):
    """Evaluate and refit compared a model with data of another dt or other walls/radii
    without a word (a relative error of 0.88, and a refit to the wrong data)."""
    root = tmp_path / "r"
    root.mkdir()
    run = run_dir(root, dataset, log=False)
    LearnedModel({**TINY, **change}, hidden=(4,)).save(run / "model.pt")
    assert cli(["evaluate", str(run), "--n-gif", "0", "--out", str(tmp_path / "ev")]) == 2
    line = _error_line(capsys)
    assert said in line and "another system" in line
    assert main(["refit", str(run), "--iterations", "1"]) == 2
    assert said in capsys.readouterr().err
    assert not (run / "model_adam.pt").exists()
    # the learned parameters may differ: other masses, friction and restitution are scored
    LearnedModel({**TINY, "masses": [0.2, 0.2], "mu": 0.4, "cor": 0.5}, hidden=(4,)).save(
        run / "model.pt"
    )
    assert cli(["evaluate", str(run), "--n-gif", "0", "--out", str(tmp_path / "ev2")]) == 0


def test_a_run_without_model_pt_is_scored_with_a_warning(tmp_path, dataset, capsys):
    """An interrupted run is evaluated from its last checkpoint: said on screen and in
    metrics.json (it looked like a final model)."""
    from diffcontact.learning.training.run import train

    run = tmp_path / "run"
    train(dataset, run, epochs=1, batch_size=1, hidden=(4,), progress=False)
    (run / "model.pt").unlink()  # as a run killed before its end leaves it...
    info = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(json.dumps({**info, "epochs": 3}))  # ...after 1 of 3 epochs
    assert cli(["evaluate", str(run), "--n-gif", "0", "--no-uncertainty"]) == 0
    out = capsys.readouterr().out
    assert "WARNING: " in out and "has no model.pt (its training did not finish)" in out
    metrics = json.loads((run / "evaluation" / "metrics.json").read_text())
    assert "last checkpoint after 1 of 3 epochs, not a final model" in metrics["model_note"]


def test_a_finished_run_without_model_pt_is_said_to_miss_it(tmp_path, dataset, capsys):
    """model.pt deleted from a finished run: the warning said "its training did not finish"
    (after 1 of 1 epochs)."""
    from diffcontact.learning.training.run import train

    run = tmp_path / "run"
    train(dataset, run, epochs=1, batch_size=1, hidden=(4,), progress=False)
    (run / "model.pt").unlink()
    assert cli(["evaluate", str(run), "--n-gif", "0", "--no-uncertainty"]) == 0
    out = capsys.readouterr().out
    note = (
        f"{run} has no model.pt although its training finished: the file is missing (deleted "
        "or moved?); this is its last checkpoint after 1 of 1 epochs, the weights at the end "
        "of its training"
    )
    assert f"WARNING: {note}" in out and "did not finish" not in out
    assert json.loads((run / "evaluation" / "metrics.json").read_text())["model_note"] == note


def test_a_run_without_last_ckpt_is_scored_from_its_newest_epoch_checkpoint(
    tmp_path, dataset, capsys
):
    """No model.pt and no last.ckpt (deleted, or lost) but epochNNNN.ckpt files: evaluate
    failed ("holds neither model.pt nor checkpoints/last.ckpt")."""
    from diffcontact.learning.models.storage import load_model
    from diffcontact.learning.training.run import train

    run = tmp_path / "run"
    # (a constant rate: the cosine schedule's is 0 in the second and last step)
    train(dataset, run, epochs=2, batch_size=1, hidden=(4,), progress=False, schedule="constant")
    (run / "model.pt").unlink()
    (run / "checkpoints" / "last.ckpt").unlink()
    newest = run / "checkpoints" / "epoch0001.ckpt"
    ratios = [
        load_model(run / "checkpoints" / f"epoch000{e}.ckpt").learned_parameters()["mass_ratios"]
        for e in (0, 1)
    ]
    assert ratios[0] != ratios[1]
    assert cli(["evaluate", str(run), "--n-gif", "0", "--no-uncertainty"]) == 0
    out = capsys.readouterr().out
    note = (
        f"{run} has no model.pt although its training finished: the file is missing (deleted "
        "or moved?); this is its newest epoch checkpoint, checkpoints/epoch0001.ckpt after 2 "
        "of 2 epochs (no checkpoints/last.ckpt), the weights at the end of its training"
    )
    assert f"WARNING: {note}" in out
    metrics = json.loads((run / "evaluation" / "metrics.json").read_text())
    assert metrics["model_note"] == note
    assert metrics["mass_ratios"]["learned"] == pytest.approx(ratios[1][1:])  # epoch 2's model
    # an unreadable last.ckpt (a kill while it was written, with earlier versions) is skipped
    (run / "checkpoints" / "last.ckpt").write_bytes(b"")
    assert cli(["evaluate", str(run), "--n-gif", "0", "--no-uncertainty", "--force"]) == 0
    out = capsys.readouterr().out
    assert "its newest epoch checkpoint, checkpoints/epoch0001.ckpt after 2 of 2 epochs " in out
    assert "last.ckpt cannot be read (truncated or corrupted?): it is empty" in out
    # no readable checkpoint at all: one line naming what was skipped, exit status 2
    newest.write_bytes(b"")
    (run / "checkpoints" / "epoch0000.ckpt").write_bytes(b"")
    assert cli(["evaluate", str(run), "--n-gif", "0", "--no-uncertainty", "--force"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("diffcontact evaluate: error: no trained model in") and (
        "epoch0000.ckpt cannot be read" in err
    )


def test_diverged_rollouts_are_said_once(tmp_path, dataset, capsys, monkeypatch):
    """evaluate() warns (RuntimeWarning) on diverged rollouts; the command says so on its
    own WARNING line and does not repeat it as Python's two-line warning."""
    import diffcontact.learning.models.storage as storage
    from diffcontact.systems import NonFiniteRolloutError

    first_diverges = FailingTruth([0], lambda states: NonFiniteRolloutError("diverged", states))
    root = tmp_path / "r"
    root.mkdir()
    run = run_dir(root, dataset, log=False)
    (run / "model.pt").write_bytes(b"")  # (load_model is replaced)
    monkeypatch.setattr(storage, "load_model", lambda path: first_diverges)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code = cli(["evaluate", str(run), "--n-gif", "0", "--steps", "5", "--no-uncertainty"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert not [w for w in caught if "rollouts diverged" in str(w.message)]
    assert "rollouts diverged" not in err
    said = "WARNING: 1 of 3 test rollouts diverged (non-finite); left out below"
    assert out.count("rollouts diverged") == 1 and said in out


def test_the_same_run_is_evaluated_again_from_anywhere(tmp_path, dataset, capsys, monkeypatch):
    """metrics.json named the run as typed ("run"), which the check of the output folder
    resolved against the working directory: the same run evaluated again from another
    directory, or after its folder moved, was "another evaluation" (exit 2, --force)."""
    project = tmp_path / "project"
    project.mkdir()
    shutil.copytree(dataset, project / "data")
    run = _run_with_model(project / "runs", dataset)
    (run / "run.json").write_text(json.dumps({"data_dir": "../../data", "model": "CM-CD-CLNN"}))
    argv = ["--steps", "5", "--n-gif", "0", "--no-uncertainty"]
    monkeypatch.chdir(project / "runs")
    assert cli(["evaluate", "run", *argv]) == 0  # as typed: "run"
    monkeypatch.chdir(tmp_path)
    assert cli(["evaluate", str(run), *argv]) == 0, capsys.readouterr().err
    moved = tmp_path / "moved"
    project.rename(moved)  # the project folder moved: run, data and evaluation with it
    assert cli(["evaluate", str(moved / "runs" / "run"), *argv]) == 0, capsys.readouterr().err
    # a run identified by its run.json (created): the same run, moved, into a fixed --out
    out = tmp_path / "ev"
    runs = [_run_with_model(tmp_path / name, dataset) for name in ("a", "b")]
    for r, hour in zip(runs, (10, 11), strict=True):
        created = f"2026-11-28T{hour}:00:00+00:00"
        info = {"data_dir": str(dataset), "model": "CM-CD-CLNN", "created": created}
        (r / "run.json").write_text(json.dumps(info))
    assert cli(["evaluate", str(runs[0]), *argv, "--out", str(out)]) == 0
    elsewhere = runs[0].rename(tmp_path / "a-moved")
    assert cli(["evaluate", str(elsewhere), *argv, "--out", str(out)]) == 0
    capsys.readouterr()
    assert cli(["evaluate", str(runs[1]), *argv, "--out", str(out)]) == 2  # another run
    assert "of another evaluation" in _error_line(capsys)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["run_dir"] == str(elsewhere) and metrics["identity"]["run_id"]


@pytest.mark.parametrize("case", ["truncated model.pt", "too many steps", "data of 3 balls"])
def test_bad_input_leaves_no_output_folder(tmp_path, dataset, capsys, monkeypatch, case):
    """Bad input found after the output folder was made left it holding only
    .evaluation-started.json (and --steps beyond simulate's limit exited 1)."""
    monkeypatch.delenv("DIFFCONTACT_ALLOW_LARGE", raising=False)
    run = _run_with_model(tmp_path / "r", dataset)
    out = tmp_path / "deep" / "ev"
    argv = ["evaluate", str(run), "--n-gif", "0", "--no-uncertainty", "--out", str(out)]
    if case == "truncated model.pt":
        raw = (run / "model.pt").read_bytes()
        (run / "model.pt").write_bytes(raw[: len(raw) // 2])
        said = "cannot load the model of"
    elif case == "too many steps":
        argv += ["--steps", "2000000"]
        said = "steps=2000000: at most 1000000"
    else:  # the model's system with three balls
        from diffcontact.learning.data.generate import generate_dataset

        three = {**TINY, "masses": [0.1, 0.2, 0.3], "radii": [0.1] * 3, "cor": 0.8}
        other = generate_dataset(three, tmp_path / "d3", n_train=1, n_val=1, n_test=1,
                                 progress=False)  # fmt: skip
        argv += ["--data", str(other)]
        said = "data of another system"
    assert cli(argv) == 2
    assert said in _error_line(capsys)
    assert not (tmp_path / "deep").exists()


def test_an_output_folder_where_nothing_can_be_written_is_bad_input(
    tmp_path, dataset, capsys, monkeypatch
):
    """The folder's permission bits were checked (os.access, which root passes): the first
    write then failed as "evaluation failed: PermissionError" (exit 1)."""
    import tempfile

    run = _run_with_model(tmp_path / "r", dataset)
    out = tmp_path / "ev"
    out.mkdir()
    real = tempfile.mkstemp

    def refused(*args, dir=None, **kwargs):  # a read-only file system at out
        if dir is not None and Path(dir).resolve() == out.resolve():
            raise PermissionError(13, "Permission denied")
        return real(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "mkstemp", refused)
    assert cli(["evaluate", str(run), "--n-gif", "0", "--steps", "5", "--out", str(out)]) == 2
    line = _error_line(capsys)
    assert f"cannot write to the output folder {out}: Permission denied" in line
    assert list(out.iterdir()) == []


def test_a_model_of_another_run_is_blamed_not_the_runs_data(tmp_path, dataset, capsys):
    """A model.pt of another system in a run whose run.json names these data (their
    checksum): the error said the run's own data were "data of another system"."""
    from diffcontact.learning.data.format import load_dataset

    run = _run_with_model(tmp_path / "r", dataset)
    checksum = load_dataset(dataset).metadata["metadata_sha256"]
    info = {"data_dir": str(dataset), "model": "CM-CD-CLNN", "data_checksum": checksum}
    (run / "run.json").write_text(json.dumps(info))
    LearnedModel({**TINY, "masses": [0.1, 0.2, 0.3], "radii": [0.1] * 3, "cor": 0.8},
                 hidden=(4,)).save(run / "model.pt")  # fmt: skip
    assert cli(["evaluate", str(run), "--n-gif", "0", "--no-uncertainty"]) == 2
    line = _error_line(capsys)
    said = f"{run / 'model.pt'} is not the model of the run {run} (copied from another run?)"
    assert said in line
    assert "data of another system" not in line
    assert not (run / "evaluation").exists()


def test_a_test_file_given_for_the_data_folder_is_named(tmp_path, dataset, capsys):
    """--data DIR/test.npz said "test data not found: DIR/test.npz/test.npz"."""
    run = _run_with_model(tmp_path / "r", dataset)
    given = dataset / "test.npz"
    assert cli(["evaluate", str(run), "--data", str(given), "--n-gif", "0"]) == 2
    line = _error_line(capsys)
    assert f"{given} is a file: pass the dataset folder that holds it (--data {dataset})" in line
    assert "test.npz/test.npz" not in line


def test_an_interrupted_evaluation_says_its_folder_is_unfinished(
    tmp_path, dataset, capsys, monkeypatch
):
    """Ctrl-C while the files were written left the folder unfinished and the command said
    only "interrupted"."""
    import diffcontact.learning.evaluation.evaluate as ev

    run = _run_with_model(tmp_path / "r", dataset)
    argv = ["evaluate", str(run), "--n-gif", "0", "--steps", "5", "--no-uncertainty"]

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(ev, "plot_rel_error", killed)
        try:
            assert cli(argv) == 130
        except KeyboardInterrupt:  # (not pytest's own stop)
            pytest.fail("the command let the KeyboardInterrupt through")
    err = capsys.readouterr().err
    out = run / "evaluation"
    assert err.count("\n") == 1 and err.startswith("diffcontact evaluate: interrupted: ")
    assert f"{out}{os.sep} is now an unfinished evaluation (no metrics.json)" in err
    assert "run the same command again" in err
    assert cli(argv) == 0 and (out / "metrics.json").is_file()


def test_the_energy_drift_of_model_and_truth_uses_the_same_trajectories(
    tmp_path, dataset, capsys, monkeypatch
):
    """With some rollouts diverged, the model's drift was averaged over the finite ones and
    the truth's over all (metrics.json, the printed line and energy.png's right panel)."""
    import diffcontact.learning.evaluation.plots as plots
    import diffcontact.learning.models.storage as storage
    from diffcontact.systems import NonFiniteRolloutError

    truth_but_one = FailingTruth([0], lambda states: NonFiniteRolloutError("diverged", states))
    root = tmp_path / "r"
    root.mkdir()
    run = run_dir(root, dataset, log=False)
    (run / "model.pt").write_bytes(b"")  # (load_model is replaced)
    monkeypatch.setattr(storage, "load_model", lambda path: truth_but_one)
    figures = {}
    save = plots._save

    def keep(fig, path, dpi=110):
        figures[Path(path).name] = fig
        return save(fig, path, dpi)

    monkeypatch.setattr(plots, "_save", keep)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        assert cli(["evaluate", str(run), "--n-gif", "0", "--steps", "30", "--no-uncertainty"]) == 0
    out = capsys.readouterr().out
    m = json.loads((run / "evaluation" / "metrics.json").read_text())
    drift = m["energy_rel_drift"]
    assert m["n_nonfinite"] == 1 and drift["n"] == 2
    assert drift["true"] > 0.01  # restitution < 1: energy is lost
    assert drift["pred"] == pytest.approx(drift["true"], rel=1e-9)  # the truth's own rollouts
    assert "both over the 2 of 3 finite rollouts" in out
    right = figures["energy.png"].axes[1]
    true_curve, model_curve = (line.get_ydata() for line in right.get_lines())
    np.testing.assert_allclose(model_curve, true_curve, rtol=1e-9)
    assert "over the 2 of 3 trajectories" in right.get_title()
