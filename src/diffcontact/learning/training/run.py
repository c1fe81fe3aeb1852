"""``train()``: a training run in a run directory, resumable (``docs/training.md``).

:func:`train` writes a run directory::

    run.json            options, data directory, seed, versions (first); the system
                        config is the dataset's and is stored in the model files only
    checkpoints/        last.ckpt and epoch0000.ckpt, epoch0001.ckpt, ... (every epoch)
    logs/metrics.csv    Lightning CSVLogger: losses and learned parameters per epoch
    logs/tensorboard/   TensorBoard events, when tensorboard is installed
    learned.json        learned parameters as plain numbers (updated every epoch)
    model.pt            the final model (:func:`~diffcontact.learning.models.load_model`)

The data come from :func:`~diffcontact.learning.data.load_dataset` (checksums
verified) as a :class:`ChunkDataModule`, shuffled per epoch by
:class:`EpochShuffleSampler`; the model is trained by
:class:`~diffcontact.learning.training.module.RolloutModule`.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import logging
import os
import time
import warnings
from collections.abc import Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch
from lightning.fabric.utilities.exceptions import MisconfigurationException
from lightning.pytorch.loggers import CSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter
from torch import Tensor
from torch.utils.data import DataLoader, Sampler, TensorDataset

from diffcontact import __version__
from diffcontact.io import atomic_write_bytes, atomic_write_json, jsonable, read_json_object
from diffcontact.learning.data.format import load_dataset
from diffcontact.learning.models.physical import FORMAT_VERSION as MODEL_FORMAT_VERSION
from diffcontact.learning.models.registry import create_model, is_physical_model
from diffcontact.learning.models.storage import save_model
from diffcontact.learning.training.module import DTYPES, RolloutModule, write_learned
from diffcontact.learning.training.options import (
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
    TrainingInputError,
    check_options,
)

__all__ = [
    "ChunkDataModule",
    "EpochShuffleSampler",
    "read_training_data",
    "train",
]

RUN_FILE = "run.json"
# run.json keys that must match to resume a run
_RUN_IDENTITY = (
    "model_format", "model", "options", "data_dir", "seed",
    "batch_size", "lr", "weight_decay", "physics_lr", "schedule", "dtype",
)  # fmt: skip


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


def read_training_data(data_dir: str | os.PathLike[str]) -> tuple[dict[str, Any], Tensor, Tensor]:
    """``(metadata, train chunks, val chunks)`` of a dataset folder (chunks float64).

    Read with :func:`~diffcontact.learning.data.load_dataset` (checksums verified).

    Raises:
        TrainingInputError: a missing or malformed dataset, or a split without chunks.
    """
    folder = Path(data_dir)
    try:
        ds = load_dataset(folder)
        train = ds.split("train", dtype=torch.float64).chunks
        val = ds.split("val", dtype=torch.float64).chunks
    except ValueError as err:
        raise TrainingInputError(str(err)) from None
    for name, chunks in (("train", train), ("val", val)):
        if chunks.shape[1] < 2 or chunks.shape[0] < 1:
            raise TrainingInputError(
                f"{folder}/{name}.npz: chunks must have shape (N, L, 2, P, dim) with N >= 1 "
                f"and L >= 2, got {tuple(chunks.shape)}"
            )
    return dict(ds.metadata), train, val


class ChunkDataModule(pl.LightningDataModule):
    """Train/val chunks as DataLoaders of ``(B, L, 2, P, dim)`` batches.

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
        batch_size: int = DEFAULT_BATCH_SIZE,
        seed: int = DEFAULT_SEED,
        dtype: str = DEFAULT_DTYPE,
    ) -> None:
        super().__init__()
        self.train_set = TensorDataset(train_chunks.to(DTYPES[dtype]))
        self.val_set = TensorDataset(val_chunks.to(DTYPES[dtype]))
        self.batch_size = int(batch_size)
        self.seed = int(seed)

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


# ----------------------------------------------------------------- run directory


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
    old = read_json_object(run_file, "run file", TrainingInputError)
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
        atomic_write_json(out / RUN_FILE, info)
    except OSError as err:
        raise TrainingInputError(f"cannot write to {out}: {err}") from None


# -------------------------------------------------------------------------- train


def train(
    data_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
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
) -> Any:
    """Train a learned model on a dataset folder and write a run directory.

    Args:
        data_dir: a dataset (``diffcontact generate``; ``docs/conventions.md``).
        out_dir: the run directory (created).
        model: a registered model name (``diffcontact.learning.model_names()``):
            ``CM-CD-CLNN``, ``CM-CD-CHNN``, ``CMr-CD-CLNN``, ``CMr-CD-CHNN`` or one
            added with :func:`~diffcontact.learning.register_model`.
        epochs: total number of epochs (a resumed run continues up to it).
        batch_size, lr, weight_decay: batching, and AdamW for the potential network.
        physics_lr: AdamW learning rate of the physical parameters (masses,
            second moments, mu, e_P, eps; no weight decay); ``None``: ``lr``.
        schedule: ``"cosine"`` (both learning rates decay to 1% over ``epochs``)
            or ``"constant"``.
        seed: seeds the model initialisation and the per-epoch shuffling.
        device: ``"cpu"`` or ``"cuda"``.
        eps: CMr's regulariser (a positive number or ``"learnable"``; default 0.01).
        heterogeneous: one mu/e_P per contact; ``None``: the config's
            ``contact_parameters`` key.
        hidden: hidden widths of the potential MLP (default 256, 256, 256).
        model_options: further options of the model's factory (for a
            registered model, all of them; ``eps``, ``heterogeneous`` and
            ``hidden`` are options of the physical models only).
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
    check_options(
        model=model, epochs=epochs, batch_size=batch_size, lr=lr, physics_lr=physics_lr,
        weight_decay=weight_decay, schedule=schedule, seed=seed, device=device, dtype=dtype,
        max_time=max_time, keep_checkpoints=keep_checkpoints,
    )  # fmt: skip
    physics_lr = lr if physics_lr is None else physics_lr
    data_path = Path(data_dir).resolve()
    out = Path(out_dir)
    meta, train_chunks, val_chunks = read_training_data(data_path)
    # seeded first, so that the model's initialisation depends on the seed only
    pl.seed_everything(seed, workers=True, verbose=False)
    options = dict(model_options or {})
    physical = {"eps": eps, "heterogeneous": heterogeneous, "hidden": hidden}
    if is_physical_model(model):
        defaults = {"eps": DEFAULT_EPS, "heterogeneous": None, "hidden": DEFAULT_HIDDEN}
        options = {k: defaults[k] if v is None else v for k, v in physical.items()} | options
    elif any(v is not None for v in physical.values()):
        given = ", ".join(k for k, v in physical.items() if v is not None)
        raise TrainingInputError(
            f"{given}: option(s) of the physical models only; {model} takes model_options"
        )
    try:
        learned = create_model(model, meta["config"], **options)
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
        "options": jsonable(learned.options()),
        "data_dir": str(data_path),
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
                accelerator="gpu" if torch.device(device).type == "cuda" else "cpu",
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
) -> Any:
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
        learned = getattr(trained, "learned_parameters", None)
        summary["learned"] = learned() if callable(learned) else trained.metrics()
        summary["finished"] = True
        summary["epochs_done"] = int(trainer.current_epoch)
        save_model(trained, out / "model.pt")
        write_learned(out, summary)
    return trained
