"""Runs never dead-end: signals stop with a checkpoint, kills leave a run that resumes."""

from __future__ import annotations

import csv
import json
import logging
import os
import signal
import subprocess
import sys
import textwrap

import lightning.pytorch as pl
import pytest
import torch

from diffcontact.learning.training.options import TrainingInputError, TrainingInterrupted
from diffcontact.learning.training.run import train
from diffcontact.testing import run_cli

from .support import SMALL

pytestmark = pytest.mark.filterwarnings("ignore:.*LeafSpec")

RUN_LOG = "diffcontact.learning.training.run"
# 8 training chunks in batches of 2: 4 steps per epoch
OPTS = dict(batch_size=2, seed=1, **SMALL)


def _state(run_dir):
    return torch.load(run_dir / "model.pt", weights_only=True)["state_dict"]


def _assert_same_weights(a, b):
    sa, sb = _state(a), _state(b)
    assert sa.keys() == sb.keys()
    for k in sa:
        assert torch.equal(sa[k], sb[k]), k


def _log_rows(run_dir):
    with open(run_dir / "logs" / "metrics.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def _epoch_losses(run_dir):
    rows = _log_rows(run_dir)
    return [(r["epoch"], r["train/loss_epoch"]) for r in rows if r["train/loss_epoch"]]


class _Signal(pl.Callback):
    """Send ``sig`` to this process at the start of step ``batch`` of ``epoch``."""

    def __init__(self, sig, epoch, batch):
        self.sig, self.at, self.sent = sig, (epoch, batch), False

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if (trainer.current_epoch, batch_idx) == self.at and not self.sent:
            self.sent = True
            signal.raise_signal(self.sig)


class _CrashAt(pl.Callback):
    def __init__(self, epoch, batch):
        self.at = (epoch, batch)

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if (trainer.current_epoch, batch_idx) == self.at:
            raise RuntimeError("simulated kill")


@pytest.fixture(scope="module")
def uninterrupted(bp5_data, tmp_path_factory):
    """A 3-epoch run without interruption (the reference)."""
    out = tmp_path_factory.mktemp("reference") / "run"
    train(bp5_data, out, epochs=3, **OPTS)
    return out


def test_ctrl_c_stops_at_the_next_step_and_resume_gives_the_uninterrupted_result(
    bp5_data, uninterrupted, tmp_path
):
    run = tmp_path / "run"
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(TrainingInterrupted) as caught:
        train(bp5_data, run, epochs=3, callbacks=[_Signal(signal.SIGINT, 1, 1)], **OPTS)
    stop = caught.value
    assert (stop.signal_name, stop.exit_status) == ("SIGINT", 130)
    # the step that was running (epoch 2, step 2) finished; the next one did not start
    assert "stopped before step 3 of 4 in epoch 2" in str(stop) and "--resume" in str(stop)
    assert stop.checkpoint == run / "checkpoints" / "last.ckpt"
    assert signal.getsignal(signal.SIGINT) is before  # handlers restored
    assert not (run / "model.pt").exists()
    ckpt = torch.load(stop.checkpoint, weights_only=True)
    assert ckpt["epoch"] == 1 and ckpt["global_step"] == 6  # 4 + 2 steps done
    train(bp5_data, run, epochs=3, resume=True, **OPTS)
    _assert_same_weights(run, uninterrupted)
    # the interrupted epoch's loss is over all of its steps, and each step is logged once
    assert _epoch_losses(run) == _epoch_losses(uninterrupted)
    steps = [r["step"] for r in _log_rows(run) if r["train/loss_step"]]
    assert len(steps) == 12 and len(set(steps)) == 12
    assert steps == [r["step"] for r in _log_rows(uninterrupted) if r["train/loss_step"]]
    a = json.loads((run / "learned.json").read_text())
    b = json.loads((uninterrupted / "learned.json").read_text())
    assert (a["train_loss"], a["val_loss"], a["global_step"]) == (
        b["train_loss"], b["val_loss"], b["global_step"]
    )  # fmt: skip


class _TwoCtrlC(pl.Callback):
    """Two SIGINTs at the start of step ``batch`` of ``epoch``: the second stops at once."""

    def __init__(self, epoch, batch):
        self.at = (epoch, batch)

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if (trainer.current_epoch, batch_idx) == self.at:
            signal.raise_signal(signal.SIGINT)  # stop after this step
            signal.raise_signal(signal.SIGINT)  # no: at once


def test_a_second_ctrl_c_stops_at_once_with_exit_status_130(
    bp5_data, tmp_path, monkeypatch, capsys
):
    """The second Ctrl-C's KeyboardInterrupt became Lightning's ``sys.exit(1)``: exit status 1
    and no message."""
    run = tmp_path / "run"
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(TrainingInterrupted) as caught:
        train(bp5_data, run, epochs=3, callbacks=[_TwoCtrlC(1, 1)], **OPTS)
    stop = caught.value
    assert (stop.signal_name, stop.exit_status, stop.checkpoint) == ("SIGINT", 130, None)
    last = run / "checkpoints" / "last.ckpt"
    assert str(stop) == (
        f"SIGINT received twice: stopped at once in epoch 2, without a checkpoint; continue "
        f"with --resume (from {last}, the last checkpoint written)"
    )
    assert signal.getsignal(signal.SIGINT) is before  # handlers restored (Lightning ignored it)
    assert torch.load(last, weights_only=True)["epoch"] == 0  # the end of epoch 1: no new one
    assert not (run / "model.pt").exists()
    # through the command line: one line after the first signal's, exit status 130
    from diffcontact.learning.training import run as run_module

    real = run_module.train
    monkeypatch.setattr(
        run_module, "train", lambda *a, **k: real(*a, callbacks=[_TwoCtrlC(0, 1)], **k)
    )
    fresh = tmp_path / "fresh"
    code, _, err = run_cli(
        capsys, "train", str(bp5_data), "--out", str(fresh), "--epochs", "2", "--batch-size",
        "2", "--hidden", "16,16", "--quiet",
    )  # fmt: skip
    assert code == 130, err
    lines = err.strip().splitlines()
    assert lines[-2].startswith("diffcontact train: SIGINT received: stopping after this step")
    assert lines[-1] == (
        "diffcontact train: SIGINT received twice: stopped at once in epoch 1, without a "
        "checkpoint; no checkpoint was written yet: --resume starts the run again"
    )
    assert "Traceback" not in err and not (fresh / "checkpoints" / "last.ckpt").exists()


SIGTERM_SCRIPT = textwrap.dedent(
    """
    import os, signal, sys
    import lightning.pytorch as pl
    from diffcontact.cli import main
    from diffcontact.learning.training import run

    class Term(pl.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            if (trainer.current_epoch, batch_idx) == (0, 1):
                os.kill(os.getpid(), signal.SIGTERM)

    real = run.train
    run.train = lambda *a, **k: real(*a, callbacks=[Term()], **k)
    sys.exit(main(sys.argv[1:]))
    """
)


def test_sigterm_through_the_cli_writes_a_checkpoint_and_exits_143(bp5_data, tmp_path, capsys):
    run = tmp_path / "run"
    argv = ["train", str(bp5_data), "--out", str(run), "--epochs", "2", "--batch-size", "2",
            "--seed", "1", "--hidden", "16,16", "--quiet"]  # fmt: skip
    proc = subprocess.run(
        [sys.executable, "-c", SIGTERM_SCRIPT, *argv], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 143, proc.stderr
    assert "Traceback" not in proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("diffcontact train: SIGTERM received: stopped before step 3 of 4")
    assert "last.ckpt" in last and "--resume" in last
    assert "epoch 1/2" not in proc.stdout  # stopped inside the first epoch
    assert torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["global_step"] == 2
    code, out, _ = run_cli(capsys, *argv, "--resume")
    assert code == 0
    # --quiet still prints one line per epoch: losses and the learned parameters
    lines = [line for line in out.splitlines() if line.startswith("epoch ")]
    assert [line.split(":")[0] for line in lines] == ["epoch 1/2", "epoch 2/2"]
    assert all("loss" in line and "m_i/m_1" in line and "e_P" in line for line in lines)
    assert json.loads((run / "learned.json").read_text())["global_step"] == 8


KILL_SCRIPT = textwrap.dedent(
    """
    import os, signal, sys
    real = os.replace
    seen = []

    def replace(src, dst, *args, **kwargs):  # killed just before the 2nd last.ckpt is renamed
        if str(dst).endswith("last.ckpt"):
            seen.append(dst)
            if len(seen) == 2:
                os.kill(os.getpid(), signal.SIGKILL)
        return real(src, dst, *args, **kwargs)

    os.replace = replace
    from diffcontact.cli import main
    sys.exit(main(sys.argv[1:]))
    """
)


def test_a_kill_while_a_checkpoint_is_written_leaves_the_previous_one(bp5_data, tmp_path, capsys):
    run, tmpdir = tmp_path / "run", tmp_path / "tmpdir"
    tmpdir.mkdir()
    argv = ["train", str(bp5_data), "--out", str(run), "--epochs", "2", "--batch-size", "4",
            "--hidden", "8", "--quiet"]  # fmt: skip
    env = {**os.environ, "TMPDIR": str(tmpdir)}
    proc = subprocess.run(
        [sys.executable, "-c", KILL_SCRIPT, *argv], capture_output=True, env=env, timeout=300
    )
    assert proc.returncode == -signal.SIGKILL
    checkpoints = run / "checkpoints"
    # last.ckpt is still the whole checkpoint of epoch 1; the new one was never renamed over it
    assert torch.load(checkpoints / "last.ckpt", weights_only=True)["epoch"] == 0
    orphans = [p.name for p in checkpoints.iterdir() if ".tmp-" in p.name]
    assert len(orphans) == 1 and orphans[0].startswith(".last.tmp-")
    assert not [p for p in tmpdir.rglob("*") if p.is_file()]  # nothing written to $TMPDIR
    code, _, err = run_cli(capsys, *argv, "--resume")
    assert code == 0, err
    assert not [p for p in checkpoints.iterdir() if ".tmp-" in p.name]  # the orphan is gone
    learned = json.loads((run / "learned.json").read_text())
    assert learned["finished"] and learned["global_step"] == 4


def test_a_run_killed_before_its_first_checkpoint_is_started_again(
    bp5_data, tmp_path, caplog, capsys
):
    fresh, run = tmp_path / "fresh", tmp_path / "run"
    train(bp5_data, fresh, epochs=1, **OPTS)
    with pytest.raises(RuntimeError, match="simulated kill"):
        train(bp5_data, run, epochs=1, callbacks=[_CrashAt(0, 2)], **OPTS)
    assert (run / "run.json").is_file() and not list((run / "checkpoints").glob("*.ckpt"))
    assert len(_log_rows(run)) == 2  # the rows of the two steps taken
    # without --resume: refused, saying what to do
    code, _, err = run_cli(capsys, "train", str(bp5_data), "--out", str(run), "--epochs", "1")
    assert code == 2 and "no checkpoint yet" in err and "--resume" in err
    with caplog.at_level(logging.WARNING, logger=RUN_LOG):
        train(bp5_data, run, epochs=1, resume=True, **OPTS)
    assert any("starting it again from the beginning" in r.getMessage() for r in caplog.records)
    _assert_same_weights(run, fresh)
    assert len(_log_rows(run)) == len(_log_rows(fresh))  # the old rows are gone
    # --resume of an empty or new folder starts a new run
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger=RUN_LOG):
        train(bp5_data, tmp_path / "new", epochs=1, resume=True, **OPTS)
    assert any("starting a new run" in r.getMessage() for r in caplog.records)
    _assert_same_weights(tmp_path / "new", fresh)


def test_unreadable_checkpoints_are_skipped_on_resume(bp5_data, tmp_path, caplog):
    """A 0-byte last.ckpt and a truncated epoch0001.ckpt (what a kill used to leave)."""
    ref, run = tmp_path / "ref", tmp_path / "run"
    train(bp5_data, ref, epochs=2, **OPTS)
    train(bp5_data, run, epochs=2, **OPTS)
    checkpoints = run / "checkpoints"
    (checkpoints / "last.ckpt").write_bytes(b"")
    half = (checkpoints / "epoch0001.ckpt").read_bytes()
    (checkpoints / "epoch0001.ckpt").write_bytes(half[: len(half) // 2])
    (run / "model.pt").unlink()
    with caplog.at_level(logging.WARNING, logger=RUN_LOG):
        train(bp5_data, run, epochs=2, resume=True, **OPTS)
    messages = " | ".join(r.getMessage() for r in caplog.records)
    assert "last.ckpt cannot be read (truncated or corrupted?): it is empty" in messages
    assert "epoch0001.ckpt cannot be read" in messages
    assert f"from {checkpoints / 'epoch0000.ckpt'}" in messages
    _assert_same_weights(run, ref)  # epoch 2 run again from the end of epoch 1
    assert _epoch_losses(run) == _epoch_losses(ref)
    # a finished run whose checkpoints were all deleted is not silently trained again
    for p in checkpoints.iterdir():
        p.unlink()
    with pytest.raises(TrainingInputError, match=r"finished model\.pt but no checkpoint"):
        train(bp5_data, run, epochs=3, resume=True, **OPTS)


def test_a_log_cut_mid_line_keeps_its_complete_rows_on_resume_and_says_so(
    bp5_data, uninterrupted, tmp_path, caplog
):
    """A crash (or a full disk) while a row was appended cut logs/metrics.csv in the middle
    of a line: the resume kept the cut row (a number cut short) or dropped it, silently."""
    run = tmp_path / "run"
    with pytest.raises(RuntimeError, match="simulated kill"):
        train(bp5_data, run, epochs=3, callbacks=[_CrashAt(2, 1)], **OPTS)
    log = run / "logs" / "metrics.csv"
    lines = log.read_text().splitlines(keepends=True)
    # lines[7:13]: epoch 2's rows; the disk filled while its third step's row (line 10)
    # was written: it ends 5 characters short (in its loss), the rest never was written
    assert lines[9].split(",")[0] == "1" and lines[9].endswith(",,\n")
    log.write_text("".join(lines[:9]) + lines[9][:-5])
    with caplog.at_level(logging.WARNING, logger="diffcontact.learning.training.rundir"):
        train(bp5_data, run, epochs=3, resume=True, **OPTS)
    warned = [r.getMessage() for r in caplog.records if "metrics.csv" in r.getMessage()]
    assert len(warned) == 1, warned
    assert warned[0].startswith(f"{log}: line 10 is incomplete (cut mid-line")
    assert "kept the 8 rows before it" in warned[0]
    _assert_same_weights(run, uninterrupted)  # (the checkpoint of epoch 2 was resumed)

    def key(row):  # (time/epoch_s differs between runs)
        return {k: v for k, v in row.items() if k != "time/epoch_s"}

    rows, ref = [key(r) for r in _log_rows(run)], [key(r) for r in _log_rows(uninterrupted)]
    # every complete row before the cut, no row of the cut on, epoch 3 written again
    assert rows == ref[:8] + [r for r in ref if r["epoch"] == "2"]


def test_incomplete_lines_anywhere_in_the_log_are_dropped_and_named(tmp_path, caplog):
    """Rows appended after a cut line continue it (one line with too many cells); NUL bytes
    are what a crash can leave in a file's last block."""
    from diffcontact.learning.training.rundir import truncate_log

    log = tmp_path / "logs" / "metrics.csv"
    log.parent.mkdir()
    rows = [f"{e},{s},{0.5 + s}\n" for e, s in ((0, 0), (0, 1), (1, 2), (1, 3), (2, 4))]
    log.write_text(
        "epoch,step,loss\n" + rows[0] + rows[1][:-3] + "".join(rows[1:4]) + "\0\0\0\n" + rows[4]
    )
    with caplog.at_level(logging.WARNING, logger="diffcontact.learning.training.rundir"):
        truncate_log(tmp_path, 2, 0)
    assert log.read_text() == "epoch,step,loss\n" + rows[0] + "".join(rows[2:4])
    (message,) = [r.getMessage() for r in caplog.records]
    assert message.startswith(f"{log}: lines 3, 6 are incomplete (cut mid-line")
    assert "kept the 1 rows before the first and the 2 complete rows after it" in message
    # a complete log: nothing said
    caplog.clear()
    truncate_log(tmp_path, 1, 3)
    assert log.read_text() == "epoch,step,loss\n" + rows[0] + rows[2] and not caplog.records


class _SignalInLastValidation(pl.Callback):
    """SIGINT during the validation of the last epoch: no training step is left to stop."""

    def __init__(self, epochs):
        self.epoch, self.sent = epochs - 1, False

    def on_validation_batch_start(self, trainer, pl_module, batch, batch_idx, *args):
        if trainer.current_epoch == self.epoch and not self.sent:
            self.sent = True
            signal.raise_signal(signal.SIGINT)


def test_ctrl_c_after_the_last_step_says_that_the_run_finished(
    bp5_data, tmp_path, monkeypatch, capsys
):
    """The announcement said "stopping after this step and writing a checkpoint", then the
    run finished (model.pt, exit status 0) and nothing said so; a --refit ran on."""
    from diffcontact.learning.training import run as run_module

    real = run_module.train
    monkeypatch.setattr(
        run_module, "train", lambda *a, **k: real(*a, callbacks=[_SignalInLastValidation(2)], **k)
    )
    run = tmp_path / "run"
    code, _, err = run_cli(
        capsys, "train", str(bp5_data), "--out", str(run), "--epochs", "2", "--batch-size",
        "2", "--hidden", "16,16", "--quiet", "--refit", "1",
    )  # fmt: skip
    assert code == 0, err
    assert (run / "model.pt").is_file() and not (run / "refit.json").exists()
    assert json.loads((run / "learned.json").read_text())["finished"] is True
    lines = err.strip().splitlines()
    assert lines[-2].startswith("diffcontact train: SIGINT received: stopping after this step")
    assert lines[-1] == (
        "diffcontact train: SIGINT was received after the last training step, so nothing was "
        f"left to stop: the run ended normally and wrote {run / 'model.pt'} (nothing to "
        f"resume); the refit was not run (diffcontact refit {run} --iterations 1 runs it)"
    )
