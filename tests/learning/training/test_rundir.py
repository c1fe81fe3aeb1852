"""Loading never runs code; writing never harms: crafted checkpoints, foreign folders, links."""

from __future__ import annotations

import errno
import json
import os
import shutil

import lightning.pytorch as pl
import pytest
import torch

from diffcontact.learning.models.storage import UnsafeFileError, load_model
from diffcontact.learning.training.run import EpochShuffleSampler, train
from diffcontact.testing import assert_usage_error, run_cli

from .support import SMALL, write_dataset

pytestmark = pytest.mark.filterwarnings("ignore:.*LeafSpec")

OPTS = dict(batch_size=4, **SMALL)


@pytest.fixture(scope="module")
def finished(bp5_data, tmp_path_factory):
    """A finished 1-epoch run (copied by the tests that change it)."""
    out = tmp_path_factory.mktemp("finished") / "run"
    train(bp5_data, out, epochs=1, **OPTS)
    return out


def _copy(run, tmp_path):
    return shutil.copytree(run, tmp_path / "run", symlinks=True)


class _Payload:
    """Unpickling this calls ``open(marker, "w")``: it creates the marker file."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _craft(path, marker, like):
    """A checkpoint shaped like ``like`` whose unpickling would create ``marker``."""
    data = torch.load(like, weights_only=True)
    data["payload"] = _Payload(marker)
    torch.save(data, path)


def test_a_crafted_checkpoint_is_refused_and_runs_no_code(bp5_data, finished, tmp_path, capsys):
    run = _copy(finished, tmp_path)
    ckpt = run / "checkpoints" / "last.ckpt"
    marker = tmp_path / "MARKER"
    # such a file does run code when loaded unsafely (a copy, with another marker)
    probe = tmp_path / "probe.ckpt"
    _craft(probe, tmp_path / "PROBE", ckpt)
    torch.load(probe, weights_only=False)
    assert (tmp_path / "PROBE").exists()
    _craft(ckpt, marker, ckpt)
    # train --resume refuses it (Lightning's resume path never loads it)
    argv = ["train", str(bp5_data), "--out", str(run), "--epochs", "2", "--batch-size", "4",
            "--hidden", "16,16", "--resume", "--quiet"]  # fmt: skip
    code, _, err = run_cli(capsys, *argv)
    assert_usage_error(code, err, "last.ckpt", "refused", "io.open")
    assert not marker.exists()
    # load_model refuses it: the checkpoint (no model.pt) and a crafted model.pt
    (run / "model.pt").unlink()
    with pytest.raises(UnsafeFileError, match="could run code"):
        load_model(run)
    _craft(run / "model.pt", marker, finished / "model.pt")
    with pytest.raises(UnsafeFileError, match=r"model\.pt"):
        load_model(run)
    code, _, err = run_cli(capsys, "evaluate", str(run), "--n-gif", "0")
    assert_usage_error(code, err, "model.pt", "refused")
    assert not marker.exists()


def test_truncated_model_files_give_one_line_errors(finished, tmp_path, capsys):
    run = _copy(finished, tmp_path)
    raw = (run / "model.pt").read_bytes()
    (run / "model.pt").write_bytes(raw[: len(raw) // 3])
    with pytest.raises(ValueError, match=r"model\.pt cannot be read \(truncated"):
        load_model(run)
    code, _, err = run_cli(capsys, "evaluate", str(run), "--n-gif", "0")
    assert_usage_error(code, err, "model.pt", "truncated")
    # random bytes: corrupted, not "unsafe" (the legacy unpickler's refusal said so)
    (run / "model.pt").write_bytes(bytes(range(256)) * 4)
    with pytest.raises(ValueError, match=r"model\.pt cannot be read .*not a torch file") as caught:
        load_model(run)
    assert not isinstance(caught.value, UnsafeFileError)


def test_out_must_be_new_empty_or_a_run_of_ours(bp5_data, tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "model.pt").write_text("my own model")
    (out / "metrics.json").write_text("{}")
    argv = ["train", str(bp5_data), "--out", str(out), "--epochs", "1", "--quiet"]
    for extra in ([], ["--resume"]):
        code, _, err = run_cli(capsys, *argv, *extra)
        assert_usage_error(code, err, "not empty and holds no diffcontact run", "model.pt")
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json", "model.pt"]
    assert (out / "model.pt").read_text() == "my own model"
    (out / "run.json").write_text(json.dumps({"name": "someone else's"}))
    code, _, err = run_cli(capsys, *argv, "--resume")
    assert_usage_error(code, err, "not the run file of a diffcontact run")
    code, _, err = run_cli(capsys, "train", str(bp5_data), "--out", str(out / "model.pt"))
    assert_usage_error(code, err, "not a directory")
    # an empty folder is fine
    (tmp_path / "empty").mkdir()
    train(bp5_data, tmp_path / "empty", epochs=1, **OPTS)
    assert (tmp_path / "empty" / "model.pt").is_file()


def test_a_planted_link_is_refused_and_never_written_through(bp5_data, finished, tmp_path, capsys):
    run = _copy(finished, tmp_path)
    outside = tmp_path / "outside.csv"
    outside.write_text("precious\n")
    (run / "logs" / "metrics.csv").unlink()
    (run / "logs" / "metrics.csv").symlink_to(outside)
    argv = ["train", str(bp5_data), "--out", str(run), "--epochs", "2", "--batch-size", "4",
            "--hidden", "16,16", "--resume", "--quiet"]  # fmt: skip
    code, _, err = run_cli(capsys, *argv)
    assert_usage_error(code, err, "metrics.csv is a symbolic link", str(outside))
    assert outside.read_text() == "precious\n"


class _Plant(pl.Callback):
    """Plant links at the run's files after the run directory was checked."""

    def __init__(self, run, target):
        self.run, self.target = run, target

    def on_train_epoch_start(self, trainer, pl_module):
        if trainer.current_epoch == 0:
            return
        for name in ("logs/metrics.csv", "learned.json", "checkpoints/last.ckpt", "model.pt"):
            path = self.run / name
            path.unlink(missing_ok=True)
            path.symlink_to(self.target)


def test_links_planted_during_a_run_are_replaced(bp5_data, tmp_path):
    """Every writer replaces a link at its file's name instead of writing through it."""
    run, outside = tmp_path / "run", tmp_path / "outside.txt"
    outside.write_text("precious\n")
    train(bp5_data, run, epochs=2, callbacks=[_Plant(run, outside)], **OPTS)
    assert outside.read_text() == "precious\n"
    for name in ("logs/metrics.csv", "learned.json", "checkpoints/last.ckpt", "model.pt"):
        assert not (run / name).is_symlink() and (run / name).is_file(), name
    assert json.loads((run / "learned.json").read_text())["epochs_done"] == 2
    assert load_model(run) is not None


def test_an_all_nan_training_set_is_an_error(tmp_path, capsys):
    data = write_dataset(tmp_path / "data", "BP5", n=(3, 1, 1), steps=8, nan_train=(0, 1, 2))
    code, _, err = run_cli(capsys, "train", str(data), "--out", str(tmp_path / "run"))
    assert_usage_error(code, err, "train.npz", "every training chunk (3)", "NaN")
    assert not (tmp_path / "run").exists()


def test_the_sampler_splits_ranks_as_lightning_did_and_skips_a_resumed_epoch():
    from lightning.fabric.utilities.distributed import DistributedSamplerWrapper

    for n, world in ((10, 2), (7, 2), (5, 3)):
        for rank in range(world):
            ours = EpochShuffleSampler(n, 3, rank=rank, world_size=world)
            theirs = DistributedSamplerWrapper(
                EpochShuffleSampler(n, 3), num_replicas=world, rank=rank, shuffle=False
            )
            assert list(ours) == list(theirs) and len(ours) == len(theirs)
    full = EpochShuffleSampler(10, 1)
    resumed = EpochShuffleSampler(10, 1, skip=(2, 4))
    for epoch in range(4):
        full.set_epoch(epoch)
        resumed.set_epoch(epoch)
        assert list(resumed) == list(full)[4 if epoch == 2 else 0 :]
    assert len(resumed) == 10


def test_atomic_writes_replace_a_link_at_the_destination(tmp_path):
    from diffcontact.io import atomic_write_bytes, find_symlinks, remove_orphan_temporaries

    target = tmp_path / "target"
    target.write_bytes(b"keep")
    link = tmp_path / "out" / "file.json"
    link.parent.mkdir()
    link.symlink_to(target)
    assert find_symlinks(tmp_path / "out") == [link]
    atomic_write_bytes(link, b"new")
    assert target.read_bytes() == b"keep" and link.read_bytes() == b"new"
    assert not link.is_symlink() and find_symlinks(tmp_path / "out") == []
    orphan = tmp_path / "out" / ".last.tmp-ab12cd34.ckpt"
    orphan.write_bytes(b"")
    (tmp_path / "out" / ".hidden").write_bytes(b"")
    assert remove_orphan_temporaries(tmp_path / "out") == [orphan]
    assert sorted(os.listdir(tmp_path / "out")) == [".hidden", "file.json"]


def test_a_run_that_took_no_step_fails_after_writing_its_directory(tmp_path, capsys, caplog):
    """Every batch held a NaN chunk, so every step was skipped: train exited 0 with an
    untrained model.pt. It now fails (exit 1) naming the reasons, the run written."""
    data = write_dataset(tmp_path / "data", "BP5", n=(3, 1, 1), steps=8, nan_train=(0,))
    run = tmp_path / "run"
    argv = ["train", str(data), "--out", str(run), "--epochs", "2", "--batch-size", "3",
            "--hidden", "8", "--quiet"]  # fmt: skip
    code, _, err = run_cli(capsys, *argv)
    assert code == 1
    assert "TrainingFailed: no optimiser step was taken: all 2 steps were skipped" in err
    assert "(2 nonfinite loss;" in err
    assert (run / "model.pt").is_file() and (run / "learned.json").is_file()
    skips = [r.getMessage() for r in caplog.records if "skipped" in r.getMessage()]
    assert [m.split(":")[0] for m in skips] == ["epoch 1", "epoch 2"]  # counted from 1


@pytest.mark.parametrize("name", ["checkpoints/last.ckpt", "checkpoints/epoch0003.ckpt"])
def test_a_folder_where_the_run_writes_a_file_is_refused_before_training(
    bp5_data, finished, tmp_path, capsys, name
):
    """A folder at last.ckpt failed the run only when the checkpoint was written, at the end
    of the first epoch trained."""
    run = _copy(finished, tmp_path)
    (run / "model.pt").unlink()
    (run / name).unlink(missing_ok=True)
    (run / name).mkdir()
    before = (run / "run.json").read_text()
    code, _, err = run_cli(
        capsys, "train", str(bp5_data), "--out", str(run), "--epochs", "4", "--batch-size", "4",
        "--hidden", "16,16", "--resume", "--quiet",
    )  # fmt: skip
    assert_usage_error(code, err, f"{run / name} is a directory", "move it away")
    assert not (run / "checkpoints" / "epoch0001.ckpt").exists()  # nothing trained
    assert (run / "run.json").read_text() == before  # nothing written


def _metrics_writer(folder):
    from diffcontact.learning.training.rundir import _RunCSVWriter

    writer = _RunCSVWriter(log_dir=str(folder))
    writer.log_metrics({"loss": 1.0}, step=0)
    writer.save()  # (the first save writes the file whole, atomically)
    writer.log_metrics({"loss": 0.5}, step=1)
    writer.log_metrics({"loss": 0.25}, step=2)
    return writer, folder / "metrics.csv"


def test_a_full_disk_names_the_log_and_leaves_no_cut_line(tmp_path, monkeypatch):
    """An append that failed for a full disk said only "No space left on device"."""
    writer, log = _metrics_writer(tmp_path)
    written = log.read_bytes()
    real_open = os.open
    # the disk is full: every write to the log fails (/dev/full says ENOSPC)
    monkeypatch.setattr(
        os, "open", lambda p, *a, **k: real_open("/dev/full" if p == log else p, *a, **k)
    )
    with pytest.raises(OSError) as caught:
        writer.save()
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(log)
    assert str(log) in str(caught.value)
    monkeypatch.undo()
    # room for half of the rows: the half-written line is taken back
    real_write = os.write

    def half(fd, data):
        if os.fstat(fd).st_ino == log.stat().st_ino:
            real_write(fd, bytes(data[: len(data) // 2]))
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_write(fd, data)

    monkeypatch.setattr(os, "write", half)
    with pytest.raises(OSError, match="No space left on device") as caught:
        writer.save()
    assert caught.value.filename == str(log)
    assert log.read_bytes() == written
    monkeypatch.undo()
    writer.save()  # space again: the rows are written once, whole
    assert log.read_text() == "loss,step\n1.0,0\n0.5,1\n0.25,2\n"
