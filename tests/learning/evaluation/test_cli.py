"""``diffcontact evaluate``: bad input gives one line on stderr and exit status 2."""

from __future__ import annotations

import json
import shutil
import warnings

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
    (run / "model.pt").unlink()  # as a run killed before its end leaves it
    assert cli(["evaluate", str(run), "--n-gif", "0", "--no-uncertainty"]) == 0
    out = capsys.readouterr().out
    assert "WARNING: " in out and "has no model.pt (its training did not finish)" in out
    metrics = json.loads((run / "evaluation" / "metrics.json").read_text())
    assert "last checkpoint after 1 of 1 epochs" in metrics["model_note"]


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
        f"{run} has no model.pt (its training did not finish): this is its newest epoch "
        "checkpoint, checkpoints/epoch0001.ckpt after 2 of 2 epochs (no checkpoints/last.ckpt), "
        "not a final model"
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
