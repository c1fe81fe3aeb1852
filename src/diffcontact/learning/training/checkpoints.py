"""Training checkpoints: written atomically, read without running code, chosen for resume.

:class:`SafeCheckpointIO` is the run's Lightning checkpoint IO. It writes a
checkpoint to a temporary file in the checkpoint's own folder and renames it
into place (Lightning's default copies from ``$TMPDIR`` into the file, so a
kill during the copy left a 0-byte ``last.ckpt`` and orphan temporary files
in ``$TMPDIR``), and reads every checkpoint with ``weights_only=True``
(:func:`~diffcontact.learning.models.storage.load_torch_file`).

:func:`resume_point` chooses what ``train(resume=True)`` continues from:
``last.ckpt``, else the newest readable ``epochNNNN.ckpt``, else nothing (the
run starts from the beginning).

:class:`EpochCheckpoint` is the run's ``ModelCheckpoint``: it writes a checkpoint at
the end of every epoch, also of an epoch whose steps were all skipped.
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.pytorch.callbacks import ModelCheckpoint

from diffcontact.io import atomic_write_bytes
from diffcontact.learning.models.storage import UnsafeFileError, load_torch_file
from diffcontact.learning.training.options import TrainingInputError

__all__ = [
    "LAST",
    "EpochCheckpoint",
    "ResumePoint",
    "SafeCheckpointIO",
    "epochs_done",
    "newest_checkpoint",
    "resume_point",
]

LAST = "last.ckpt"
_EPOCH_FILE = re.compile(r"^epoch(\d+)\.ckpt$")


class SafeCheckpointIO(TorchCheckpointIO):
    """Lightning checkpoint IO: atomic writes in the destination folder, ``weights_only`` reads."""

    def save_checkpoint(
        self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None
    ) -> None:
        if storage_options is not None:
            raise TypeError("SafeCheckpointIO takes no storage_options")
        buf = io.BytesIO()
        torch.save(checkpoint, buf)
        target = Path(path)
        target.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(target, buf.getvalue())

    def load_checkpoint(
        self, path: Any, map_location: Any = None, weights_only: bool | None = None
    ) -> dict[str, Any]:
        return load_torch_file(path, "checkpoint", map_location or "cpu")


class EpochCheckpoint(ModelCheckpoint):
    """Lightning's ``ModelCheckpoint``, but an epoch without an optimiser step is saved too.

    Lightning skips a save when the global step has not moved since the last one. An
    epoch whose steps were all skipped (non-finite losses, gradient spikes:
    docs/training.md) then left ``last.ckpt`` at an earlier epoch, and a resumed run
    repeated the epochs since, although their logs and summaries had been written.
    """

    def _should_skip_saving_checkpoint(self, trainer: Any) -> bool:
        saved, self._last_global_step_saved = self._last_global_step_saved, -1
        try:
            return super()._should_skip_saving_checkpoint(trainer)
        finally:
            self._last_global_step_saved = saved


@dataclass(frozen=True)
class ResumePoint:
    """Where a resumed run continues.

    Attributes:
        path: the checkpoint, or ``None``: no usable checkpoint, start from the beginning.
        epoch: the epoch stored in it (the epoch that was running; -1 without one).
        batches_stepped: Lightning's count of training batches before the
            checkpoint (the ``step`` column of ``metrics.csv``).
        batches_in_epoch: training batches of ``epoch`` done before a mid-epoch
            checkpoint (0 for one written at the end of an epoch).
        mid_epoch: the checkpoint was written during an epoch (an interruption).
        notes: what was skipped and why (unreadable checkpoints), one line each.
        shapes: the shape of each tensor of its ``state_dict`` (the model it holds).
    """

    path: Path | None
    epoch: int = -1
    batches_stepped: int = 0
    batches_in_epoch: int = 0
    mid_epoch: bool = False
    notes: list[str] = field(default_factory=list)
    shapes: dict[str, tuple[int, ...]] = field(default_factory=dict)


def _candidates(folder: Path) -> list[Path]:
    numbered = []
    if folder.is_dir():
        for p in folder.iterdir():
            match = _EPOCH_FILE.match(p.name)
            if match:
                numbered.append((int(match.group(1)), p))
    return [folder / LAST] + [p for _, p in sorted(numbered, reverse=True)]


def _progress(ckpt: Any) -> tuple[int, int, int, int]:
    """``(epoch, batches stepped, batches completed, batches ready)`` of a training checkpoint.

    Raises:
        KeyError, TypeError, AttributeError, ValueError: not a diffcontact training checkpoint.
    """
    if not {"state_dict", "hyper_parameters", "loops", "epoch"} <= set(ckpt):
        raise KeyError("keys")
    fit = ckpt["loops"]["fit_loop"]
    stepped = int(fit["epoch_loop.state_dict"].get("_batches_that_stepped", 0))
    current = fit["epoch_loop.batch_progress"]["current"]
    return int(ckpt["epoch"]), stepped, int(current["completed"]), int(current["ready"])


def epochs_done(ckpt: Any) -> int | None:
    """The epochs a training checkpoint's run had finished (its epoch, plus one when it
    was written at the epoch's end); ``None`` for contents that are not such a checkpoint."""
    try:
        epoch, _, done, ready = _progress(ckpt)
    except (KeyError, TypeError, AttributeError, ValueError):
        return None
    return epoch + (ready == done)


def _describe(ckpt: Any, path: Path, notes: list[str]) -> ResumePoint:
    try:
        _, stepped, done, ready = _progress(ckpt)
    except (KeyError, TypeError, AttributeError, ValueError):
        raise TrainingInputError(
            f"cannot resume: {path} is not a diffcontact training checkpoint (move it away "
            "to start the run again from its other checkpoints or from the beginning)"
        ) from None
    state = ckpt["state_dict"]
    bad = [
        name
        for name, x in (state.items() if isinstance(state, dict) else ())
        if isinstance(x, torch.Tensor) and x.is_floating_point() and not bool(x.isfinite().all())
    ]
    if bad:
        raise TrainingInputError(
            f"cannot resume: {path} holds NaN or infinite weights ({', '.join(bad[:3])}"
            f"{', ...' if len(bad) > 3 else ''}); move it away to resume from the run's "
            "earlier checkpoints"
        )
    # written at the start of a batch (an interruption): that batch was fetched, not run
    mid = ready != done
    shapes = {k: tuple(x.shape) for k, x in state.items() if isinstance(x, torch.Tensor)}
    return ResumePoint(path, int(ckpt["epoch"]), stepped, done if mid else 0, mid, notes, shapes)


def prune_checkpoints(checkpoints: Path, keep: int) -> None:
    """Remove all but the newest ``keep`` epoch checkpoints (``last.ckpt`` stays): what
    ``--keep-checkpoints`` keeps, also of a run started without it or in another folder,
    whose older checkpoints Lightning's callback does not know."""
    numbered = _candidates(checkpoints)[1:]  # newest first
    for path in numbered[keep:]:
        path.unlink(missing_ok=True)


def resume_point(checkpoints: Path) -> ResumePoint:
    """The checkpoint a resumed run continues from (see the module docstring).

    Checkpoints that cannot be read (truncated or empty, as a kill during a
    write by an earlier version left them) are skipped and named in ``notes``.

    Raises:
        TrainingInputError: a checkpoint holds more than tensors and plain data
            (loading it could run code: refused, not skipped), or is readable but
            not a diffcontact training checkpoint.
    """
    try:
        path, ckpt, notes = newest_checkpoint(checkpoints)
    except UnsafeFileError as err:
        raise TrainingInputError(f"cannot resume: {err}") from None
    if path is None:
        return ResumePoint(None, notes=notes)
    return _describe(ckpt, path, notes)


def newest_checkpoint(checkpoints: Path) -> tuple[Path | None, Any, list[str]]:
    """``(path, contents, notes)`` of the newest readable checkpoint in ``checkpoints``:
    ``last.ckpt``, else the newest readable ``epochNNNN.ckpt``; ``(None, None, notes)``
    without one. ``notes``: the checkpoints skipped as unreadable, one line each.

    Raises:
        UnsafeFileError: a checkpoint holds more than tensors and plain data
            (refused, not skipped).
    """
    notes: list[str] = []
    for path in _candidates(checkpoints):
        if not path.is_file():
            continue
        try:
            return path, load_torch_file(path, "checkpoint"), notes
        except UnsafeFileError:  # (a ValueError, but refused rather than skipped)
            raise
        except ValueError as err:
            notes.append(f"skipped {err}")
    return None, None, notes
