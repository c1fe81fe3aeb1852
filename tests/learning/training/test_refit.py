"""The Gauss-Newton refit: its normal equations against autograd, that it only keeps steps
that lower the validation error, the run-directory files, and bad input."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

import pytest
import torch

from diffcontact.learning.data.format import load_dataset
from diffcontact.learning.models import LearnedModel
from diffcontact.learning.models.storage import load_model, save_model
from diffcontact.learning.training import refit as refit_module
from diffcontact.learning.training.cli import _run_refit_cli
from diffcontact.learning.training.options import TrainingInputError
from diffcontact.learning.training.refit import (
    _free_entries,
    _normal_equations,
    refit,
    rollout_residual,
)
from diffcontact.learning.training.run import train

from ..data.support import read_only_storage
from .support import SMALL, write_dataset


@pytest.fixture(scope="module")
def cp3_data(tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("cp3"), "CP3", n=(12, 6, 4), steps=30)


def _model(seed: int = 0) -> LearnedModel:
    torch.manual_seed(seed)
    model = LearnedModel("CP3", hidden=(16, 16)).double()
    with torch.no_grad():
        model.log_mass_rel.copy_(torch.tensor([0.0, 0.6, 0.45], dtype=torch.float64))
        model.raw_mu.fill_(0.45)
        model.raw_cor.fill_(0.2)
    return model


def _chunks(folder, split):
    return load_dataset(folder).split(split, dtype=torch.float64).chunks


def test_normal_equations_match_autograd(cp3_data):
    """J^T r is the gradient of 0.5 ||r||^2 (autograd through the normal rollout path, for
    the output weights and the physical parameters the refit moves); J^T J is symmetric
    positive semi-definite."""
    model = _model()
    chunks = _chunks(cp3_data, "train")
    free = _free_entries(model)
    assert [label for label, _, _ in free] == [
        "log_mass_rel[1]", "log_mass_rel[2]", "raw_mu[0]", "raw_cor[0]",
    ]  # fmt: skip
    base = model.potential
    w = base.layers[-1].weight.detach().clone().squeeze(0)

    residual = rollout_residual(model)

    JtJ, Jtr = _normal_equations(residual, chunks, w, free)
    pred = model.simulate(chunks[:, 0], chunks.shape[1] - 1, check_overlap=False)
    loss = 0.5 * (pred[:, 1:] - chunks[:, 1:]).pow(2).sum()
    params = [base.layers[-1].weight, model.log_mass_rel, model.raw_mu, model.raw_cor]
    g_w, g_mass, g_mu, g_cor = torch.autograd.grad(loss, params)
    expected = torch.cat([g_w.flatten(), g_mass[1:], g_mu, g_cor])
    torch.testing.assert_close(Jtr, expected, rtol=1e-6, atol=1e-9 * expected.abs().max())
    torch.testing.assert_close(JtJ, JtJ.T)
    assert torch.linalg.eigvalsh(JtJ).min() > -1e-9 * JtJ.diagonal().max()


def test_refit_lowers_the_validation_error_and_keeps_only_improvements(cp3_data):
    model = _model(1)
    train_chunks, val_chunks = _chunks(cp3_data, "train"), _chunks(cp3_data, "val")
    lines: list[str] = []
    report = refit(model, train_chunks, val_chunks, 3, log=lines.append)
    assert report.val_mse < 0.1 * report.val_mse_before
    assert report.train_mse < 0.1 * report.train_mse_before
    accepted = [it for it in report.iterations if it["accepted"]]
    assert accepted and all(it["val_mse"] <= report.val_mse_before for it in accepted)
    vals = [it["val_mse"] for it in accepted]
    assert vals == sorted(vals, reverse=True)  # each kept step lowered it
    assert len(lines) == 1 + len(report.iterations)
    # the model now computes what the report says (the normal forward path, not the refit's)
    pred = model.simulate(val_chunks[:, 0], val_chunks.shape[1] - 1, check_overlap=False)
    mse = (pred[:, 1:] - val_chunks[:, 1:]).pow(2).mean().item()
    assert mse == pytest.approx(report.val_mse, rel=1e-6)
    # no step can lower the validation error of a refit model much further: with damping
    # factors this large, the steps are tiny and rejected or accepted, never harmful
    again = refit(model, train_chunks, val_chunks, 1, lambdas=(1e6,), log=None)
    assert again.val_mse <= report.val_mse


def test_refit_run_writes_the_files(cp3_data, tmp_path, monkeypatch):
    # the second refit below must find a step that lowers the validation MSE: it does with
    # the default (Warp) solver; the torch reference's rounding leaves it without one
    monkeypatch.delenv("DIFFCONTACT_SOLVER", raising=False)
    run = tmp_path / "run"
    train(cp3_data, run, epochs=2, refit=1, threads=1, **SMALL)
    report = json.loads((run / "refit.json").read_text())
    assert report["val_mse"] < report["val_mse_before"]
    assert report["iterations"][0]["accepted"]
    learned = json.loads((run / "learned.json").read_text())
    assert learned["refit"]["val_mse"] == report["val_mse"]
    before, after = load_model(run / "model_adam.pt"), load_model(run)
    w0, w1 = before.potential.layers[-1].weight, after.potential.layers[-1].weight
    assert not torch.equal(w0, w1)
    torch.testing.assert_close(before.potential.layers[0].weight, after.potential.layers[0].weight)
    # a refit that changes nothing says so and leaves every file as it was
    files = {f.name: f.read_bytes() for f in run.iterdir() if f.is_file()}
    out = subprocess.run(
        [sys.executable, "-m", "diffcontact", "refit", str(run), "--iterations", "0"],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "no iteration was run (--iterations 0)" in out.stdout
    assert "is unchanged" in out.stdout and "wrote" not in out.stdout
    assert {f.name: f.read_bytes() for f in run.iterdir() if f.is_file()} == files
    # refitting again keeps model_adam.pt (the model before the first refit)
    adam_bytes = (run / "model_adam.pt").read_bytes()
    out = subprocess.run(
        [sys.executable, "-m", "diffcontact", "refit", str(run), "--iterations", "1"],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "refit.json" in out.stdout
    assert (run / "model_adam.pt").read_bytes() == adam_bytes
    # training the run further makes model.pt Adam's again: the refit's files go
    train(cp3_data, run, epochs=3, resume=True, threads=1, **SMALL)
    assert not (run / "refit.json").exists() and not (run / "model_adam.pt").exists()


def test_bad_input(cp3_data, tmp_path):
    with pytest.raises(TrainingInputError, match="refit must be a non-negative integer"):
        train(cp3_data, tmp_path / "a", epochs=1, refit=-1, **SMALL)
    with pytest.raises(TrainingInputError, match="no potential network to refit"):
        train(cp3_data, tmp_path / "b", epochs=1, refit=1, model="IN-SP-CP", progress=False)
    chunks = _chunks(cp3_data, "train")
    with pytest.raises(ValueError, match="needs a physical model with a potential network"):
        refit(torch.nn.Linear(2, 2), chunks, chunks)
    with pytest.raises(ValueError, match=r"shape \(N, L, 2, P, dim\)"):
        refit(_model(), chunks[:, :1], chunks)
    with pytest.raises(ValueError, match="no chunk without NaN"):
        refit(_model(), chunks, torch.full_like(chunks, float("nan")))
    with pytest.raises(ValueError, match="iterations must be a non-negative integer"):
        refit(_model(), chunks, chunks, -1)
    # refit_run(RUN, iterations=True) ran one iteration; refit_run(None) a raw TypeError;
    # both checked before anything is loaded
    from diffcontact.learning.training.refit import refit_run

    with pytest.raises(ValueError, match="iterations must be a non-negative integer, got True"):
        refit_run(tmp_path / "missing", iterations=True)
    with pytest.raises(ValueError, match="run_dir must be a path, got NoneType"):
        refit_run(None)
    with pytest.raises(ValueError, match="float64"):
        refit(LearnedModel("CP3", hidden=(4,)).float(), chunks, chunks)
    (tmp_path / "unfinished").mkdir()
    out = subprocess.run(
        [sys.executable, "-m", "diffcontact", "refit", str(tmp_path / "unfinished")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert out.returncode == 2
    assert "diffcontact refit: error:" in out.stderr and "no model.pt" in out.stderr
    assert "Traceback" not in out.stderr


def _fake_run(folder, data):
    """A run directory holding what refit reads: model.pt and run.json's data_dir."""
    folder.mkdir()
    save_model(_model(), folder / "model.pt")
    (folder / "run.json").write_text(json.dumps({"data_dir": str(data)}))
    return folder


def _refit_cli(capsys, run, iterations: int) -> tuple[int, str, str]:
    code = _run_refit_cli(argparse.Namespace(run_dir=str(run), iterations=iterations, data=None))
    out, err = capsys.readouterr()
    return code, out, err


def test_refit_with_no_iterations_says_so(cp3_data, tmp_path, capsys):
    """``--iterations 0`` said "no step lowered the validation MSE", though none was tried."""
    run = _fake_run(tmp_path / "run", cp3_data)
    code, out, err = _refit_cli(capsys, run, 0)
    assert code == 0, err
    assert f"no iteration was run (--iterations 0): {run} is unchanged" in out
    assert "no step lowered" not in out


def test_refit_refuses_a_read_only_run_before_any_work(cp3_data, tmp_path, monkeypatch, capsys):
    """A run on read-only storage ran every iteration, then failed writing
    ``.model_adam.tmp-*.pt`` (``OSError``, exit 1)."""
    run = _fake_run(tmp_path / "run", cp3_data)
    files = {f.name: f.read_bytes() for f in run.iterdir()}

    def no_refit(*args, **kwargs):
        raise AssertionError("refit ran on a run it cannot write")

    monkeypatch.setattr(refit_module, "refit", no_refit)
    attempts = read_only_storage(monkeypatch, run)
    with pytest.raises(ValueError, match=r"cannot refit .*run: folder .*run is not writable"):
        refit_module.refit_run(run, 2)
    code, out, err = _refit_cli(capsys, run, 2)
    assert code == 2 and out == ""
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("diffcontact refit: error: cannot refit"), err
    assert "is not writable" in lines[0]
    assert attempts == []
    monkeypatch.undo()
    assert {f.name: f.read_bytes() for f in run.iterdir()} == files


def test_refit_of_a_missing_folder_says_it_does_not_exist(tmp_path, capsys):
    """``refit nope`` said "nope: no model.pt (not a finished run ...)"."""
    code, _, err = _refit_cli(capsys, tmp_path / "nope", 2)
    assert code == 2 and f"run directory {tmp_path / 'nope'} does not exist" in err


def test_a_refit_killed_between_its_writes_is_finished_by_the_next(cp3_data, tmp_path):
    """A kill after ``model.pt`` was written left ``learned.json`` (and ``refit.json``) of the
    model before, and a second refit, starting from the refitted model, kept no step and
    returned without touching them: the run stayed inconsistent."""
    from diffcontact import io as dc_io

    run = _fake_run(tmp_path / "run", cp3_data)
    adam = {"finished": True, "learned": _model().learned_parameters()}  # training's
    (run / "learned.json").write_text(json.dumps(adam))
    before = (run / "model.pt").read_bytes()
    write_json = dc_io.atomic_write_json

    def killed_at_learned_json(path, data):
        if path.name == "learned.json":
            raise KeyboardInterrupt  # the kill: after model.pt, before learned.json
        return write_json(path, data)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(dc_io, "atomic_write_json", killed_at_learned_json)
        with pytest.raises(KeyboardInterrupt):
            refit_module.refit_run(run, 1, log=None)
    assert (run / "model.pt").read_bytes() != before  # the refitted model
    assert json.loads((run / "learned.json").read_text()) == adam  # Adam's, not the refit's
    assert not (run / "refit.json").exists()

    lines: list[str] = []
    report = refit_module.refit_run(run, 0, log=lines.append)  # no iteration: only the repair
    assert report.iterations == []
    model = load_model(run)
    learned = json.loads((run / "learned.json").read_text())
    assert learned["learned"] == json.loads(json.dumps(model.learned_parameters()))
    assert learned["learned"] != adam["learned"]  # the refit moved the physical parameters
    assert learned["finished"] is True  # training's entries kept
    refit_report = json.loads((run / "refit.json").read_text())
    assert learned["refit"]["val_mse"] == refit_report["val_mse"]
    assert refit_report["iterations"][0]["accepted"]
    assert refit_report["data_dir"] == str(cp3_data)
    assert any("finished the writes of an interrupted refit" in line for line in lines), lines
    assert not (run / refit_module.PENDING).exists()


def test_a_refit_killed_before_model_pt_leaves_the_run_as_it_was(cp3_data, tmp_path):
    """The journal of a refit killed before it replaced ``model.pt`` is removed by the next
    refit, which says so and goes on from the model before."""
    from diffcontact import io as dc_io

    run = _fake_run(tmp_path / "run", cp3_data)
    before = (run / "model.pt").read_bytes()
    write_bytes = dc_io.atomic_write_bytes

    def killed_at_model_pt(path, data):
        if path.name == "model.pt":
            raise KeyboardInterrupt
        return write_bytes(path, data)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(dc_io, "atomic_write_bytes", killed_at_model_pt)
        with pytest.raises(KeyboardInterrupt):
            refit_module.refit_run(run, 1, log=None)
    assert (run / "model.pt").read_bytes() == before
    assert (run / refit_module.PENDING).is_file()

    lines: list[str] = []
    refit_module.refit_run(run, 0, log=lines.append)
    assert any("model.pt is not the one it names" in line for line in lines), lines
    assert not (run / refit_module.PENDING).exists()
    assert (run / "model.pt").read_bytes() == before
    assert not (run / "learned.json").exists() and not (run / "refit.json").exists()


def test_refit_on_a_dataset_without_a_validation_split_says_so(cp3_data, tmp_path, capsys):
    """A dataset made with ``val_fraction=0`` made ``refit --iterations 1 --data DS`` say
    "val_chunks: no chunk without NaN or infinite values": there is no NaN, the split is
    empty (``train`` says so)."""
    from diffcontact.learning.data.arrays import dataset_from_arrays

    traj = load_dataset(cp3_data).split("train").traj.numpy()
    data = dataset_from_arrays(traj, load_dataset(cp3_data).metadata["config"],
                               tmp_path / "noval", val_fraction=0, progress=False)  # fmt: skip
    run = _fake_run(tmp_path / "run", data)
    code, out, err = _refit_cli(capsys, run, 1)
    assert code == 2 and out == "", err
    assert f"error: {data}: its validation split is empty, and refit chooses the damping " in err
    assert "--val-fraction (or --n-val) above 0" in err and "NaN" not in err
    chunks = _chunks(cp3_data, "train")
    with pytest.raises(ValueError, match=r"val_chunks holds no chunk \(shape \(0, 5, 2, 3, 2\)\)"):
        refit(_model(), chunks, chunks[:0])
