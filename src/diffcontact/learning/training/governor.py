"""The ``threads`` option of ``train()``: a Lightning callback around :class:`ThreadGovernor`."""

from __future__ import annotations

import contextlib
from typing import Any

import lightning.pytorch as pl
import torch

from diffcontact.threads import ThreadGovernor, available_cores, claim_threads

__all__ = ["ThreadCallback", "thread_callback"]


class ThreadCallback(pl.Callback):
    """Sets torch's CPU threads for a run and puts the previous count back at its end.

    While the run lasts the threads are claimed (:func:`~diffcontact.threads.claim_threads`):
    rollouts inside it (``System.simulate(threads="auto")``) leave them to this callback.

    Args:
        threads: a fixed count, or ``None`` to let ``governor`` choose.
        governor: times every training step (validation and checkpointing
            are not timed) and chooses the count (:class:`ThreadGovernor`).
    """

    def __init__(self, threads: int | None = None, governor: ThreadGovernor | None = None) -> None:
        if (threads is None) == (governor is None):
            raise ValueError("give either a fixed thread count or a governor")
        self.threads = threads
        self.governor = governor
        self._initial: int | None = None
        self._claim: contextlib.ExitStack | None = None

    def setup(self, trainer: Any, pl_module: Any, stage: str) -> None:
        self._initial = torch.get_num_threads()
        if self._claim is None:
            self._claim = contextlib.ExitStack()
            self._claim.enter_context(claim_threads())
        if self.threads is not None:
            torch.set_num_threads(self.threads)

    def on_train_batch_start(
        self, trainer: Any, pl_module: Any, batch: Any, batch_idx: int
    ) -> None:
        if self.governor is not None:
            self.governor.start()

    def on_train_batch_end(self, trainer: Any, pl_module: Any, *args: Any) -> None:
        if self.governor is not None:
            self.governor.stop()

    def teardown(self, trainer: Any, pl_module: Any, stage: str) -> None:
        if self._claim is not None:
            self._claim.close()
            self._claim = None
        if self._initial is not None:
            torch.set_num_threads(self._initial)


def thread_callback(threads: int | str | None, device: str) -> ThreadCallback | None:
    """The callback for ``train(threads=...)``, or ``None`` when nothing is to be set.

    ``"auto"`` on the CPU: a :class:`ThreadGovernor` choosing between 1 thread
    and ``min(available_cores(), torch.get_num_threads())`` (nothing to choose
    when that is 1). On CUDA the host threads matter little and ``"auto"``
    leaves them alone. An integer fixes the count for the run; ``None`` leaves
    torch's setting alone.
    """
    if threads is None:
        return None
    if threads == "auto":
        if torch.device(device).type != "cpu":
            return None
        top = min(available_cores(), torch.get_num_threads())
        return (
            ThreadCallback(threads=1) if top == 1 else ThreadCallback(governor=ThreadGovernor(top))
        )
    return ThreadCallback(threads=int(threads))
