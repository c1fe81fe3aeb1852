"""train(): the run directory, resume, the cosine schedule and run identity."""

from __future__ import annotations

import csv
import json
import logging
import os
from pathlib import Path

import lightning.pytorch as pl
import numpy as np
import pytest
import torch

from diffcontact.learning.models.storage import load_model
from diffcontact.learning.training.options import COSINE_FLOOR, TrainingInputError
from diffcontact.learning.training.run import train

from .support import SMALL, write_dataset


def _state(run_dir):
    return torch.load(run_dir / "model.pt", weights_only=True)["state_dict"]


def test_train_writes_the_run_directory(bp5_data, tmp_path, caplog):
    out = tmp_path / "run"
    # max_time: stop after the first epoch that ends after 1e-9 minutes, i.e. after epoch 0
    with caplog.at_level(logging.WARNING, logger="diffcontact.learning.training.run"):
        model = train(bp5_data, out, epochs=3, batch_size=4, max_time=1e-9, **SMALL)
    # the run ends early with its files, and says that the learning-rate schedule was cut
    (warning,) = [r.getMessage() for r in caplog.records if "--max-time" in r.getMessage()]
    assert "stopped after epoch 1 of 3" in warning and "schedule was cut" in warning
    assert "--resume" in warning
    run = json.loads((out / "run.json").read_text())
    assert run["model"] == "CM-CD-CLNN" and run["data_dir"] == str(bp5_data.resolve())
    assert run["dtype"] == "float64" and run["options"]["heterogeneous"] is True
    assert (out / "checkpoints" / "last.ckpt").is_file()
    assert (out / "checkpoints" / "epoch0000.ckpt").is_file()
    learned = json.loads((out / "learned.json").read_text())
    assert learned["finished"] and learned["epoch"] == 0
    stopped = learned["stopped_early"]
    assert (stopped["reason"], stopped["epochs_done"], stopped["epochs"]) == ("max_time", 1, 3)
    assert 0.5 < stopped["lr_factor"] < 1  # 2 of 6 steps along the cosine
    assert not (out / "checkpoints" / "epoch0001.ckpt").exists()
    assert learned["learned"] == model.learned_parameters()
    with open(out / "logs" / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    columns = set(rows[0])
    assert {"train/loss_epoch", "val/loss", "param/mass_ratio_4", "param/mu_29"} <= columns
    assert {"param/cor_0", "train/loss_step", "train/skipped"} <= columns
    val = [float(r["val/loss"]) for r in rows if r["val/loss"]]
    assert len(val) == 1 and np.isfinite(val[0])
    back = load_model(out)
    assert back.learned_parameters() == model.learned_parameters()
    from_ckpt = load_model(out / "checkpoints" / "last.ckpt")
    assert from_ckpt.learned_parameters() == model.learned_parameters()


class _CrashAt(pl.Callback):
    """Raise in the middle of an epoch (an interruption)."""

    def __init__(self, epoch, batch):
        self.epoch, self.batch = epoch, batch

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.current_epoch == self.epoch and batch_idx == self.batch:
            raise RuntimeError("simulated crash")


def test_resume_gives_the_uninterrupted_result(bp5_data, tmp_path):
    opts = dict(batch_size=4, seed=3, **SMALL)
    train(bp5_data, tmp_path / "a", epochs=2, keep_checkpoints=1, **opts)
    kept = sorted(p.name for p in (tmp_path / "a" / "checkpoints").iterdir())
    assert kept == ["epoch0001.ckpt", "last.ckpt"]
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(bp5_data, tmp_path / "b", epochs=2, callbacks=[_CrashAt(1, 1)], **opts)
    assert not (tmp_path / "b" / "model.pt").exists()
    assert (tmp_path / "b" / "checkpoints" / "epoch0000.ckpt").is_file()
    train(bp5_data, tmp_path / "b", epochs=2, resume=True, **opts)
    a, b = _state(tmp_path / "a"), _state(tmp_path / "b")
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(b[k], a[k]), k
    with open(tmp_path / "b" / "logs" / "metrics.csv") as fh:
        epochs = [r["epoch"] for r in csv.DictReader(fh) if r["train/loss_epoch"]]
    assert epochs == ["0", "1"]  # continuous log, the interrupted epoch once


def test_a_run_resumed_with_more_epochs_steps_at_the_longer_cosine(bp5_data, tmp_path):
    """The first step after ``--resume`` with more epochs takes the stretched schedule's
    rate, not the one the checkpoint held (the finished schedule's last: 0)."""
    seen = []

    class Record(pl.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            seen.append(trainer.optimizers[0].param_groups[0]["lr"])

    opts = dict(batch_size=4, lr=1e-3, **SMALL)
    train(bp5_data, tmp_path / "run", epochs=2, **opts)  # 8 chunks: 4 steps
    train(bp5_data, tmp_path / "run", epochs=3, resume=True, callbacks=[Record()], **opts)
    x = 4 / 5  # step 4 of 6
    factor = COSINE_FLOOR + (1 - COSINE_FLOOR) * 0.5 * (1 + np.cos(np.pi * x))
    assert seen[0] == pytest.approx(1e-3 * factor, rel=1e-12) and seen[0] > 0


def test_resume_with_fewer_epochs_than_trained_is_refused_and_changes_nothing(bp5_data, tmp_path):
    """It ended in Lightning's traceback ("You restored a checkpoint with current_epoch=1,
    but you have set Trainer(max_epochs=1)") after run.json had been rewritten."""
    opts = dict(batch_size=4, **SMALL)
    run = tmp_path / "run"
    train(bp5_data, run, epochs=2, **opts)
    before = (run / "run.json").read_bytes()
    with pytest.raises(
        TrainingInputError, match=r"--epochs 1: .* has trained 2 .*--epochs 2 or more"
    ):
        train(bp5_data, run, epochs=1, resume=True, **opts)
    assert (run / "run.json").read_bytes() == before


@pytest.mark.parametrize("variable", ["LOCAL_RANK", "SLURM_PROCID", "RANK"])
def test_a_rank_variable_does_not_turn_off_the_checks_of_a_one_process_run(
    bp5_data, tmp_path, monkeypatch, variable
):
    """A rank above 0 in the environment (a task of a multi-task SLURM job, a variable a
    launcher left) had made train() skip every check of the output folder: a finished
    run's model.pt was overwritten, a run written into the dataset folder."""
    opts = dict(batch_size=4, **SMALL)
    run = tmp_path / "run"
    train(bp5_data, run, epochs=1, **opts)
    before = (run / "model.pt").read_bytes()
    monkeypatch.setenv(variable, "1")
    with pytest.raises(TrainingInputError, match="resume"):
        train(bp5_data, run, epochs=1, **opts)  # a finished run, no --resume
    assert (run / "model.pt").read_bytes() == before
    with pytest.raises(TrainingInputError):
        train(bp5_data, bp5_data, epochs=1, **opts)  # the dataset folder
    assert not (Path(bp5_data) / "model.pt").exists()


def test_a_run_that_diverged_fails(bp5_data, tmp_path):
    """lr 1e30: one step, then every loss NaN and every step skipped; train() had returned
    as if finished (learned.json with null losses)."""
    from diffcontact.learning.training.options import TrainingFailed

    run = tmp_path / "run"
    with pytest.raises(TrainingFailed, match="training diverged: the last epoch's training"):
        train(bp5_data, run, epochs=3, lr=1e30, physics_lr=1e30, batch_size=4, **SMALL)
    assert (run / "model.pt").is_file()  # the run directory is still written


def test_an_epoch_without_an_optimiser_step_is_checkpointed(bp5_data, tmp_path):
    """Epochs whose steps were all skipped wrote no checkpoint (Lightning saves only when
    the global step has moved): last.ckpt stayed at epoch 1 and a resumed run repeated
    epochs whose logs and summaries had been written."""
    from diffcontact.learning.models.storage import load_torch_file
    from diffcontact.learning.training.checkpoints import epochs_done
    from diffcontact.learning.training.options import TrainingFailed

    run = tmp_path / "run"
    opts = dict(lr=1e30, physics_lr=1e30, batch_size=4, **SMALL)
    with pytest.raises(TrainingFailed):  # one step, then every step skipped
        train(bp5_data, run, epochs=3, **opts)
    files = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert files == ["epoch0000.ckpt", "epoch0001.ckpt", "epoch0002.ckpt", "last.ckpt"]
    assert epochs_done(load_torch_file(run / "checkpoints" / "last.ckpt", "checkpoint")) == 3


def test_a_split_of_trajectories_without_a_chunk_is_named(bp5_data, tmp_path):
    """A dataset of windows whose stride left the train split no chunk (written by an
    earlier version, which did not refuse it) was said to have an empty train split."""
    import hashlib
    import json
    import shutil

    from diffcontact.learning.data.format import metadata_checksum

    folder = tmp_path / "data"
    shutil.copytree(bp5_data, folder)
    meta = json.loads((folder / "metadata.json").read_text())
    for name in ("train", "val", "test"):
        path = folder / f"{name}.npz"
        with np.load(path) as npz:
            arrays = {k: npz[k] for k in npz.files}
        n = len(arrays["traj"])
        keep = slice(0, 0) if name == "train" else slice(None)
        for key in ("chunks", "chunk_start", "chunk_has_contact"):
            arrays[key] = arrays[key][keep]
        arrays["chunk_traj"] = np.arange(n, dtype=np.int64)[keep]
        np.savez(path, **arrays)
        meta["files"][path.name] = hashlib.sha256(path.read_bytes()).hexdigest()
    meta["stride"] = 3
    meta["metadata_sha256"] = metadata_checksum(meta)
    (folder / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(TrainingInputError, match=r"its train split holds 8 trajectories but no "
                       r"chunk: .*stride \(3\).*smaller --stride"):  # fmt: skip
        train(folder, tmp_path / "run", epochs=1, **SMALL)


def test_callbacks_that_are_not_callbacks_are_named(bp5_data, tmp_path):
    """callbacks=[1] ended in Lightning's AttributeError (no on_exception) mid-setup."""
    with pytest.raises(TrainingInputError, match=r"callbacks must be Lightning callbacks.*1"):
        train(bp5_data, tmp_path / "run", epochs=1, callbacks=[1], **SMALL)
    assert not (tmp_path / "run").exists()


def test_resume_of_a_finished_run_keeps_its_model_and_refit(bp5_data, tmp_path, caplog):
    """Re-running the same ``--resume`` command on a finished run trained nothing but
    rewrote model.pt with the Adam model and deleted refit.json and model_adam.pt."""
    opts = dict(batch_size=4, **SMALL)
    run = tmp_path / "run"
    train(bp5_data, run, epochs=2, **opts)
    (run / "refit.json").write_text("{}")  # as a refit leaves them
    (run / "model_adam.pt").write_bytes((run / "model.pt").read_bytes())
    refitted = torch.load(run / "model.pt", weights_only=True)  # another model.pt
    name = next(k for k, v in refitted["state_dict"].items() if v.is_floating_point())
    refitted["state_dict"][name] += 1.0
    torch.save(refitted, run / "model.pt")
    files = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    with caplog.at_level(logging.WARNING, logger="diffcontact.learning.training.run"):
        model = train(bp5_data, run, epochs=2, resume=True, **opts)
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == files
    assert torch.equal(model.state_dict()[name], refitted["state_dict"][name])
    assert any("nothing to train" in r.getMessage() for r in caplog.records)


def test_a_resume_that_trains_removes_the_model_of_the_earlier_stop(bp5_data, tmp_path):
    """After ``--max-time`` wrote model.pt at epoch 1, a resume killed later left that
    model.pt, and evaluate scored it as the run's model."""
    opts = dict(batch_size=4, **SMALL)
    run = tmp_path / "run"
    train(bp5_data, run, epochs=3, max_time=1e-9, **opts)  # stops after epoch 1
    assert (run / "model.pt").is_file()
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(bp5_data, run, epochs=3, resume=True, callbacks=[_CrashAt(2, 1)], **opts)
    assert not (run / "model.pt").exists()
    train(bp5_data, run, epochs=3, resume=True, **opts)
    assert json.loads((run / "learned.json").read_text())["epochs_done"] == 3


def test_a_checkpoint_of_another_model_is_refused_before_anything_is_written(bp5_data, tmp_path):
    """It failed inside Lightning (exit 1, a long state_dict message) after run.json had
    been rewritten and the log cut back to the foreign checkpoint's epoch."""
    opts = dict(batch_size=4, **SMALL)
    run, other = tmp_path / "run", tmp_path / "other"
    train(bp5_data, run, epochs=2, **opts)
    train(bp5_data, other, epochs=1, **(opts | {"hidden": (8,)}))
    (run / "checkpoints" / "last.ckpt").write_bytes(
        (other / "checkpoints" / "last.ckpt").read_bytes()
    )
    before = {p.name: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    with pytest.raises(TrainingInputError, match=r"last\.ckpt: it holds another model's weights"):
        train(bp5_data, run, epochs=3, resume=True, **opts)
    assert {p.name: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before


def test_keep_checkpoints_given_on_resume_prunes_the_earlier_ones(bp5_data, tmp_path):
    """A run started without --keep-checkpoints and resumed with it kept all of them."""
    opts = dict(batch_size=4, **SMALL)
    run = tmp_path / "run"
    train(bp5_data, run, epochs=3, **opts)
    assert len(list((run / "checkpoints").glob("epoch*.ckpt"))) == 3
    train(bp5_data, run, epochs=4, resume=True, keep_checkpoints=2, **opts)
    kept = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert kept == ["epoch0002.ckpt", "epoch0003.ckpt", "last.ckpt"]


@pytest.mark.skipif(os.name == "nt", reason="no fcntl lock on Windows")
def test_a_second_trainer_in_a_live_run_folder_is_refused(bp5_data, tmp_path):
    """Two trainers in one folder both ran, interleaving their log rows."""
    from diffcontact.learning.training.rundir import RunLock

    opts = dict(batch_size=4, **SMALL)
    run = tmp_path / "run"
    train(bp5_data, run, epochs=1, **opts)
    other = RunLock(run)  # another process's lock (a second descriptor: flock conflicts)
    other.acquire()
    before = {p.name: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    try:
        with pytest.raises(TrainingInputError, match="another process is training in"):
            train(bp5_data, run, epochs=2, resume=True, **opts)
    finally:
        other.release()
    assert {p.name: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before
    train(bp5_data, run, epochs=2, resume=True, **opts)  # the lock ended with its holder


def test_a_checkpoint_with_nan_weights_is_refused(bp5_data, tmp_path):
    opts = dict(batch_size=4, **SMALL)
    run = tmp_path / "run"
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(bp5_data, run, epochs=2, callbacks=[_CrashAt(1, 1)], **opts)
    last = run / "checkpoints" / "last.ckpt"
    ckpt = torch.load(last, weights_only=True)
    name = next(k for k, v in ckpt["state_dict"].items() if v.is_floating_point())
    ckpt["state_dict"][name].view(-1)[0] = float("nan")
    torch.save(ckpt, last)
    message = f"last.ckpt holds NaN or infinite weights .{name}"
    with pytest.raises(TrainingInputError, match=message):
        train(bp5_data, run, epochs=2, resume=True, **opts)


def test_resume_follows_moved_data_and_refuses_replaced_data(tmp_path):
    """A run's data are known by their checksum: moved data resume (the path in run.json
    follows them; they were "a different run" before, even through a link to the new
    place), other data written at the run's path are refused (they trained silently)."""
    opts = dict(batch_size=4, **SMALL)
    data, run = tmp_path / "data", tmp_path / "run"
    write_dataset(data, "BP5")
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(data, run, epochs=2, callbacks=[_CrashAt(1, 0)], **opts)
    moved = tmp_path / "moved data"
    data.rename(moved)
    train(moved, run, epochs=2, resume=True, **opts)
    info = json.loads((run / "run.json").read_text())
    assert info["data_dir"] == str(moved.resolve()) and (run / "model.pt").is_file()
    # other data at the run's path: another seed, the same shapes
    write_dataset(data, "BP5", seed=7)
    with pytest.raises(TrainingInputError, match=r"data_checksum: .*is not the one this run"):
        train(data, run, epochs=3, resume=True, **opts)


def test_a_dataset_without_a_validation_split_is_named(tmp_path):
    """generate writes empty splits (--val-fraction 0); train said the file's chunks had a
    bad shape, as for a corrupt file."""
    from diffcontact import load_system
    from diffcontact.learning import dataset_from_arrays

    system = load_system("BP5")
    traj = system.simulate(system.sample_initial_conditions(10), 19, progress=False)
    dataset_from_arrays(traj.numpy(), "BP5", tmp_path / "data", val_fraction=0.0, progress=False)
    with pytest.raises(TrainingInputError, match=r"validation split is empty.*--val-fraction"):
        train(tmp_path / "data", tmp_path / "run", epochs=1, **SMALL)
    assert not (tmp_path / "run").exists()


def test_cosine_schedule_runs_from_lr_to_the_floor(bp5_data, tmp_path):
    """Learning rates per step, logged by a callback, follow the documented cosine."""
    seen = []

    class Record(pl.Callback):
        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
            seen.append([g["lr"] for g in trainer.optimizers[0].param_groups])

    train(bp5_data, tmp_path / "run", epochs=3, batch_size=4, lr=1e-3, physics_lr=0.02,
          callbacks=[Record()], **SMALL)  # fmt: skip
    steps = len(seen)
    assert steps == 6  # 8 chunks, batch 4, 3 epochs
    floor = COSINE_FLOOR
    for k, (lr_net, lr_phys) in enumerate(seen):
        # after step k (0-based) the scheduler has advanced k + 1 times
        x = min((k + 1) / (steps - 1), 1.0)
        factor = floor + (1 - floor) * 0.5 * (1 + np.cos(np.pi * x))
        assert lr_net == pytest.approx(1e-3 * factor, rel=1e-12)
        assert lr_phys == pytest.approx(0.02 * factor, rel=1e-12)
    assert seen[-1][1] == pytest.approx(0.02 * floor)
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert (run["schedule"], run["physics_lr"]) == ("cosine", 0.02)
    # a different schedule or physics_lr is a different run: resume refuses it
    with pytest.raises(TrainingInputError, match="physics_lr"):
        train(bp5_data, tmp_path / "run", epochs=4, batch_size=4, lr=1e-3, physics_lr=0.03,
              resume=True, **SMALL)  # fmt: skip
    # so is a run of an older model format (different parameters)
    old = {**run, "model_format": 2}
    (tmp_path / "run" / "run.json").write_text(json.dumps(old))
    with pytest.raises(TrainingInputError, match="model_format: 2 -> 3"):
        train(bp5_data, tmp_path / "run", epochs=4, batch_size=4, lr=1e-3, physics_lr=0.02,
              resume=True, **SMALL)  # fmt: skip
    with pytest.raises(TrainingInputError, match="schedule must be"):
        train(bp5_data, tmp_path / "other", schedule="step", **SMALL)
    with pytest.raises(TrainingInputError, match="physics_lr must be > 0"):
        train(bp5_data, tmp_path / "other", physics_lr=-1.0, **SMALL)


@pytest.mark.parametrize("threads", ["auto", 1])
def test_threads_are_set_for_the_run_and_put_back(bp5_data, tmp_path, threads):
    """``threads``: the run uses its own count; torch's setting is unchanged afterwards."""
    seen = []

    class Spy(pl.Callback):
        def on_train_batch_end(self, *args):
            seen.append(torch.get_num_threads())

    before = torch.get_num_threads()
    train(bp5_data, tmp_path / "run", epochs=1, batch_size=4, threads=threads,
          callbacks=[Spy()], **SMALL)  # fmt: skip
    assert torch.get_num_threads() == before and seen
    if threads == 1:
        assert set(seen) == {1}
    else:
        assert set(seen) <= {1, min(before, __import__("diffcontact").threads.available_cores())}
