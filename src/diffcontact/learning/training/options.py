"""Training options: every default of ``train()``, ``RolloutModule`` and ``diffcontact train``.

One set of constants, used by all three (no torch at import, so the command
line can show them). :func:`check_options` validates the numbers a user gives
and raises :class:`TrainingInputError` with a one-line message.
"""

from __future__ import annotations

import math
from typing import Any

from diffcontact.io import parse_device
from diffcontact.learning.models.registry import model_names

__all__ = [
    "COSINE_FLOOR",
    "DEFAULT_BATCH_SIZE",
    "DEFAULT_DEVICE",
    "DEFAULT_DTYPE",
    "DEFAULT_EPOCHS",
    "DEFAULT_EPS",
    "DEFAULT_HIDDEN",
    "DEFAULT_LR",
    "DEFAULT_MODEL",
    "DEFAULT_PHYSICS_LR",
    "DEFAULT_SCHEDULE",
    "DEFAULT_SEED",
    "DEFAULT_WEIGHT_DECAY",
    "DTYPE_NAMES",
    "SCHEDULES",
    "TrainingInputError",
    "TrainingInterrupted",
    "check_options",
]

DEFAULT_MODEL = "CM-CD-CLNN"
DEFAULT_EPOCHS = 100
# AdamW for the potential network (paper-facts.md, "Training set-up")
DEFAULT_BATCH_SIZE = 200
DEFAULT_LR = 1e-3
DEFAULT_WEIGHT_DECAY = 1e-4
# the physical parameters (a handful of numbers) take larger steps than the potential
# network; measured in docs/training.md ("Learning rates")
DEFAULT_PHYSICS_LR = 3e-2
SCHEDULES = ("cosine", "constant")
DEFAULT_SCHEDULE = "cosine"
# the cosine schedule ends at zero: Adam moves a parameter by about its learning rate per
# step, so a floor of 1% left the mass ratios jittering by ~1e-4, which the chaotic
# test rollouts amplify (docs/training.md, "Learning rates and schedule")
COSINE_FLOOR = 0.0
# chosen from the float32/float64 measurement in docs/training.md: float32 saves ~20% per
# step but its gradients through CM's singular contact problems need a larger KKT
# regularisation; float64 gradients match without it
DTYPE_NAMES = ("float32", "float64")
DEFAULT_DTYPE = "float64"
DEFAULT_SEED = 0
DEFAULT_DEVICE = "cpu"
DEFAULT_EPS = 0.01  # CMr's regulariser
DEFAULT_HIDDEN = (256, 256, 256)  # hidden widths of the potential MLP


class TrainingInputError(ValueError):
    """Bad input to ``train()`` (data, options, run directory); one-line message."""


class TrainingFailed(RuntimeError):
    """``train()`` ran every epoch but took no optimiser step (every step was skipped:
    non-finite losses or gradients, solver failures, spikes), or diverged (its last epoch's
    training and validation losses are not finite). The run directory is written (its
    ``model.pt`` holds the model as it ended); the message names the reasons."""


class TrainingInterrupted(KeyboardInterrupt):
    """``train()`` stopped on SIGINT (Ctrl-C) or SIGTERM after writing a checkpoint.

    Attributes:
        signal_name: ``"SIGINT"`` or ``"SIGTERM"``.
        exit_status: ``128 + signal number`` (130, 143), the status of the command.
        checkpoint: the checkpoint written (resume with ``resume=True``), or
            ``None`` when none was written (a second Ctrl-C stopped the run at once).
    """

    def __init__(self, message: str, signal_name: str, exit_status: int, checkpoint: Any) -> None:
        super().__init__(message)
        self.signal_name = signal_name
        self.exit_status = exit_status
        self.checkpoint = checkpoint

    def __reduce__(self) -> tuple[Any, ...]:
        # picklable with its attributes: a worker process of experiments/reproduce.py or
        # compare.py sends it back to the main one (unpickled from ``args`` alone it failed,
        # and the pool broke: BrokenProcessPool for every run)
        return (type(self), (str(self), self.signal_name, self.exit_status, self.checkpoint))


def _positive_int(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise TrainingInputError(f"{name} must be a positive integer, got {value!r}")


def _number(name: str, value: Any, zero_ok: bool) -> None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TrainingInputError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not zero_ok):
        raise TrainingInputError(f"{name} must be {'>= 0' if zero_ok else '> 0'}, got {value!r}")


def check_options(
    *,
    model: str,
    epochs: Any,
    batch_size: Any,
    lr: Any,
    physics_lr: Any,
    weight_decay: Any,
    schedule: str,
    seed: Any,
    device: Any,
    dtype: str,
    max_time: Any,
    keep_checkpoints: Any,
    steps_per_epoch: Any = None,
) -> None:
    """Check the options of ``train()``; ``physics_lr`` ``None`` stands for ``lr``.

    The model's own options (``eps``, ``heterogeneous``, ``hidden``) are checked
    when it is built.

    Raises:
        TrainingInputError: the first bad option, named.
    """
    if model not in model_names():
        raise TrainingInputError(
            f"unknown model {model!r}; registered models: {', '.join(model_names())}"
        )
    try:
        parse_device(device, allow_index=False)
    except ValueError as err:
        raise TrainingInputError(str(err)) from None
    _positive_int("epochs", epochs)
    _positive_int("batch_size", batch_size)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise TrainingInputError(f"seed must be a non-negative integer, got {seed!r}")
    _number("lr", lr, zero_ok=False)
    _number("weight_decay", weight_decay, zero_ok=True)
    if physics_lr is not None:
        _number("physics_lr", physics_lr, zero_ok=False)
    if max_time is not None:
        try:
            mt = float(max_time)
        except (TypeError, ValueError):
            mt = math.nan
        if not mt > 0:
            raise TrainingInputError(f"max_time must be minutes (> 0), got {max_time!r}")
    if dtype not in DTYPE_NAMES:
        raise TrainingInputError(f"dtype must be one of {DTYPE_NAMES}, got {dtype!r}")
    if schedule not in SCHEDULES:
        raise TrainingInputError(f"schedule must be one of {SCHEDULES}, got {schedule!r}")
    if keep_checkpoints is not None:
        _positive_int("keep_checkpoints", keep_checkpoints)
    if steps_per_epoch is not None:
        _positive_int("steps_per_epoch", steps_per_epoch)
