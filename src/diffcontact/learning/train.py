"""Training: a Lightning module around the rollout loss, and ``diffcontact train``.

The loss of a batch of chunks ``(B, L, 2, P, dim)`` (``docs/conventions.md``,
"Learning") is the mean absolute error between the model's rollout from the
first state of each chunk and the chunk's remaining ``L - 1`` states::

    pred = model.simulate(chunk[:, 0], L - 1, check_overlap=False)
    loss = (pred[:, 1:] - chunk[:, 1:]).abs().mean()

optimised with AdamW (lr 1e-3, weight decay 1e-4, batch 200 by default;
paper-facts.md, "Training set-up").

A step whose loss is not finite, whose gradients are not finite, or whose
rollout fails in the contact solver (:class:`~diffcontact.contact.ConeQPError`)
is *skipped*: no parameter or optimiser state changes (manual optimisation:
the optimiser's ``step`` is not called). Skipped steps are counted per reason,
logged (``train/skipped``), reported by one warning per epoch and stored in
``learned.json`` and in the checkpoints.

:func:`train` writes a run directory (``docs/training.md``)::

    run.json            options, data directory, config, seed, versions (first)
    checkpoints/        last.ckpt and epoch0000.ckpt, epoch0001.ckpt, ... (every epoch)
    logs/metrics.csv    Lightning CSVLogger: losses and learned parameters per epoch
    logs/tensorboard/   TensorBoard events, when tensorboard is installed
    learned.json        learned parameters as plain numbers (updated every epoch)
    model.pt            the final model (:func:`~diffcontact.learning.model.load_model`)

:func:`register_cli` adds ``diffcontact train``.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import logging
import math
import os
import time
import warnings
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import numpy as np
import torch
from lightning.fabric.utilities.exceptions import MisconfigurationException
from lightning.pytorch.loggers import CSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter
from lightning.pytorch.utilities import rank_zero_only
from torch import Tensor
from torch.utils.data import DataLoader, Sampler, TensorDataset

from diffcontact import __version__
from diffcontact.contact import ConeQPError, SolverSettings
from diffcontact.io import atomic_write_bytes
from diffcontact.learning.model import FORMAT_VERSION as MODEL_FORMAT_VERSION
from diffcontact.learning.model import LearnedModel, parse_model_name

# the CLI lives in train_cli.py so that building the parser does not import Lightning
from diffcontact.learning.train_cli import (
    DEFAULT_DTYPE,
    DEFAULT_PHYSICS_LR,
    DEFAULT_SCHEDULE,
    register_cli,
)

__all__ = [
    "DEFAULT_DTYPE",
    "DEFAULT_PHYSICS_LR",
    "DEFAULT_SCHEDULE",
    "ChunkDataModule",
    "EpochShuffleSampler",
    "RolloutModule",
    "TrainingInputError",
    "register_cli",
    "rollout_loss",
    "solver_settings_for",
    "train",
]

log = logging.getLogger(__name__)

# chosen from the float32/float64 measurement in docs/training.md: float32 saves ~20% per
# step but its gradients through CM's singular contact problems need a larger KKT
# regularisation (below); float64 gradients match without it
DTYPES = {"float32": torch.float32, "float64": torch.float64}
SKIP_REASONS = ("nonfinite_loss", "nonfinite_grad", "solver_failure", "gradient_spike")
# a step whose gradient norm (per group: network, physical) exceeds SPIKE_FACTOR times the
# median over the last SPIKE_WINDOW accepted steps (once SPIKE_MIN_HISTORY are known) is
# skipped: a near-grazing contact can give one batch a gradient 1e4 times the usual, which
# then dominates Adam's second-moment estimate and freezes the parameter (docs/training.md)
SPIKE_FACTOR = 100.0
SPIKE_WINDOW = 50
SPIKE_MIN_HISTORY = 2
SCHEDULES = ("cosine", "constant")
COSINE_FLOOR = 0.01  # the cosine schedule ends at 1% of each learning rate
# Adam's betas for the physical parameters: beta2 = 0.99 (not 0.999) so that their step
# size follows the gradient scale within ~100 steps: their gradients shrink by orders of
# magnitude once mu and e_P settle, and a run has only a few hundred steps
PHYSICS_BETAS = (0.9, 0.99)
RUN_FILE = "run.json"
# run.json keys that must match to resume a run
_RUN_IDENTITY = (
    "model_format", "model", "eps", "heterogeneous", "hidden", "data_dir", "seed",
    "batch_size", "lr", "weight_decay", "physics_lr", "schedule", "dtype",
)  # fmt: skip


class TrainingInputError(ValueError):
    """Bad input to :func:`train` (data, options, run directory); one-line message."""


# ---------------------------------------------------------------------------- loss


def solver_settings_for(dtype: torch.dtype) -> SolverSettings | None:
    """Contact-solver settings for training in ``dtype``.

    The QP is solved in float64 either way; for float32 inputs the KKT
    regularisation of the implicit backward is raised to 1e-7 (float32's
    default), because with the float64 default (1e-12) float32 rounding of
    ``A`` and ``b`` is amplified in the gradients of singular (CM) contact
    problems, e.g. a point mass in a corner (docs/training.md).
    """
    return SolverSettings(kkt_reg=1e-7) if dtype == torch.float32 else None


def rollout_loss(model: LearnedModel, chunk: Tensor) -> Tensor:
    """MAE between the rollout from ``chunk[:, 0]`` and ``chunk[:, 1:]``.

    Args:
        model: the learned model.
        chunk: ``(B, L, 2, P, dim)`` data chunks (L >= 2).

    Returns:
        ``()``, the mean over all predicted states and coordinates.
    """
    pred = model.simulate(
        chunk[:, 0],
        chunk.shape[1] - 1,
        check_overlap=False,
        solver_settings=solver_settings_for(chunk.dtype),
    )
    return (pred[:, 1:] - chunk[:, 1:]).abs().mean()


def _is_nonfinite_error(err: ValueError) -> bool:
    # System/solve_cone_qp input checks on a rollout that blew up
    return "NaN or infinite" in str(err)


# ---------------------------------------------------------------------------- module


class RolloutModule(pl.LightningModule):
    """Lightning module: a :class:`LearnedModel` trained on the rollout loss.

    Args:
        config: the system config (dict) the model is built from.
        options: :meth:`LearnedModel.options` (model name, eps, heterogeneous, hidden).
        lr: AdamW learning rate of the potential network.
        weight_decay: AdamW weight decay of the potential network.
        physics_lr: AdamW learning rate of the physical parameters (masses,
            second moments, mu, e_P, eps; no weight decay, which would pull them
            towards the parameterisation's zero); ``None``: ``lr``.
        schedule: ``"cosine"``: both learning rates follow a cosine from their
            value down to :data:`COSINE_FLOOR` times it at the last step of
            ``trainer.max_epochs`` (stepped per batch, skipped ones included);
            ``"constant"``: no schedule (the paper's set-up).
        dtype: ``"float32"`` or ``"float64"``: the parameters' and the batches' dtype.
        model: optionally an existing model (e.g. with some parameters frozen by
            ``requires_grad_(False)``); ``config``/``options`` are then taken from it.

    Only parameters with ``requires_grad`` are optimised.
    """

    def __init__(
        self,
        config: Any = None,
        options: dict[str, Any] | None = None,
        lr: float = 1e-3,
        weight_decay: float = 1e-4,
        dtype: str = DEFAULT_DTYPE,
        model: LearnedModel | None = None,
        physics_lr: float | None = None,
        schedule: str = "constant",
    ) -> None:
        super().__init__()
        if model is None:
            if config is None:
                raise ValueError("give a config (and options) or a model")
            model = LearnedModel(config, **(options or {}))
        if dtype not in DTYPES:
            raise ValueError(f"dtype must be one of {tuple(DTYPES)}, got {dtype!r}")
        if schedule not in SCHEDULES:
            raise ValueError(f"schedule must be one of {SCHEDULES}, got {schedule!r}")
        self.save_hyperparameters(
            {
                "config": model.config.model_dump(mode="json"),
                "options": model.options(),
                "lr": float(lr),
                "weight_decay": float(weight_decay),
                "physics_lr": float(lr if physics_lr is None else physics_lr),
                "schedule": schedule,
                "dtype": dtype,
            }
        )
        self.model = model.to(DTYPES[dtype])
        self.automatic_optimization = False
        self.run_dir: Path | None = None  # set by train(): learned.json is written there
        self.skipped_total = dict.fromkeys(SKIP_REASONS, 0)
        # gradient norms of the last accepted steps, per parameter group (spike detection)
        self.grad_norm_history: list[list[float]] = [[], []]
        self._reset_epoch()
        self.last_epoch_summary: dict[str, Any] = {}

    def _reset_epoch(self) -> None:
        self._epoch_skipped = dict.fromkeys(SKIP_REASONS, 0)
        self._epoch_first_error: str | None = None
        self._train_sum = 0.0
        self._train_count = 0
        self._reset_validation()
        self._val_loss = math.nan
        self._epoch_start = time.perf_counter()

    def _reset_validation(self) -> None:
        self._val_sum = 0.0
        self._val_count = 0
        self._val_failed = 0

    # --------------------------------------------------------------- optimisation
    def configure_optimizers(self):
        hp = self.hparams
        physical = [p for p in self.model.physical_parameters() if p.requires_grad]
        chosen = {id(p) for p in physical}
        network = [p for p in self.model.parameters() if p.requires_grad and id(p) not in chosen]
        groups = [
            {"params": network, "lr": hp["lr"], "weight_decay": hp["weight_decay"]},
            {
                "params": physical,
                "lr": hp.get("physics_lr", hp["lr"]),
                "weight_decay": 0.0,
                "betas": PHYSICS_BETAS,
            },
        ]
        optimizer = torch.optim.AdamW([g for g in groups if g["params"]])
        if hp.get("schedule", "constant") == "constant":
            return optimizer
        scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, self._cosine_factor)
        schedule = {"scheduler": scheduler, "interval": "step"}
        return {"optimizer": optimizer, "lr_scheduler": schedule}

    def _cosine_factor(self, step: int) -> float:
        """Learning-rate factor at ``step``: cosine from 1 to COSINE_FLOOR over the run.

        The run's length is read from the trainer on every call, so a run resumed
        with more epochs stretches the rest of its schedule to the new end.
        """
        trainer = self._trainer
        total = trainer.estimated_stepping_batches if trainer is not None else math.inf
        if not math.isfinite(total) or total <= 1:
            return 1.0
        x = min(step / (total - 1), 1.0)
        return COSINE_FLOOR + (1.0 - COSINE_FLOOR) * 0.5 * (1.0 + math.cos(math.pi * x))

    def forward(self, z0: Tensor, steps: int | None = None, **kwargs: Any) -> Tensor:
        return self.model.simulate(z0, steps, **kwargs)

    def _chunk(self, batch: Any) -> Tensor:
        chunk = batch[0] if isinstance(batch, (list, tuple)) else batch
        return chunk.to(DTYPES[self.hparams["dtype"]])

    def _zero_loss(self) -> Tensor:
        """A zero loss on every trainable parameter (DDP needs a backward on every rank)."""
        params = [p for p in self.model.parameters() if p.requires_grad]
        return sum((p.sum() * 0.0 for p in params), torch.zeros((), device=self.device))

    def _grads_finite(self) -> bool:
        flags = [p.grad.isfinite().all() for p in self.model.parameters() if p.grad is not None]
        return bool(torch.stack(flags).all()) if flags else True

    def _group_grad_norms(self) -> list[float]:
        """Gradient norms of the network and the physical parameters (0 when absent)."""
        physical = {id(p) for p in self.model.physical_parameters()}
        sums = [torch.zeros((), dtype=torch.float64, device=self.device) for _ in range(2)]
        for p in self.model.parameters():
            if p.grad is not None:
                k = 1 if id(p) in physical else 0
                sums[k] = sums[k] + p.grad.detach().double().pow(2).sum()
        return [float(x.sqrt()) for x in sums]

    def _spike(self, norms: list[float]) -> str | None:
        """A message when a group's gradient norm is a spike against its recent history."""
        for name, norm, history in zip(
            ("network", "physical"), norms, self.grad_norm_history, strict=True
        ):
            if len(history) < SPIKE_MIN_HISTORY:
                continue
            typical = float(np.median(history))
            if typical > 0 and norm > SPIKE_FACTOR * typical:
                return f"{name} gradient norm {norm:.3g} > {SPIKE_FACTOR:g} x median {typical:.3g}"
        return None

    def _record_norms(self, norms: list[float]) -> None:
        for norm, history in zip(norms, self.grad_norm_history, strict=True):
            if norm > 0:
                history.append(norm)
                del history[:-SPIKE_WINDOW]

    def _step_schedule(self) -> None:
        """Advance the learning-rate schedule by one batch (skipped batches count too)."""
        scheduler = self.lr_schedulers()
        if scheduler is None:
            return
        with warnings.catch_warnings():  # a skipped first batch steps before the optimizer
            warnings.filterwarnings("ignore", message=".*lr_scheduler.step.*before.*optimizer")
            scheduler.step()

    def training_step(self, batch: Any, batch_idx: int) -> None:
        chunk = self._chunk(batch)
        opt = self.optimizers()
        opt.zero_grad(set_to_none=True)
        reason, message, loss = None, None, None
        norms: list[float] = []
        try:
            loss = rollout_loss(self.model, chunk)
            if not bool(torch.isfinite(loss.detach())):
                reason, message = "nonfinite_loss", f"loss {float(loss.detach())}"
        except ConeQPError as err:
            reason, message = "solver_failure", str(err).splitlines()[0]
        except ValueError as err:
            if not _is_nonfinite_error(err):
                raise
            reason, message = "nonfinite_loss", str(err).splitlines()[0]
        distributed = self.trainer.world_size > 1
        if reason is None:
            self.manual_backward(loss)
            if not self._grads_finite():
                reason, message = "nonfinite_grad", "non-finite gradient"
            else:  # gradients are all-reduced by now: every rank sees the same norms
                norms = self._group_grad_norms()
                message = self._spike(norms)
                if message is not None:
                    reason = "gradient_spike"
        elif distributed:  # every rank must take part in the gradient all-reduce
            self.manual_backward(self._zero_loss())
        if distributed:  # skip on every rank when any failed (the replicas stay identical)
            flags = torch.tensor(
                [float(reason == r) for r in SKIP_REASONS], dtype=torch.float64, device=self.device
            )
            counts = self.trainer.strategy.reduce(flags, reduce_op="sum").tolist()
            failed = [r for r, c in zip(SKIP_REASONS, counts, strict=True) if c > 0]
            if failed and reason is None:
                reason, message = failed[0], "on another rank"
        if reason is not None:
            self._step_schedule()
            opt.zero_grad(set_to_none=True)
            self._epoch_skipped[reason] += 1
            self.skipped_total[reason] += 1
            if self._epoch_first_error is None:
                self._epoch_first_error = f"{reason}: {message}"
            return None
        self._record_norms(norms)
        opt.step()
        self._step_schedule()
        value = loss.detach()
        n = chunk.shape[0]
        self._train_sum += float(value) * n
        self._train_count += n
        self.log(
            "train/loss_step", value, on_step=True, on_epoch=False, prog_bar=True, batch_size=n
        )
        return None

    def validation_step(self, batch: Any, batch_idx: int) -> None:
        chunk = self._chunk(batch)
        try:
            loss = rollout_loss(self.model, chunk)
        except ConeQPError:
            self._val_failed += 1
            return None
        except ValueError as err:
            if not _is_nonfinite_error(err):
                raise
            self._val_failed += 1
            return None
        n = chunk.shape[0]
        self._val_sum += float(loss) * n
        self._val_count += n
        return None

    # ------------------------------------------------------------------- epochs
    def on_train_epoch_start(self) -> None:
        self._reset_epoch()

    def _reduce_sum(self, *values: float) -> list[float]:
        t = torch.tensor(values, dtype=torch.float64, device=self.device)
        if self.trainer.world_size > 1:
            t = self.trainer.strategy.reduce(t, reduce_op="sum")
        return t.tolist()

    def on_validation_epoch_start(self) -> None:
        self._reset_validation()

    def on_validation_epoch_end(self) -> None:
        if self.trainer.sanity_checking:
            return
        s, n, failed = self._reduce_sum(self._val_sum, self._val_count, self._val_failed)
        self._val_loss = s / n if n > 0 else math.nan
        self.log("val/loss", self._val_loss, on_epoch=True, prog_bar=True, sync_dist=False)
        if failed and self.trainer.is_global_zero:
            log.warning("validation: %d batch(es) failed (solver failure or non-finite)", failed)

    def on_train_epoch_end(self) -> None:
        epoch = self.current_epoch
        s, n = self._reduce_sum(self._train_sum, self._train_count)
        train_loss = s / n if n > 0 else math.nan
        val_loss = self._val_loss
        skipped_by = dict(self._epoch_skipped)  # the same on every rank
        n_skipped = sum(skipped_by.values())
        params = self.model.learned_parameters()
        self.log("train/loss_epoch", train_loss, on_epoch=True)
        self.log("train/skipped", float(n_skipped), on_epoch=True)
        self.log("time/epoch_s", time.perf_counter() - self._epoch_start, on_epoch=True)
        for name, value in self._param_metrics(params).items():
            self.log(name, value, on_epoch=True)
        if n_skipped and self.trainer.is_global_zero:
            detail = ", ".join(f"{c} {r.replace('_', ' ')}" for r, c in skipped_by.items() if c)
            first = f"; first: {self._epoch_first_error}" if self._epoch_first_error else ""
            log.warning("epoch %d: skipped %d step(s) (%s)%s", epoch, n_skipped, detail, first)
        self.last_epoch_summary = {
            "epoch": epoch,
            "global_step": int(self.global_step),
            "train_loss": train_loss,
            "val_loss": val_loss,
            "skipped_steps": skipped_by,
            "skipped_steps_total": dict(self.skipped_total),
            "learned": params,
        }
        if self.run_dir is not None:
            _write_learned(self.run_dir, self.last_epoch_summary)

    def _param_metrics(self, params: dict[str, Any]) -> dict[str, float]:
        out: dict[str, float] = {"param/mass_0": params["mass"][0]}  # the (free) mass scale
        for i, r in enumerate(params["mass_ratios"][1:], start=1):
            out[f"param/mass_ratio_{i}"] = r
        for key in ("mu", "cor"):
            values = params[key]
            if self.model.heterogeneous:
                for k, v in enumerate(values):
                    out[f"param/{key}_{k}"] = v
            else:
                out[f"param/{key}"] = values[0]
        if params["eps"] is not None and self.model.eps_option == "learnable":
            out["param/eps"] = params["eps"]
        return out

    # -------------------------------------------------------------- checkpoints
    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["diffcontact"] = {
            "skipped_total": dict(self.skipped_total),
            "grad_norm_history": [list(h) for h in self.grad_norm_history],
            "model_format": MODEL_FORMAT_VERSION,
            "version": __version__,
        }

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        extra = checkpoint.get("diffcontact", {})
        self.skipped_total.update(extra.get("skipped_total", {}))
        if "grad_norm_history" in extra:
            self.grad_norm_history = [list(h) for h in extra["grad_norm_history"]]


@rank_zero_only
def _write_learned(run_dir: Path, summary: dict[str, Any]) -> None:
    atomic_write_bytes(run_dir / "learned.json", _json_bytes(summary))


def _json_bytes(data: Any) -> bytes:
    def clean(x: Any) -> Any:
        if isinstance(x, dict):
            return {str(k): clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, float) and not math.isfinite(x):
            return None
        return x

    return (json.dumps(clean(data), indent=2) + "\n").encode()


# ---------------------------------------------------------------------------- data


class EpochShuffleSampler(Sampler[int]):
    """A random permutation per epoch drawn from ``(seed, epoch)`` only.

    Lightning calls :meth:`set_epoch` at the start of every epoch, so a
    resumed run sees exactly the batches an uninterrupted one would.
    """

    def __init__(self, n: int, seed: int = 0) -> None:
        self.n = int(n)
        self.seed = int(seed)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __iter__(self):
        gen = torch.Generator().manual_seed(self.seed * 100_003 + self.epoch)
        return iter(torch.randperm(self.n, generator=gen).tolist())

    def __len__(self) -> int:
        return self.n


def _read_npz_chunks(data_dir: Path, split: str) -> np.ndarray:
    """``chunks`` of ``data_dir/split.npz`` (fallback reader, no checksum)."""
    path = data_dir / f"{split}.npz"
    if not path.is_file():
        raise TrainingInputError(f"dataset {data_dir} has no {split}.npz")
    try:
        with np.load(path, allow_pickle=False) as npz:
            if "chunks" not in npz.files:
                raise TrainingInputError(f"{path} has no 'chunks' array")
            return np.asarray(npz["chunks"], dtype=np.float64)
    except (OSError, ValueError) as err:
        if isinstance(err, TrainingInputError):
            raise
        raise TrainingInputError(f"cannot read {path}: {err}") from None


def read_training_data(data_dir: str | os.PathLike[str]) -> tuple[dict[str, Any], Tensor, Tensor]:
    """``(metadata, train chunks, val chunks)`` of a dataset folder (chunks float64).

    Uses :func:`diffcontact.learning.data.load_dataset` (checksums verified)
    when available.

    Raises:
        TrainingInputError: a missing or malformed dataset.
    """
    folder = Path(data_dir)
    if not folder.is_dir():
        raise TrainingInputError(f"data directory {folder} does not exist")
    try:
        from diffcontact.learning.data import load_dataset
    except ImportError:  # pragma: no cover - data layer not installed
        load_dataset = None
    if load_dataset is not None:
        try:
            ds = load_dataset(folder)
            meta = dict(ds.metadata)
            train = ds.split("train", dtype=torch.float64).chunks
            val = ds.split("val", dtype=torch.float64).chunks
        except ValueError as err:
            raise TrainingInputError(str(err)) from None
    else:  # pragma: no cover
        meta_path = folder / "metadata.json"
        if not meta_path.is_file():
            raise TrainingInputError(f"{folder} has no metadata.json: not a dataset")
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise TrainingInputError(f"cannot read {meta_path}: {err}") from None
        train = torch.from_numpy(_read_npz_chunks(folder, "train"))
        val = torch.from_numpy(_read_npz_chunks(folder, "val"))
    if "config" not in meta:
        raise TrainingInputError(f"{folder}/metadata.json has no config")
    for name, chunks in (("train", train), ("val", val)):
        if chunks.dim() != 5 or chunks.shape[1] < 2 or chunks.shape[0] < 1:
            raise TrainingInputError(
                f"{folder}/{name}.npz: chunks must have shape (N, L, 2, P, dim) with N >= 1 "
                f"and L >= 2, got {tuple(chunks.shape)}"
            )
    return meta, train, val


class ChunkDataModule(pl.LightningDataModule):
    """Train/val chunks of a dataset folder as DataLoaders of ``(B, L, 2, P, dim)`` batches.

    Args:
        train_chunks, val_chunks: ``(N, L, 2, P, dim)`` tensors.
        batch_size: chunks per batch.
        seed: the shuffling seed (:class:`EpochShuffleSampler`).
        dtype: ``"float32"`` or ``"float64"``.
    """

    def __init__(
        self,
        train_chunks: Tensor,
        val_chunks: Tensor,
        batch_size: int = 200,
        seed: int = 0,
        dtype: str = DEFAULT_DTYPE,
    ) -> None:
        super().__init__()
        self.train_set = TensorDataset(train_chunks.to(DTYPES[dtype]))
        self.val_set = TensorDataset(val_chunks.to(DTYPES[dtype]))
        self.batch_size = int(batch_size)
        self.seed = int(seed)

    @classmethod
    def from_dir(cls, data_dir: str | os.PathLike[str], **kwargs: Any) -> ChunkDataModule:
        _, train, val = read_training_data(data_dir)
        return cls(train, val, **kwargs)

    def train_dataloader(self) -> DataLoader:
        sampler = EpochShuffleSampler(len(self.train_set), self.seed)
        return DataLoader(self.train_set, batch_size=self.batch_size, sampler=sampler)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(self.val_set, batch_size=self.batch_size, shuffle=False)


# ------------------------------------------------------------------------ logging


class _AppendingCSVWriter(ExperimentWriter):
    """Lightning's CSV writer, but an existing ``metrics.csv`` is continued, not deleted."""

    def _check_log_dir_exists(self) -> None:
        if self._fs.isfile(self.metrics_file_path):
            with self._fs.open(self.metrics_file_path, "r", newline="") as fh:
                self.metrics_keys = list(next(csv.reader(fh), []))


class _RunCSVLogger(CSVLogger):
    """``CSVLogger`` writing ``RUN_DIR/logs/metrics.csv``; a resumed run appends to it."""

    @property
    def experiment(self):  # type: ignore[override]
        if self._experiment is None:
            self._fs.makedirs(self.root_dir, exist_ok=True)
            self._experiment = _AppendingCSVWriter(log_dir=self.log_dir)
        return self._experiment


def _truncate_csv(path: Path, first_epoch: int) -> None:
    """Drop the rows of epochs >= ``first_epoch`` (an interrupted epoch) from a metrics.csv."""
    if not path.is_file():
        return
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        fields = reader.fieldnames or []
        rows = [r for r in reader if not r.get("epoch") or int(float(r["epoch"])) < first_epoch]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_bytes(path, buf.getvalue().encode())


def _loggers(out: Path) -> list[Any]:
    loggers: list[Any] = [_RunCSVLogger(save_dir=out, name="logs", version="")]
    try:
        import tensorboard  # noqa: F401
    except ImportError:
        pass
    else:
        from lightning.pytorch.loggers import TensorBoardLogger

        loggers.append(TensorBoardLogger(save_dir=out / "logs", name="tensorboard", version=""))
    return loggers


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


class _StopAfter(pl.Callback):
    """Stop at the end of the first epoch that ends after ``seconds`` of this invocation."""

    def __init__(self, seconds: float) -> None:
        self.seconds = float(seconds)
        self.start = time.monotonic()

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self.start = time.monotonic()

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if time.monotonic() - self.start >= self.seconds:
            trainer.should_stop = True


# -------------------------------------------------------------------------- train


def _check_options(
    model: str,
    epochs: Any,
    batch_size: Any,
    lr: Any,
    weight_decay: Any,
    seed: Any,
    device: str,
    eps: Any,
    dtype: str,
    max_time: Any,
    lr_name: str = "lr",
) -> float | str | None:
    try:
        contact, _ = parse_model_name(model)
    except ValueError as err:
        raise TrainingInputError(str(err)) from None

    def positive_int(name: str, value: Any) -> None:
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise TrainingInputError(f"{name} must be a positive integer, got {value!r}")

    positive_int("epochs", epochs)
    positive_int("batch_size", batch_size)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise TrainingInputError(f"seed must be a non-negative integer, got {seed!r}")
    for name, value, low_ok in ((lr_name, lr, False), ("weight_decay", weight_decay, True)):
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise TrainingInputError(f"{name} must be a number, got {value!r}") from None
        if not math.isfinite(v) or v < 0 or (v == 0 and not low_ok):
            raise TrainingInputError(f"{name} must be {'>= 0' if low_ok else '> 0'}, got {value!r}")
    if max_time is not None:
        try:
            mt = float(max_time)
        except (TypeError, ValueError):
            raise TrainingInputError(f"max_time must be minutes (> 0), got {max_time!r}") from None
        if not mt > 0:
            raise TrainingInputError(f"max_time must be minutes (> 0), got {max_time!r}")
    if dtype not in DTYPES:
        raise TrainingInputError(f"dtype must be one of {tuple(DTYPES)}, got {dtype!r}")
    if device not in ("cpu", "cuda"):
        raise TrainingInputError(f"device must be 'cpu' or 'cuda', got {device!r}")
    if device == "cuda" and not torch.cuda.is_available():
        raise TrainingInputError("device 'cuda' requested but CUDA is not available (use cpu)")
    if contact == "CM":
        return None
    if eps == "learnable":
        return "learnable"
    try:
        value = float(eps)
    except (TypeError, ValueError):
        raise TrainingInputError(
            f"eps must be a positive number or 'learnable', got {eps!r}"
        ) from None
    if not (value > 0 and math.isfinite(value)):
        raise TrainingInputError(f"eps must be a positive number or 'learnable', got {eps!r}")
    return value


def _differences(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    return [
        f"{k}: {old.get(k)!r} -> {new.get(k)!r}" for k in _RUN_IDENTITY if old.get(k) != new.get(k)
    ]


def _launcher_rank() -> int:
    """This process's rank as set by a distributed launcher (0 when not launched as one)."""
    for key in ("RANK", "SLURM_PROCID", "LOCAL_RANK", "NODE_RANK", "JSM_NAMESPACE_RANK"):
        value = os.environ.get(key, "0")
        if value.isdigit() and int(value) > 0:
            return int(value)
    return 0


def _check_run_dir(out: Path, run_info: dict[str, Any], resume: bool) -> dict[str, Any]:
    """Check ``out`` against the new run; return the ``run.json`` to write (rank 0 only)."""
    run_file = out / RUN_FILE
    if not resume:
        if run_file.exists() or (out / "checkpoints" / "last.ckpt").exists():
            raise TrainingInputError(
                f"{out} already holds a run; pass --resume to continue it or choose another --out"
            )
        if out.exists() and not out.is_dir():
            raise TrainingInputError(f"--out {out} exists and is not a directory")
        return run_info
    if not run_file.is_file():
        return run_info
    try:
        old = json.loads(run_file.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise TrainingInputError(f"cannot read {run_file}: {err}") from None
    diff = _differences(old, run_info)
    if diff:
        raise TrainingInputError(
            f"{out} holds a different run ({'; '.join(diff)}); use another --out"
        )
    info = dict(old)
    info["epochs"] = run_info["epochs"]
    info["resumed"] = [*info.get("resumed", []), run_info["created"]]
    return info


def _write_run_file(out: Path, info: dict[str, Any]) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(out / RUN_FILE, _json_bytes(info))
    except OSError as err:
        raise TrainingInputError(f"cannot write to {out}: {err}") from None


def train(
    data_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    model: str = "CM-CD-CLNN",
    epochs: int = 100,
    batch_size: int = 200,
    lr: float = 1e-3,
    weight_decay: float = 1e-4,
    physics_lr: float | None = DEFAULT_PHYSICS_LR,
    schedule: str = DEFAULT_SCHEDULE,
    seed: int = 0,
    device: str = "cpu",
    eps: float | str = 0.01,
    heterogeneous: bool | None = None,
    hidden: Sequence[int] = (256, 256, 256),
    dtype: str = DEFAULT_DTYPE,
    resume: bool = False,
    progress: bool = True,
    max_time: float | None = None,
    strategy: Any = "auto",
    devices: Any = 1,
    num_nodes: int = 1,
    keep_checkpoints: int | None = None,
    callbacks: Sequence[pl.Callback] = (),
) -> LearnedModel:
    """Train a learned model on a dataset folder and write a run directory.

    Args:
        data_dir: a dataset (``diffcontact generate``; ``docs/conventions.md``).
        out_dir: the run directory (created).
        model: one of ``CM-CD-CLNN``, ``CM-CD-CHNN``, ``CMr-CD-CLNN``, ``CMr-CD-CHNN``.
        epochs: total number of epochs (a resumed run continues up to it).
        batch_size, lr, weight_decay: batching, and AdamW for the potential network.
        physics_lr: AdamW learning rate of the physical parameters (masses,
            second moments, mu, e_P, eps; no weight decay); ``None``: ``lr``.
        schedule: ``"cosine"`` (both learning rates decay to 1% over ``epochs``)
            or ``"constant"``.
        seed: seeds the model initialisation and the per-epoch shuffling.
        device: ``"cpu"`` or ``"cuda"``.
        eps: CMr's regulariser (a positive number or ``"learnable"``).
        heterogeneous: one mu/e_P per contact; ``None``: from the task (BP5, BD5).
        hidden: hidden widths of the potential MLP.
        dtype: ``"float64"`` (default, see docs/training.md) or ``"float32"``.
        resume: continue from ``out_dir/checkpoints/last.ckpt`` (the run's
            options must be the same; ``epochs`` may grow).
        progress: show Lightning's progress bar and model summary.
        max_time: minutes; stop at the end of the first epoch that ends after
            this much time of this invocation (checkpoint and files written).
        strategy, devices, num_nodes: passed to ``lightning.Trainer`` (e.g.
            ``strategy="ddp", devices=4``; ``"ddp"`` is run with
            ``find_unused_parameters=True``, see docs/training.md).
        keep_checkpoints: keep only the newest this many per-epoch checkpoints
            (``None``: all; ``last.ckpt`` is always written).
        callbacks: extra Lightning callbacks.

    Returns:
        The trained model (on the CPU).

    Raises:
        TrainingInputError (a ``ValueError``): missing/malformed data, unknown
            model, bad options, CUDA unavailable, ``resume`` without a
            checkpoint, or ``out_dir`` holding a different run.
    """
    eps_value = _check_options(
        model, epochs, batch_size, lr, weight_decay, seed, device, eps, dtype, max_time
    )
    physics_lr = lr if physics_lr is None else physics_lr
    _check_options(model, 1, 1, physics_lr, 0.0, 0, device, eps, dtype, None, lr_name="physics_lr")
    if schedule not in SCHEDULES:
        raise TrainingInputError(f"schedule must be one of {SCHEDULES}, got {schedule!r}")
    if keep_checkpoints is not None and (
        isinstance(keep_checkpoints, bool)
        or not isinstance(keep_checkpoints, int)
        or keep_checkpoints < 1
    ):
        raise TrainingInputError(
            f"keep_checkpoints must be a positive integer or None, got {keep_checkpoints!r}"
        )
    data_path = Path(data_dir).resolve()
    out = Path(out_dir)
    meta, train_chunks, val_chunks = read_training_data(data_path)
    try:
        learned = LearnedModel(
            meta["config"], model=model, eps=eps_value, heterogeneous=heterogeneous, hidden=hidden
        )
    except ValueError as err:
        raise TrainingInputError(str(err)) from None
    if tuple(train_chunks.shape[2:]) != learned.state_shape:
        raise TrainingInputError(
            f"{data_path}: chunks hold states {tuple(train_chunks.shape[2:])}, the config's "
            f"system has {learned.state_shape}"
        )

    run_info = {
        "format_version": 1,
        "model_format": MODEL_FORMAT_VERSION,
        "model": model,
        "eps": eps_value,
        "heterogeneous": learned.heterogeneous,
        "hidden": list(learned.hidden),
        "data_dir": str(data_path),
        "task": meta.get("task"),
        "config": meta["config"],
        "seed": int(seed),
        "epochs": int(epochs),
        "batch_size": int(batch_size),
        "lr": float(lr),
        "weight_decay": float(weight_decay),
        "physics_lr": float(physics_lr),
        "schedule": schedule,
        "dtype": dtype,
        "device": device,
        "loss": "mean absolute error of the rolled-out chunk (states 1..L-1)",
        "optimizer": "AdamW",
        "versions": {
            "diffcontact": __version__,
            "torch": torch.__version__,
            "lightning": pl.__version__,
        },
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    last_ckpt = out / "checkpoints" / "last.ckpt"
    if resume and not last_ckpt.is_file():
        raise TrainingInputError(f"cannot resume: {last_ckpt} does not exist")
    # processes started by a DDP launcher (Lightning's, torchrun, SLURM) leave the files to rank 0
    launcher = _launcher_rank() == 0
    info = _check_run_dir(out, run_info, resume) if launcher else None

    pl.seed_everything(seed, workers=True, verbose=False)
    # the model is built again after seeding so that its initialisation depends on the seed only
    learned = LearnedModel(
        meta["config"], model=model, eps=eps_value, heterogeneous=heterogeneous, hidden=hidden
    )
    module = RolloutModule(
        model=learned,
        lr=lr,
        weight_decay=weight_decay,
        dtype=dtype,
        physics_lr=physics_lr,
        schedule=schedule,
    )
    module.run_dir = out
    datamodule = ChunkDataModule(
        train_chunks, val_chunks, batch_size=batch_size, seed=seed, dtype=dtype
    )
    ckpt_path = str(last_ckpt) if resume else None

    from lightning.pytorch.callbacks import ModelCheckpoint

    keep = {} if keep_checkpoints is None else {"monitor": "step", "mode": "max"}
    checkpoint = ModelCheckpoint(
        dirpath=out / "checkpoints",
        filename="epoch{epoch:04d}",
        auto_insert_metric_name=False,
        save_top_k=-1 if keep_checkpoints is None else keep_checkpoints,
        **keep,
        every_n_epochs=1,
        save_last=True,
        save_on_train_epoch_end=True,
        enable_version_counter=False,
    )
    all_callbacks: list[pl.Callback] = [checkpoint, *callbacks]
    if max_time is not None:
        all_callbacks.append(_StopAfter(float(max_time) * 60.0))
    if strategy == "ddp":
        strategy = "ddp_find_unused_parameters_true"
    with _lightning_messages(progress):
        try:
            trainer = pl.Trainer(
                max_epochs=epochs,
                accelerator="gpu" if device == "cuda" else "cpu",
                devices=devices,
                num_nodes=num_nodes,
                strategy=strategy,
                precision="64-true" if dtype == "float64" else "32-true",
                logger=_loggers(out),
                callbacks=all_callbacks,
                enable_progress_bar=progress,
                enable_model_summary=progress,
                inference_mode=False,  # the dynamics take grad V by autograd, also in validation
                num_sanity_val_steps=0,
                log_every_n_steps=1,
                default_root_dir=out,
            )
        except (MisconfigurationException, ValueError, TypeError) as err:
            raise TrainingInputError(f"bad strategy/devices/num_nodes: {err}") from None
        if info is not None:  # nothing is written before all checks have passed
            _write_run_file(out, info)
            if resume:  # drop the log rows of the interrupted epoch
                done = torch.load(last_ckpt, map_location="cpu", weights_only=False)["epoch"]
                _truncate_csv(out / "logs" / "metrics.csv", int(done) + 1)
        return _fit(trainer, module, datamodule, out, ckpt_path)


def _fit(
    trainer: pl.Trainer,
    module: RolloutModule,
    datamodule: ChunkDataModule,
    out: Path,
    ckpt_path: str | None,
) -> LearnedModel:
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*does not have many workers.*")
        warnings.filterwarnings("ignore", message=".*smaller than the logging interval.*")
        warnings.filterwarnings("ignore", message=".*is not a valid metric.*")
        warnings.filterwarnings("ignore", message=".*treespec, LeafSpec.*")  # lightning internals
        warnings.filterwarnings("ignore", message="Checkpoint directory .* is not empty")
        # epoch values are reduced across ranks by the module itself (or identical on all)
        warnings.filterwarnings("ignore", message=".*recommended to use `self.log.*sync_dist")
        trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt_path)

    trained = module.model.cpu()
    if trainer.is_global_zero:
        summary = dict(module.last_epoch_summary)
        if not summary and (out / "learned.json").is_file():  # resumed a finished run
            with contextlib.suppress(OSError, json.JSONDecodeError):
                summary = json.loads((out / "learned.json").read_text())
        summary["learned"] = trained.learned_parameters()
        summary["finished"] = True
        summary["epochs_done"] = int(trainer.current_epoch)
        trained.save(out / "model.pt")
        _write_learned(out, summary)
    return trained


# ---------------------------------------------------------------------------- CLI
