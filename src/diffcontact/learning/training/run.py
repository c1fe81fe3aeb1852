"""``train()``: a training run in a run directory, resumable (``docs/training.md``).

:func:`train` writes a run directory::

    run.json            options, data directory, seed, versions (first); the system
                        config is the dataset's and is stored in the model files only
    checkpoints/        last.ckpt and epoch0000.ckpt, epoch0001.ckpt, ... (every epoch)
    logs/metrics.csv    Lightning CSVLogger: losses and learned parameters per epoch
    logs/tensorboard/   TensorBoard events, when tensorboard is installed
    learned.json        learned parameters as plain numbers (updated every epoch)
    model.pt            the final model (:func:`~diffcontact.learning.models.load_model`)
    refit.json          with ``refit``: the Gauss-Newton refit's report; model_adam.pt is
                        then the model before it

The data come from :func:`~diffcontact.learning.data.load_dataset` (checksums
verified) as a :class:`ChunkDataModule`, shuffled per epoch by
:class:`EpochShuffleSampler`; the model is trained by
:class:`~diffcontact.learning.training.module.RolloutModule`. What may be
written where is decided in :mod:`~diffcontact.learning.training.rundir`;
checkpoints are written and read by
:mod:`~diffcontact.learning.training.checkpoints` (atomically; never running
code); SIGINT/SIGTERM and ``max_time`` stop a run through
:mod:`~diffcontact.learning.training.stopping`.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import math
import os
import signal
import sys
import warnings
from collections.abc import Callable, Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch
from lightning.fabric.utilities.exceptions import MisconfigurationException
from torch import Tensor
from torch.utils.data import DataLoader, DistributedSampler, Sampler, TensorDataset

from diffcontact import __version__
from diffcontact.io import jsonable
from diffcontact.learning.data.format import METADATA_CHECKSUM, load_dataset, metadata_checksum
from diffcontact.learning.models.physical import FORMAT_VERSION as MODEL_FORMAT_VERSION
from diffcontact.learning.models.registry import (
    BASELINE_MODELS,
    create_model,
    is_physical_model,
)
from diffcontact.learning.models.storage import save_model
from diffcontact.learning.training.checkpoints import (
    LAST,
    EpochCheckpoint,
    SafeCheckpointIO,
    prune_checkpoints,
    resume_point,
)
from diffcontact.learning.training.governor import thread_callback
from diffcontact.learning.training.module import DTYPES, RolloutModule, write_learned
from diffcontact.learning.training.options import (
    COSINE_FLOOR,
    DEFAULT_BATCH_SIZE,
    DEFAULT_DEVICE,
    DEFAULT_DTYPE,
    DEFAULT_EPOCHS,
    DEFAULT_EPS,
    DEFAULT_HIDDEN,
    DEFAULT_LR,
    DEFAULT_MODEL,
    DEFAULT_PHYSICS_LR,
    DEFAULT_SCHEDULE,
    DEFAULT_SEED,
    DEFAULT_WEIGHT_DECAY,
    TrainingFailed,
    TrainingInputError,
    TrainingInterrupted,
    check_options,
)
from diffcontact.learning.training.rundir import (
    RunLock,
    check_run_dir,
    clear_for_restart,
    loggers,
    remove_temporaries,
    truncate_log,
    write_run_file,
)
from diffcontact.learning.training.stopping import (
    GracefulStop,
    ResumedStepCount,
    StopAfter,
    Stopped,
)
from diffcontact.systems.config import stored_config
from diffcontact.threads import parse_threads

__all__ = [
    "ChunkDataModule",
    "EpochShuffleSampler",
    "contact_weights",
    "read_training_data",
    "train",
]

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------- data


class EpochShuffleSampler(Sampler[int]):
    """Indices per epoch drawn from ``(seed, epoch)`` only, split across ranks.

    By default one random permutation of the ``n`` items per epoch. With
    ``draws`` (the number of indices per epoch, all ranks together) and no
    ``weights``, consecutive permutations are drawn and cut to ``draws``
    (the first one is the default's); with ``weights`` (``(n,)``, not
    necessarily normalised), ``draws`` indices are drawn with replacement in
    proportion to them.

    Lightning calls :meth:`set_epoch` at the start of every epoch, so a
    resumed run sees exactly the batches an uninterrupted one would. With
    ``world_size > 1`` (DDP) rank ``r`` takes the drawn elements
    ``r, r + W, ...``, after padding them to a multiple of ``W`` with their own
    first elements (what ``torch.utils.data.DistributedSampler`` does to a
    sampler's indices). ``skip=(epoch, k)`` leaves out this rank's first ``k``
    indices in that epoch: where a run stopped in the middle of it resumes.
    """

    def __init__(
        self,
        n: int,
        seed: int = 0,
        *,
        rank: int = 0,
        world_size: int = 1,
        skip: tuple[int, int] = (-1, 0),
        draws: int | None = None,
        weights: Tensor | None = None,
    ) -> None:
        self.n = int(n)
        self.seed = int(seed)
        self.epoch = 0
        self.rank, self.world_size = int(rank), int(world_size)
        self.skip = (int(skip[0]), int(skip[1]))
        self.draws = self.n if draws is None else int(draws)
        if weights is not None:
            weights = torch.as_tensor(weights, dtype=torch.float64)
            if weights.shape != (self.n,) or not (weights >= 0).all() or weights.sum() <= 0:
                raise ValueError(f"weights must be {self.n} non-negative numbers, not all zero")
        self.weights = weights
        self.num_samples = math.ceil(self.draws / self.world_size)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def _draw(self, gen: torch.Generator) -> list[int]:
        if self.weights is not None:
            return torch.multinomial(self.weights, self.draws, True, generator=gen).tolist()
        order: list[int] = []
        while len(order) < self.draws:
            order += torch.randperm(self.n, generator=gen).tolist()
        return order[: self.draws]

    def __iter__(self):
        gen = torch.Generator().manual_seed(self.seed * 100_003 + self.epoch)
        order = self._draw(gen)
        if self.world_size > 1:
            total = self.num_samples * self.world_size
            pad = total - len(order)
            order = (order + (order * math.ceil(pad / max(len(order), 1)))[:pad])[
                self.rank : total : self.world_size
            ]
        if self.epoch == self.skip[0]:
            order = order[self.skip[1] :]
        return iter(order)

    def __len__(self) -> int:
        return self.num_samples


def read_training_data(data_dir: str | os.PathLike[str]) -> tuple[dict[str, Any], Tensor, Tensor]:
    """``(metadata, train chunks, val chunks)`` of a dataset folder (chunks float64).

    Read with :func:`~diffcontact.learning.data.load_dataset` (checksums verified).

    Raises:
        TrainingInputError: a missing or malformed dataset, or a split without chunks.
    """
    meta, train, val, _ = _read_data(data_dir)
    return meta, train, val


def contact_weights(has_contact: Tensor, contact_fraction: float) -> Tensor | None:
    """Sampling weights ``(M,)`` under which a draw contains a contact with probability
    ``contact_fraction``: ``f / M_c`` for each of the ``M_c`` chunks with a contact,
    ``(1 - f) / M_f`` for the others; ``None`` (uniform) when either kind is missing.
    """
    has = torch.as_tensor(has_contact, dtype=torch.bool)
    n_c = int(has.sum())
    n_f = len(has) - n_c
    if n_c == 0 or n_f == 0:
        return None
    f = float(contact_fraction)
    return torch.where(has, f / n_c, (1.0 - f) / n_f).to(torch.float64)


def _read_data(data_dir: str | os.PathLike[str]) -> tuple[dict[str, Any], Tensor, Tensor, Tensor]:
    """``read_training_data`` and the training chunks' contact flags ``(M,)``."""
    folder = Path(data_dir)
    try:
        ds = load_dataset(folder)
        split = ds.split("train", dtype=torch.float64)
        train, has_contact = split.chunks, split.chunk_has_contact
        val_split = ds.split("val", dtype=torch.float64)
        val = val_split.chunks
    except ValueError as err:
        raise TrainingInputError(str(err)) from None
    for name, chunks, n_traj in (("train", train, len(split)), ("val", val, len(val_split))):
        if chunks.shape[0] == 0 and n_traj > 0:  # (a dataset of an earlier version)
            raise TrainingInputError(
                f"{folder}: its {name} split holds {n_traj} trajectories but no chunk: every "
                f"state where its stride ({ds.stride}) lets a chunk start is flagged in contact;"
                " generate the dataset again with a smaller --stride (1: every window)"
            )
        if chunks.shape[0] == 0:
            raise TrainingInputError(
                f"{folder}: its validation split is empty, and training reports the "
                "validation loss every epoch: generate the dataset with a --val-fraction "
                "(or --n-val) above 0"
                if name == "val"
                else f"{folder}: its train split is empty: nothing to train on"
            )
        if chunks.shape[1] < 2:
            raise TrainingInputError(
                f"{folder}/{name}.npz: chunks must have shape (N, L, 2, P, dim) with N >= 1 "
                f"and L >= 2, got {tuple(chunks.shape)}"
            )
    bad = int((~torch.isfinite(train.flatten(1)).all(1)).sum())
    if bad == len(train):
        raise TrainingInputError(
            f"{folder}/train.npz: every training chunk ({bad}) contains NaN or infinite "
            "values: there is nothing to train on"
        )
    if bad:
        log.warning(
            "%s/train.npz: %d of %d training chunks contain NaN or infinite values; no "
            "step is taken on a batch that holds one",
            folder, bad, len(train),
        )  # fmt: skip
    return dict(ds.metadata), train, val, has_contact


class ChunkDataModule(pl.LightningDataModule):
    """Train/val chunks as DataLoaders of ``(B, L, 2, P, dim)`` batches.

    Args:
        train_chunks, val_chunks: ``(N, L, 2, P, dim)`` tensors.
        batch_size: chunks per batch.
        seed: the shuffling seed (:class:`EpochShuffleSampler`).
        dtype: ``"float32"`` or ``"float64"``.
        resume_at: ``(epoch, batches)``: a run resumed in the middle of
            ``epoch`` leaves out the batches it has done (default: none).
        steps_per_epoch: optimiser steps per epoch (per rank); ``None``: one
            pass over the training chunks (``ceil(M / batch_size)``), or,
            with ``weights``, ``ceil(ceil(n_reference / ranks) / batch_size)``.
        weights: ``(M,)`` sampling weights of the training chunks (drawn with
            replacement; :func:`contact_weights`); ``None``: shuffled passes.
        n_reference: the item count of an epoch with ``weights`` and no
            ``steps_per_epoch`` (the training trajectories: as many steps as
            one chunk per trajectory would take).

    The samplers split the data across ranks themselves (the Trainer runs
    with ``use_distributed_sampler=False``).
    """

    def __init__(
        self,
        train_chunks: Tensor,
        val_chunks: Tensor,
        batch_size: int = DEFAULT_BATCH_SIZE,
        seed: int = DEFAULT_SEED,
        dtype: str = DEFAULT_DTYPE,
        resume_at: tuple[int, int] = (-1, 0),
        steps_per_epoch: int | None = None,
        weights: Tensor | None = None,
        n_reference: int | None = None,
    ) -> None:
        super().__init__()
        self.train_set = TensorDataset(train_chunks.to(DTYPES[dtype]))
        self.val_set = TensorDataset(val_chunks.to(DTYPES[dtype]))
        self.batch_size = int(batch_size)
        self.seed = int(seed)
        self.resume_at = resume_at
        self.steps_per_epoch = steps_per_epoch
        self.weights = weights
        self.n_reference = len(self.train_set) if n_reference is None else int(n_reference)

    def draws(self, world: int = 1) -> int | None:
        """Indices drawn per epoch over all ranks; ``None``: one permutation of the chunks."""
        steps = self.steps_per_epoch
        if steps is None and self.weights is None:
            return None
        if steps is None:
            steps = math.ceil(math.ceil(self.n_reference / world) / self.batch_size)
        return int(steps) * self.batch_size * world

    def _ranks(self) -> tuple[int, int]:
        trainer = getattr(self, "trainer", None)
        return (trainer.global_rank, trainer.world_size) if trainer is not None else (0, 1)

    def train_dataloader(self) -> DataLoader:
        rank, world = self._ranks()
        epoch, batches = self.resume_at
        sampler = EpochShuffleSampler(
            len(self.train_set), self.seed, rank=rank, world_size=world,
            skip=(epoch, batches * self.batch_size), draws=self.draws(world),
            weights=self.weights,
        )  # fmt: skip
        return DataLoader(self.train_set, batch_size=self.batch_size, sampler=sampler)

    def val_dataloader(self) -> DataLoader:
        rank, world = self._ranks()
        if world == 1:
            return DataLoader(self.val_set, batch_size=self.batch_size, shuffle=False)
        sampler = DistributedSampler(self.val_set, num_replicas=world, rank=rank, shuffle=False)
        return DataLoader(self.val_set, batch_size=self.batch_size, sampler=sampler)


# ------------------------------------------------------------------------ logging


class _DropTips(logging.Filter):
    """Drop Lightning's advertising tips and its note on estimating the schedule's length."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        return "Tip:" not in message and "to estimate number of stepping batches" not in message


@contextlib.contextmanager
def _lightning_messages(progress: bool):
    """Lightning's info lines only with ``progress`` (never its advertising tips)."""
    names = ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero")
    loggers = [logging.getLogger(n) for n in names]
    levels = [lg.level for lg in loggers]
    tips = _DropTips()
    for lg in loggers:
        lg.addFilter(tips)
        if not progress:
            lg.setLevel(logging.WARNING)
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels, strict=True):
            lg.removeFilter(tips)
            lg.setLevel(level)


# ----------------------------------------------------------------- run directory


def _one_process(devices: Any, num_nodes: Any) -> bool:
    """Whether a run with ``devices`` and ``num_nodes`` is one process (no launcher ranks:
    this process is rank 0 whatever the environment says)."""
    one = (isinstance(devices, int) and not isinstance(devices, bool) and devices == 1) or (
        isinstance(devices, (list, tuple)) and len(devices) == 1
    )
    return one and num_nodes == 1


def _launcher_rank() -> int:
    """This process's rank as set by a distributed launcher (0 when not launched as one)."""
    for key in ("RANK", "SLURM_PROCID", "LOCAL_RANK", "NODE_RANK", "JSM_NAMESPACE_RANK"):
        value = os.environ.get(key, "0")
        if value.isdigit() and int(value) > 0:
            return int(value)
    return 0


# -------------------------------------------------------------------------- train


def _holding_run_lock(fit: Callable[..., Any]) -> Callable[..., Any]:
    """``train`` holding the run directory's :class:`RunLock` (rank 0 takes it, in
    ``train``) until the call ends, however it ends."""

    @functools.wraps(fit)
    def locked(data_dir: str | os.PathLike[str], out_dir: str | os.PathLike[str], **kwargs):
        lock = RunLock(Path(out_dir))
        try:
            return fit(data_dir, out_dir, _lock=lock, **kwargs)
        finally:
            lock.release()

    return locked


@_holding_run_lock
def train(
    data_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    _lock: RunLock | None = None,
    model: str = DEFAULT_MODEL,
    epochs: int = DEFAULT_EPOCHS,
    batch_size: int = DEFAULT_BATCH_SIZE,
    lr: float = DEFAULT_LR,
    weight_decay: float = DEFAULT_WEIGHT_DECAY,
    physics_lr: float | None = DEFAULT_PHYSICS_LR,
    schedule: str = DEFAULT_SCHEDULE,
    seed: int = DEFAULT_SEED,
    device: str = DEFAULT_DEVICE,
    eps: float | str | None = None,
    heterogeneous: bool | None = None,
    hidden: Sequence[int] | None = None,
    model_options: Mapping[str, Any] | None = None,
    dtype: str = DEFAULT_DTYPE,
    resume: bool = False,
    progress: bool = True,
    max_time: float | None = None,
    strategy: Any = "auto",
    devices: Any = 1,
    num_nodes: int = 1,
    keep_checkpoints: int | None = None,
    callbacks: Sequence[pl.Callback] = (),
    steps_per_epoch: int | None = None,
    threads: int | str | None = "auto",
    refit: int = 0,
) -> Any:
    """Train a learned model on a dataset folder and write a run directory.

    Args:
        data_dir: a dataset (``diffcontact generate``; ``docs/conventions.md``).
        out_dir: the run directory (created).
        model: a registered model name (``diffcontact.learning.model_names()``):
            ``CM-CD-CLNN``, ``CM-CD-CHNN``, ``CMr-CD-CLNN``, ``CMr-CD-CHNN``, the
            baselines ``MLP-CD-CLNN``, ``IN-CP-CLNN``, ``IN-SP-CP`` or one added with
            :func:`~diffcontact.learning.register_model`.
        epochs: total number of epochs (a resumed run continues up to it).
        batch_size, lr, weight_decay: batching, and AdamW for the potential network.
        physics_lr: AdamW learning rate of the physical parameters (masses,
            second moments, mu, e_P, eps; no weight decay); ``None``: ``lr``.
        schedule: ``"cosine"`` (both learning rates decay to zero over ``epochs``)
            or ``"constant"``.
        seed: seeds the model initialisation and the per-epoch shuffling.
        device: ``"cpu"`` or ``"cuda"``.
        eps: CMr's regulariser (a positive number or ``"learnable"``; default 0.01).
        heterogeneous: one mu/e_P per contact; ``None``: the config's
            ``contact_parameters`` key.
        hidden: hidden widths of the potential MLP (default 256, 256, 256); the
            baselines' ``hidden`` option (the potential MLP's, or IN-SP-CP's network's).
        model_options: further options of the model's factory (for a
            registered model, all of them; ``eps`` and ``heterogeneous`` are
            options of the physical models only, ``hidden`` of the physical
            models and the baselines).
        dtype: ``"float64"`` (default, see docs/training.md) or ``"float32"``.
        resume: continue the run in ``out_dir`` from ``checkpoints/last.ckpt``
            (else from the newest readable per-epoch checkpoint; the run's
            options must be the same; ``epochs`` may grow). A run with no
            usable checkpoint (stopped before its first epoch ended), or an
            empty or new ``out_dir``, starts from the beginning, with a warning.
        progress: show Lightning's progress bar and model summary; without
            it, print one line per epoch (losses, learned physical parameters).
        max_time: minutes; stop at the end of the first epoch that ends after
            this much time of this invocation (checkpoint and files written;
            a warning says that the learning-rate schedule was cut).
        strategy, devices, num_nodes: passed to ``lightning.Trainer`` (e.g.
            ``strategy="ddp", devices=4``; ``"ddp"`` is run with
            ``find_unused_parameters=True``, see docs/training.md).
        keep_checkpoints: keep only the newest this many per-epoch checkpoints
            (``None``: all; ``last.ckpt`` is always written).
        callbacks: extra Lightning callbacks.
        steps_per_epoch: optimiser steps per epoch, so that the schedule does
            not change with the amount of data. ``None``: for a dataset of one
            chunk per trajectory, one shuffled pass (``ceil(N / batch_size)``
            steps, the paper's set-up); for a dataset of windows (metadata
            ``stride``), as many steps as one chunk per training trajectory
            would take, the windows drawn with replacement, weighted so that
            a draw contains a contact with probability ``contact_fraction``
            (:func:`contact_weights`; uniform when one kind is missing).
        threads: torch's CPU threads during the run (put back afterwards).
            ``"auto"`` (default): a :class:`~diffcontact.threads.ThreadGovernor`
            times the steps and uses 1 thread or ``min(available cores,
            torch.get_num_threads())``, whichever is faster now (several
            threads are faster on an idle CPU, far slower on a loaded one;
            docs/training.md, "CPU threads"); an integer fixes the count;
            ``None`` leaves torch's setting alone.
        refit: after the last epoch, this many Gauss-Newton iterations on the potential
            network's output layer and the free physical parameters
            (:func:`~diffcontact.learning.training.refit.refit_run`: ``model_adam.pt``
            keeps the model before, ``refit.json`` the report; docs/training.md,
            "Refit"); physical models only. 0 (default): none.

    Returns:
        The trained model (on the CPU).

    Raises:
        TrainingInputError (a ``ValueError``): missing/malformed data (a
            training set with no finite chunk included), unknown model, bad
            options, CUDA unavailable, an ``out_dir`` that is not empty and
            holds no run of ours, holds a symbolic link, holds a run (without
            ``resume``) or a different run, holds a folder where the run writes
            a file (``checkpoints/last.ckpt``, ...), or a checkpoint that would
            need more than tensors and plain data to load.
        TrainingInterrupted (a ``KeyboardInterrupt``): SIGINT or SIGTERM
            stopped the run after the running step; a checkpoint was written
            (``resume=True`` continues). A second SIGINT stops it at once, without
            a checkpoint (its ``checkpoint`` is ``None``; ``resume=True`` continues
            from the last one written). A signal after the last training step
            stops nothing: the run ends (``model.pt`` written, a ``refit`` not
            run) and a line on stderr says so.
    """
    check_options(
        model=model, epochs=epochs, batch_size=batch_size, lr=lr, physics_lr=physics_lr,
        weight_decay=weight_decay, schedule=schedule, seed=seed, device=device, dtype=dtype,
        max_time=max_time, keep_checkpoints=keep_checkpoints, steps_per_epoch=steps_per_epoch,
    )  # fmt: skip
    if not isinstance(refit, int) or isinstance(refit, bool) or refit < 0:
        raise TrainingInputError(f"refit must be a non-negative integer, got {refit!r}")
    if refit and not is_physical_model(model):
        raise TrainingInputError(
            f"refit: {model} has no potential network to refit (physical models only)"
        )
    bad = [c for c in callbacks if not isinstance(c, pl.Callback)]
    if bad:  # (Lightning's AttributeError "'int' object has no attribute 'on_exception'")
        raise TrainingInputError(
            f"callbacks must be Lightning callbacks (lightning.pytorch.Callback), got "
            f"{', '.join(repr(c) for c in bad[:3])}"
        )
    try:
        threads = parse_threads(threads)
    except ValueError as err:
        raise TrainingInputError(str(err)) from None
    physics_lr = lr if physics_lr is None else physics_lr
    data_path = Path(data_dir).resolve()
    out = Path(out_dir)
    meta, train_chunks, val_chunks, has_contact = _read_data(data_path)
    windows = meta.get("stride") is not None
    weights = contact_weights(has_contact, meta.get("contact_fraction", 0.5)) if windows else None
    if windows and weights is None:
        weights = torch.ones(len(train_chunks), dtype=torch.float64)
    # seeded first, so that the model's initialisation depends on the seed only
    pl.seed_everything(seed, workers=True, verbose=False)
    options = dict(model_options or {})
    physical = {"eps": eps, "heterogeneous": heterogeneous, "hidden": hidden}
    twice = [k for k, v in physical.items() if v is not None and k in options]
    if twice:  # (model_options won silently)
        raise TrainingInputError(f"{', '.join(twice)} given twice (as such and in model_options)")
    if is_physical_model(model):
        if (eps is not None or "eps" in options) and not model.startswith("CMr-"):
            raise TrainingInputError(
                f"eps is the regulariser of the CMr models; {model} has none (leave eps unset)"
            )
        defaults = {"eps": DEFAULT_EPS, "heterogeneous": None, "hidden": DEFAULT_HIDDEN}
        options = {k: defaults[k] if v is None else v for k, v in physical.items()} | options
    elif model in BASELINE_MODELS:
        wrong = [k for k in ("eps", "heterogeneous") if physical[k] is not None]
        if wrong:
            raise TrainingInputError(
                f"{', '.join(wrong)}: option(s) of the physical models only; {model} takes "
                "hidden and model_options"
            )
        if hidden is not None:  # the baselines' "hidden" option, as for the physical models
            options["hidden"] = list(hidden)
    elif any(v is not None for v in physical.values()):
        given = ", ".join(k for k, v in physical.items() if v is not None)
        raise TrainingInputError(
            f"{given}: option(s) of the built-in models only; {model} takes model_options"
        )
    try:
        learned = create_model(model, stored_config(meta["config"]), **options)
    except ValueError as err:
        raise TrainingInputError(str(err)) from None
    if not isinstance(learned, torch.nn.Module):
        raise TrainingInputError(
            f"model {model!r}: its factory returned {type(learned).__name__}, not a "
            "torch.nn.Module (docs/architecture.md)"
        )
    if not any(p.requires_grad for p in learned.parameters()):  # (torch's empty-list error)
        raise TrainingInputError(f"model {model!r} has no trainable parameters")
    if tuple(train_chunks.shape[2:]) != learned.state_shape:
        raise TrainingInputError(
            f"{data_path}: chunks hold states {tuple(train_chunks.shape[2:])}, the config's "
            f"system has {learned.state_shape}"
        )

    run_info = {
        "format_version": 1,
        "model_format": MODEL_FORMAT_VERSION,
        "model": model,
        "options": jsonable(learned.options()),
        "data_dir": str(data_path),
        # the data's identity (metadata.json's checksum covers every file's): a resume
        # checks it, so data replaced at the same path are refused and moved data are not
        "data_checksum": meta.get(METADATA_CHECKSUM) or metadata_checksum(meta),
        "task": meta.get("task"),
        "seed": int(seed),
        "epochs": int(epochs),
        "batch_size": int(batch_size),
        "lr": float(lr),
        "weight_decay": float(weight_decay),
        "physics_lr": float(physics_lr),
        "schedule": schedule,
        "dtype": dtype,
        "device": str(device),
        **({} if steps_per_epoch is None else {"steps_per_epoch": int(steps_per_epoch)}),
        **({"sampling": "windows weighted by contact_fraction"} if windows else {}),
        "loss": "mean absolute error of the rolled-out chunk (states 1..L-1)",
        "optimizer": "AdamW",
        "versions": {
            "diffcontact": __version__,
            "torch": torch.__version__,
            "lightning": pl.__version__,
        },
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    checkpoints = out / "checkpoints"
    # processes started by a DDP launcher (Lightning's, torchrun, SLURM) leave the files to rank
    # 0; a run of one process checks and writes them whatever rank variable the environment
    # holds (SLURM_PROCID of a task of a multi-task job, LOCAL_RANK left by a launcher had
    # turned off every check: a finished run's model.pt was overwritten)
    launcher = _launcher_rank() == 0 or _one_process(devices, num_nodes)
    if launcher and _lock is not None:
        _lock.acquire()  # an existing folder: before any check reads it
    info = check_run_dir(out, run_info, resume) if launcher else None
    point = resume_point(checkpoints) if resume else None
    if point is not None and point.path is not None and epochs < point.epoch + 1:
        reached = "was in epoch" if point.mid_epoch else "has trained"
        raise TrainingInputError(
            f"cannot resume with --epochs {epochs}: {out} {reached} {point.epoch + 1} (its "
            f"last checkpoint), and a resumed run trains up to --epochs; pass --epochs "
            f"{point.epoch + 1} or more"
        )
    if launcher and point is not None and point.path is None and (out / "model.pt").is_file():
        raise TrainingInputError(
            f"cannot resume: {out} holds a finished model.pt but no checkpoint to continue "
            "from; choose another --out to train again"
        )
    if (
        point is not None
        and point.path is not None
        and not point.mid_epoch
        and epochs == point.epoch + 1
        and (out / "model.pt").is_file()
    ):  # (a resume that trains removes model.pt first: this one is the last checkpoint's;
        # every rank returns here, so that none waits in a fit the others do not start)
        if launcher:
            log.warning(
                "nothing to train: %s has trained its %d epochs; model.pt (and a refit of "
                "it) kept as it is (pass a larger --epochs to train on)", out, epochs,
            )  # fmt: skip
        from diffcontact.learning.models.storage import load_model

        if refit and launcher:
            from diffcontact.learning.training.refit import refit_run

            refit_run(out, refit, data_dir=data_path)
        return load_model(out)

    module = RolloutModule(
        model=learned,
        lr=lr,
        weight_decay=weight_decay,
        dtype=dtype,
        physics_lr=physics_lr,
        schedule=schedule,
    )
    module.run_dir = out
    if point is not None and point.path is not None:
        _check_checkpoint_model(module, point)
    module.report_epochs = not progress
    resume_at = (point.epoch, point.batches_in_epoch) if point and point.mid_epoch else (-1, 0)
    datamodule = ChunkDataModule(
        train_chunks, val_chunks, batch_size=batch_size, seed=seed, dtype=dtype,
        resume_at=resume_at, steps_per_epoch=steps_per_epoch, weights=weights,
        n_reference=int(meta.get("n_train", len(train_chunks))),
    )  # fmt: skip

    keep = {} if keep_checkpoints is None else {"monitor": "step", "mode": "max"}
    checkpoint = EpochCheckpoint(
        dirpath=checkpoints,
        filename="epoch{epoch:04d}",
        auto_insert_metric_name=False,
        save_top_k=-1 if keep_checkpoints is None else keep_checkpoints,
        **keep,
        every_n_epochs=1,
        save_last=True,
        save_on_train_epoch_end=True,
        enable_version_counter=False,
    )
    stop = GracefulStop(checkpoints / LAST, announce=launcher)
    stop_after = None if max_time is None else StopAfter(float(max_time) * 60.0)
    governor = thread_callback(threads, device)
    all_callbacks = [checkpoint, stop, *callbacks, *([stop_after] if stop_after else [])]
    if point is not None and point.path is not None and point.mid_epoch:
        all_callbacks.append(ResumedStepCount(point.batches_stepped))
    all_callbacks += [governor] if governor is not None else []
    if strategy == "ddp":
        strategy = "ddp_find_unused_parameters_true"
    with _lightning_messages(progress):
        try:
            trainer = pl.Trainer(
                max_epochs=epochs,
                accelerator="gpu" if torch.device(device).type == "cuda" else "cpu",
                devices=devices,
                num_nodes=num_nodes,
                strategy=strategy,
                precision="64-true" if dtype == "float64" else "32-true",
                logger=loggers(out),
                callbacks=all_callbacks,
                plugins=[SafeCheckpointIO()],
                enable_progress_bar=progress,
                enable_model_summary=progress,
                inference_mode=False,  # the dynamics take grad V by autograd, also in validation
                num_sanity_val_steps=0,
                log_every_n_steps=1,
                default_root_dir=out,
                use_distributed_sampler=False,  # ChunkDataModule splits the data across ranks
            )
        except (MisconfigurationException, ValueError, TypeError) as err:
            raise TrainingInputError(f"bad strategy/devices/num_nodes: {err}") from None
        if launcher:  # nothing is written before all checks have passed
            _prepare(out, info or run_info, point)
            if _lock is not None:
                _lock.acquire()  # a new folder, now made (no-op where held)
        ckpt_path = None if point is None or point.path is None else str(point.path)
        stop.install()
        try:
            trained = _fit(
                trainer, module, datamodule, out, ckpt_path, stop, stop_after, keep_checkpoints
            )
        finally:
            stop.restore()
    # a signal after the last training step (in the last validation): nothing was left to
    # stop, and the run ended as it would have; its announcement said otherwise
    late_stop = stop.received is not None and trainer.is_global_zero
    if late_stop:
        _ended_after_signal(stop, out, refit, stop_after is not None and stop_after.triggered)
    if refit and trainer.is_global_zero and not late_stop:
        from diffcontact.learning.models.storage import load_model
        from diffcontact.learning.training.refit import refit_run

        refit_run(out, refit, data_dir=data_path)  # prints a line per iteration
        trained = load_model(out)
    return trained


def _check_checkpoint_model(module: RolloutModule, point: Any) -> None:
    """Refuse, before anything is written, a checkpoint whose weights are not this run's
    model's (one copied from another run): Lightning would fail on it only after
    ``run.json`` and the log had been rewritten."""
    mine = {k: tuple(x.shape) for k, x in module.state_dict().items()}
    if point.shapes == mine:
        return
    differ = sorted(set(mine) ^ set(point.shapes))
    differ += [k for k in mine if k in point.shapes and mine[k] != point.shapes[k]]
    names = ", ".join(differ[:3]) + (", ..." if len(differ) > 3 else "")
    raise TrainingInputError(
        f"cannot resume from {point.path}: it holds another model's weights ({names} "
        "differ from this run's model): a checkpoint "
        "copied from another run? Move it away to resume from the run's own checkpoints"
    )


def _prepare(out: Path, info: dict[str, Any], point: Any) -> None:
    """Write ``run.json`` and tidy the run directory for a new, restarted or resumed run."""
    write_run_file(out, info)
    remove_temporaries(out)
    if point is None:
        return
    for note in point.notes:
        log.warning("%s", note)
    if point.path is None:
        if "resumed" in info:
            log.warning(
                "%s has no usable checkpoint (the run stopped before its first epoch ended): "
                "starting it again from the beginning", out,
            )  # fmt: skip
            clear_for_restart(out)
        else:
            log.warning("nothing to resume in %s (no run yet): starting a new run", out)
        return
    if point.notes:
        log.warning("resuming %s from %s", out, point.path)
    # the run goes on: a model.pt of an earlier stop (--max-time, a finished run trained
    # further) is older than the checkpoint; until the run ends, evaluate uses the checkpoint
    if (out / "model.pt").is_file():
        log.warning(
            "%s: removed model.pt of the run's earlier stop (it goes on from %s; evaluate "
            "uses the last checkpoint until the run ends)", out, point.path.name,
        )  # fmt: skip
    for stale in ("model.pt", "refit.json", "model_adam.pt"):
        (out / stale).unlink(missing_ok=True)
    # the log keeps the rows written before the checkpoint (an interrupted epoch's are redone)
    if point.mid_epoch:
        truncate_log(out, point.epoch, point.batches_stepped)
    else:
        truncate_log(out, point.epoch + 1, 0)


def _fit(
    trainer: pl.Trainer,
    module: RolloutModule,
    datamodule: ChunkDataModule,
    out: Path,
    ckpt_path: str | None,
    stop: GracefulStop,
    stop_after: StopAfter | None,
    keep_checkpoints: int | None = None,
) -> Any:
    with warnings.catch_warnings():
        # a resume with another --keep-checkpoints, or of a moved run folder: Lightning's
        # checkpoint callback starts afresh (prune_checkpoints keeps the newest at the end)
        warnings.filterwarnings("ignore", message="Be aware that when using `ckpt_path`")
        warnings.filterwarnings("ignore", message="The dirpath has changed from")
        warnings.filterwarnings("ignore", message=".*does not have many workers.*")
        warnings.filterwarnings("ignore", message=".*smaller than the logging interval.*")
        warnings.filterwarnings("ignore", message=".*is not a valid metric.*")
        warnings.filterwarnings("ignore", message=".*treespec, LeafSpec.*")  # lightning internals
        warnings.filterwarnings("ignore", message="Checkpoint directory .* is not empty")
        # a mid-epoch checkpoint: ChunkDataModule leaves out the batches done (resume_at)
        warnings.filterwarnings("ignore", message=".*your dataloader is not resumable.*")
        # epoch values are reduced across ranks by the module itself (or identical on all)
        warnings.filterwarnings("ignore", message=".*recommended to use `self.log.*sync_dist")
        try:
            trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt_path, weights_only=True)
        except Stopped:
            raise _interrupted(trainer, stop) from None
        except (SystemExit, KeyboardInterrupt) as exc:
            # a second Ctrl-C: Lightning shuts down and exits with status 1 (SystemExit)
            if not stop.at_once or isinstance(exc, TrainingInterrupted):
                raise
            raise _interrupted_at_once(trainer, stop) from None

    trained = module.model.cpu()
    if trainer.is_global_zero and keep_checkpoints is not None:
        prune_checkpoints(out / "checkpoints", keep_checkpoints)
    if trainer.is_global_zero:
        summary = dict(module.last_epoch_summary)
        if not summary and (out / "learned.json").is_file():  # resumed a finished run
            with contextlib.suppress(OSError, json.JSONDecodeError):
                summary = json.loads((out / "learned.json").read_text())
        learned = getattr(trained, "learned_parameters", None)
        summary["learned"] = learned() if callable(learned) else trained.metrics()
        summary["finished"] = True
        summary["epochs_done"] = int(trainer.current_epoch)
        if stop_after is not None and stop_after.triggered:
            summary["stopped_early"] = _schedule_cut(trainer, stop_after)
        save_model(trained, out / "model.pt")
        write_learned(out, summary)
        for stale in ("refit.json", "model_adam.pt"):  # of an earlier model.pt
            (out / stale).unlink(missing_ok=True)
        skipped = {r: c for r, c in module.skipped_total.items() if c}
        last = module.last_epoch_summary  # (empty: this call trained no epoch)
        if (
            last
            and int(trainer.global_step) > 0
            and not any(
                isinstance(last.get(k), (int, float)) and math.isfinite(last[k])
                for k in ("train_loss", "val_loss")
            )
        ):  # (a run that blew up ended "finished" with NaN losses and no error)
            raise TrainingFailed(
                f"training diverged: the last epoch's training and validation losses are not "
                f"finite (epoch {int(last['epoch']) + 1}; {sum(skipped.values())} steps "
                f"skipped in all), so {out / 'model.pt'} holds a model that predicts no "
                "finite motion: lower --lr or --physics-lr, or check the data "
                "(docs/training.md, 'Skipped steps')"
            )
        if skipped and int(trainer.global_step) == 0:
            reasons = ", ".join(f"{c} {r.replace('_', ' ')}" for r, c in skipped.items())
            raise TrainingFailed(
                f"no optimiser step was taken: all {sum(skipped.values())} steps were skipped "
                f"({reasons}; the warnings above name each epoch's first), so {out / 'model.pt'} "
                "holds the untrained model: check the data for NaN chunks (docs/training.md, "
                "'Skipped steps')"
            )
    return trained


def _interrupted(trainer: pl.Trainer, stop: GracefulStop) -> TrainingInterrupted:
    epoch, batch = stop.stopped_at or (trainer.current_epoch, 0)
    n = trainer.num_training_batches
    message = (
        f"{stop.signal_name} received: stopped before step {batch + 1} of {n} in epoch "
        f"{epoch + 1}; wrote {stop.checkpoint}; continue with --resume"
    )
    return TrainingInterrupted(message, stop.signal_name, stop.exit_status, stop.checkpoint)


def _ended_after_signal(stop: GracefulStop, out: Path, refit: int, cut: bool) -> None:
    """Say that a signal received after the last step stopped nothing: the run ended and
    wrote ``model.pt`` (a refit, which takes a while, is left to ``diffcontact refit``).
    ``cut``: ``max_time`` ended the run (its warning says how to finish it)."""
    if not stop.announce:
        return
    ended = "ended at --max-time (see above)" if cut else "ended normally"
    left = "" if cut else " (nothing to resume)"
    later = (
        f"; the refit was not run (diffcontact refit {out} --iterations {refit} runs it)"
        if refit
        else ""
    )
    print(
        f"diffcontact train: {stop.signal_name} was received after the last training step, "
        f"so nothing was left to stop: the run {ended} and wrote {out / 'model.pt'}"
        f"{left}{later}",
        file=sys.stderr,
        flush=True,
    )


def _interrupted_at_once(trainer: pl.Trainer, stop: GracefulStop) -> TrainingInterrupted:
    """A second Ctrl-C stopped the run at once: no checkpoint was written."""
    last = stop.checkpoint
    resume = (
        f"continue with --resume (from {last}, the last checkpoint written)"
        if last.is_file()
        else "no checkpoint was written yet: --resume starts the run again"
    )
    message = (
        f"SIGINT received twice: stopped at once in epoch {trainer.current_epoch + 1}, "
        f"without a checkpoint; {resume}"
    )
    return TrainingInterrupted(message, "SIGINT", 128 + int(signal.SIGINT), None)


def _schedule_cut(trainer: pl.Trainer, stop_after: StopAfter) -> dict[str, Any]:
    """Warn that ``max_time`` ended the run early; what ``learned.json`` records about it."""
    done, total = int(trainer.current_epoch), int(trainer.max_epochs or 0)
    group = trainer.optimizers[0].param_groups[0] if trainer.optimizers else {}
    factor = group.get("lr", 1.0) / group.get("initial_lr", group.get("lr", 1.0))
    cosine = bool(trainer.lr_scheduler_configs)
    record = {"reason": "max_time", "epochs_done": done, "epochs": total, "lr_factor": factor}
    schedule = (
        f"; the cosine learning-rate schedule was cut: the rates are at {factor:.0%} of their "
        f"initial values, not the final {COSINE_FLOOR:.0%}, so the parameters have not "
        "settled"
        if cosine
        else ""
    )
    log.warning(
        "--max-time %.4g min: stopped after epoch %d of %d%s; continue with --resume to finish "
        "the run", stop_after.seconds / 60, done, total, schedule,
    )  # fmt: skip
    return record
