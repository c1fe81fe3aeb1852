"""Stopping a run early: on a signal (:class:`GracefulStop`) or a time limit (:class:`StopAfter`).

``GracefulStop`` turns SIGINT (Ctrl-C) and SIGTERM into a stop at the next
step: the step that is running finishes, a checkpoint of the state before the
next one is written (``last.ckpt``, mid-epoch; ``resume=True`` continues
from it with the same result as an uninterrupted run) and ``train()`` raises
:class:`~diffcontact.learning.training.options.TrainingInterrupted`. A second
Ctrl-C stops at once (no checkpoint): it raises ``KeyboardInterrupt``, which
Lightning's ``fit`` turns into ``SystemExit(1)`` after its own shutdown;
``train()`` reports it, seeing ``at_once``, as ``TrainingInterrupted`` too.

``StopAfter`` ends the run at the end of the first epoch that ends after a
time limit; ``train()`` then warns that the learning-rate schedule was cut.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch

__all__ = ["GracefulStop", "StopAfter", "Stopped"]

_SIGNALS = (signal.SIGINT, signal.SIGTERM)
_OTHER_RANK = -1  # ``received`` when the stop came from another rank's signal


class Stopped(Exception):
    """Raised by :class:`GracefulStop` after the checkpoint is written (caught by ``train()``)."""


class GracefulStop(pl.Callback):
    """On SIGINT or SIGTERM: finish the current step, write ``checkpoint``, raise :class:`Stopped`.

    Args:
        checkpoint: where the checkpoint goes (the run's ``last.ckpt``).
        announce: print a line on stderr when the signal arrives.

    :meth:`install` sets the handlers (main thread only: elsewhere signals
    keep their default behaviour) and :meth:`restore` puts the previous ones
    back; the callback installs them again when training starts, since
    Lightning sets its own SIGTERM handler when ``fit`` begins. With several
    processes (DDP) the stop is agreed on all ranks before the next step.
    """

    def __init__(self, checkpoint: Path, announce: bool = True) -> None:
        self.checkpoint = Path(checkpoint)
        self.announce = announce
        self.received: int | None = None
        self.at_once = False  # a second Ctrl-C raised KeyboardInterrupt: no checkpoint
        self.stopped_at: tuple[int, int] | None = None  # (epoch, batch) of the next step
        self._previous: dict[int, Any] = {}

    @property
    def signal_name(self) -> str:
        if self.received == _OTHER_RANK:
            return "a signal to another process (DDP)"
        return signal.Signals(self.received).name if self.received is not None else ""

    @property
    def exit_status(self) -> int:
        """``128 + signal number`` (143 when another rank got the signal)."""
        return 128 + (signal.SIGTERM if self.received == _OTHER_RANK else int(self.received or 0))

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for sig in _SIGNALS:
            if sig not in self._previous:
                self._previous[sig] = signal.getsignal(sig)
            signal.signal(sig, self._handle)

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    def _handle(self, signum: int, frame: Any) -> None:
        if self.received is not None:
            if signum == signal.SIGINT:  # the second Ctrl-C: stop at once
                self.at_once = True
                raise KeyboardInterrupt
            return
        self.received = signum
        if self.announce:
            again = "; press Ctrl-C again to stop at once" if signum == signal.SIGINT else ""
            print(
                f"diffcontact train: {signal.Signals(signum).name} received: stopping after "
                f"this step and writing a checkpoint{again}",
                file=sys.stderr,
                flush=True,
            )

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self.install()  # take SIGTERM back from Lightning's handler

    def _requested(self, trainer: pl.Trainer, device: torch.device) -> bool:
        flag = self.received is not None
        if trainer.world_size > 1:
            t = torch.tensor([float(flag)], dtype=torch.float64, device=device)
            flag = float(trainer.strategy.reduce(t, reduce_op="sum")) > 0
        return flag

    def on_train_batch_start(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch: Any, batch_idx: int
    ) -> None:
        if not self._requested(trainer, pl_module.device):
            return
        if self.received is None:
            self.received = _OTHER_RANK
        trainer.save_checkpoint(self.checkpoint, weights_only=False)
        self.stopped_at = (int(trainer.current_epoch), int(batch_idx))
        raise Stopped(self.signal_name)


class ResumedStepCount(pl.Callback):
    """Put Lightning's count of stepped batches back to a mid-epoch checkpoint's.

    :class:`GracefulStop` writes its checkpoint at the start of a batch, after Lightning
    has counted the previous one (``_batches_that_stepped``, the ``step`` column of
    ``metrics.csv``); restoring it, Lightning adds one more (it expects checkpoints written
    before that count), and every later row was logged one step ahead. The first batch
    after the resume sets the count back to the checkpoint's ``stepped``.
    """

    def __init__(self, stepped: int) -> None:
        self.stepped: int | None = int(stepped)

    def on_train_batch_start(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch: Any, batch_idx: int
    ) -> None:
        loop = trainer.fit_loop.epoch_loop
        if self.stepped is not None and hasattr(loop, "_batches_that_stepped"):
            loop._batches_that_stepped = self.stepped
        self.stepped = None


class StopAfter(pl.Callback):
    """Stop at the end of the first epoch that ends after ``seconds`` of this invocation.

    ``triggered`` tells whether it stopped the run.
    """

    def __init__(self, seconds: float) -> None:
        self.seconds = float(seconds)
        self.start = time.monotonic()
        self.triggered = False

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self.start = time.monotonic()

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if time.monotonic() - self.start >= self.seconds:
            trainer.should_stop = True
            self.triggered = trainer.current_epoch + 1 < (trainer.max_epochs or 0)
