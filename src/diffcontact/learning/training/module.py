"""The Lightning module: a learned model trained on the rollout loss.

The loss of a batch of chunks ``(B, L, 2, P, dim)`` (``docs/conventions.md``,
"Learning") is the mean absolute error between the model's rollout from the
first state of each chunk and the chunk's remaining ``L - 1`` states::

    pred = model.simulate(chunk[:, 0], L - 1, check_overlap=False)
    loss = (pred[:, 1:] - chunk[:, 1:]).abs().mean()

optimised with AdamW: the potential network with ``lr`` and weight decay, the
physical parameters with ``physics_lr`` and none (defaults in
:mod:`~diffcontact.learning.training.options`; paper-facts.md, "Training set-up").

A step whose loss is not finite, whose gradients are not finite, whose
rollout fails in the contact solver (:class:`~diffcontact.contact.ConeQPError`)
or whose gradient norm is a spike against the recent ones is *skipped*: no
parameter or optimiser state changes (manual optimisation: the optimiser's
``step`` is not called). Skipped steps are counted per reason, logged
(``train/skipped``), reported by one warning per epoch and stored in
``learned.json`` and in the checkpoints.

The checkpoints also hold the running epoch's partial sums (``epoch_state``),
so a run resumed from a checkpoint written in the middle of an epoch (after
SIGINT/SIGTERM) reports the same epoch loss as an uninterrupted one. With
``report_epochs`` the module prints one line per epoch (:func:`epoch_line`).
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import numpy as np
import torch
from lightning.pytorch.utilities import rank_zero_only
from torch import Tensor

from diffcontact import __version__
from diffcontact.contact import ConeQPError, SolverSettings
from diffcontact.io import atomic_write_json
from diffcontact.learning.models.physical import FORMAT_VERSION as MODEL_FORMAT_VERSION
from diffcontact.learning.models.protocol import DynamicsModel, OptimizerSettings
from diffcontact.learning.models.registry import create_model
from diffcontact.learning.models.storage import model_spec
from diffcontact.learning.training.options import (
    COSINE_FLOOR,
    DEFAULT_DTYPE,
    DEFAULT_LR,
    DEFAULT_MODEL,
    DEFAULT_PHYSICS_LR,
    DEFAULT_SCHEDULE,
    DEFAULT_WEIGHT_DECAY,
    SCHEDULES,
)

__all__ = [
    "DTYPES",
    "SKIP_REASONS",
    "SPIKE_FACTOR",
    "RolloutModule",
    "epoch_line",
    "rollout_loss",
    "solver_settings_for",
    "write_learned",
]

log = logging.getLogger(__name__)

DTYPES = {"float32": torch.float32, "float64": torch.float64}
SKIP_REASONS = ("nonfinite_loss", "nonfinite_grad", "solver_failure", "gradient_spike")
# a step whose gradient norm (per group: network, physical) exceeds SPIKE_FACTOR times the
# SPIKE_QUANTILE quantile of the norms of the last SPIKE_WINDOW steps (once
# SPIKE_MIN_HISTORY are known) is skipped: a near-grazing contact can give one batch a
# gradient 1e4 times the usual, which then dominates Adam's second-moment estimate and
# freezes the parameter (docs/training.md). The skipped steps' norms count too, and the
# quantile is a high one: a batch whose gradient stays large (its contacts, once the other
# batches' gradients have shrunk) sets it once such norms are a tenth of the window, and
# is trained on again instead of being left out for good (a median over the accepted
# steps did that on small training sets); a rare spike stays above it
SPIKE_FACTOR = 100.0
SPIKE_QUANTILE = 0.9
SPIKE_WINDOW = 50
SPIKE_MIN_HISTORY = 2


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


def rollout_loss(model: DynamicsModel, chunk: Tensor) -> Tensor:
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


def counted_rollout_loss(model: DynamicsModel, chunk: Tensor) -> tuple[Tensor, str | None]:
    """:func:`rollout_loss`, with its :class:`~diffcontact.systems.RolloutWarning` (bodies
    tunnelled, constraints drifted) caught: ``(loss, the first such warning's message or
    None)``. Other warnings pass on.

    A learned contact model lets bodies pass through each other until it has learned to
    stop them: one warning per batch flooded the log, so the module counts them and
    reports one line per epoch.
    """
    from diffcontact.systems.system import TUNNELLING_HINT, RolloutWarning

    caught: list[warnings.WarningMessage] = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", RolloutWarning)
            loss = rollout_loss(model, chunk)
    finally:
        for w in caught:  # (the filters in force decide, as for any warning)
            if not issubclass(w.category, RolloutWarning):
                warnings.warn_explicit(
                    w.message, w.category, w.filename, w.lineno, registry=_REEMITTED
                )
    mine = [str(w.message) for w in caught if issubclass(w.category, RolloutWarning)]
    # (the hint names simulate's option, which train does not take)
    return loss, (mine[0].removesuffix(TUNNELLING_HINT) if mine else None)


_REEMITTED: dict[Any, Any] = {}  # warn_explicit's registry for the warnings passed on


def _is_nonfinite_error(err: ValueError) -> bool:
    """A rollout that blew up: ``System.simulate``'s :class:`NonFiniteRolloutError` (NaN,
    infinite or beyond ``BLOW_UP``), or an input check of the solver that met one."""
    from diffcontact.systems import NonFiniteRolloutError

    return isinstance(err, NonFiniteRolloutError) or "NaN or infinite" in str(err)


# ---------------------------------------------------------------------------- module


class RolloutModule(pl.LightningModule):
    """Lightning module: a learned model (:class:`DynamicsModel`) trained on the rollout loss.

    The model says how its parameters are grouped for the optimiser
    (``param_groups``) and what to log every epoch (``metrics``); nothing here
    knows about masses, mu or e_P.

    Args:
        config: the system config (dict) the model is built from.
        options: the model's ``options()`` (its factory's keyword arguments).
        model_name: the registered name of the model built from ``config``/``options``.
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
            ``requires_grad_(False)``); ``config``/``options``/``model_name`` are
            then taken from it.

    Only parameters with ``requires_grad`` are optimised. The defaults are
    ``train()``'s (:mod:`~diffcontact.learning.training.options`).
    """

    def __init__(
        self,
        config: Any = None,
        options: dict[str, Any] | None = None,
        lr: float = DEFAULT_LR,
        weight_decay: float = DEFAULT_WEIGHT_DECAY,
        dtype: str = DEFAULT_DTYPE,
        model: DynamicsModel | None = None,
        physics_lr: float | None = DEFAULT_PHYSICS_LR,
        schedule: str = DEFAULT_SCHEDULE,
        model_name: str = DEFAULT_MODEL,
    ) -> None:
        super().__init__()
        if model is None:
            if config is None:
                raise ValueError("give a config (and options) or a model")
            options = dict(options or {})
            model = create_model(options.pop("model", model_name), config, **options)
        if dtype not in DTYPES:
            raise ValueError(f"dtype must be one of {tuple(DTYPES)}, got {dtype!r}")
        if schedule not in SCHEDULES:
            raise ValueError(f"schedule must be one of {SCHEDULES}, got {schedule!r}")
        self.save_hyperparameters(
            {
                **model_spec(model),
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
        self.report_epochs = False  # set by train(progress=False): one line per epoch on stdout
        self._resumed_epoch: dict[str, Any] | None = None  # a mid-epoch checkpoint's sums
        self.skipped_total = dict.fromkeys(SKIP_REASONS, 0)
        # gradient norms of the last steps, skipped spikes included, per parameter group
        self.group_names = [g["name"] for g in model.param_groups(self._optimizer_settings())]
        self.grad_norm_history: list[list[float]] = [[] for _ in self.group_names]
        self._reset_epoch()
        self.last_epoch_summary: dict[str, Any] = {}

    def _reset_epoch(self) -> None:
        self._epoch_batches = 0
        self._epoch_skipped = dict.fromkeys(SKIP_REASONS, 0)
        self._epoch_first_error: str | None = None
        # batches whose rollouts warned (tunnelling, constraint drift)
        self._warned = {"train": 0, "val": 0}
        self._warned_first: str | None = None
        self._train_sum = 0.0
        self._train_count = 0
        self._reset_validation()
        self._val_loss = math.nan
        self._epoch_start = time.perf_counter()

    def _reset_validation(self) -> None:
        self._val_sum = 0.0
        self._val_count = 0
        self._val_failed = 0
        self._warned["val"] = 0

    # --------------------------------------------------------------- optimisation
    def _optimizer_settings(self) -> OptimizerSettings:
        hp = self.hparams  # checkpoints of older versions lack physics_lr and schedule
        return OptimizerSettings(
            lr=hp["lr"], weight_decay=hp["weight_decay"], physics_lr=hp.get("physics_lr", hp["lr"])
        )

    def configure_optimizers(self):
        hp = self.hparams
        groups = self.model.param_groups(self._optimizer_settings())
        optimizer = torch.optim.AdamW([g for g in groups if list(g["params"])])
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
        """Gradient norm of each of the model's parameter groups (0 when it has none)."""
        groups = self.model.param_groups(self._optimizer_settings())
        norms = []
        for group in groups:
            total = torch.zeros((), dtype=torch.float64, device=self.device)
            for p in group["params"]:
                if p.grad is not None:
                    total = total + p.grad.detach().double().pow(2).sum()
            norms.append(total)
        return torch.stack(norms).sqrt().tolist() if norms else []

    def _spike(self, norms: list[float]) -> str | None:
        """A message when a group's gradient norm is a spike against its recent history."""
        for name, norm, history in zip(
            self.group_names, norms, self.grad_norm_history, strict=True
        ):
            if len(history) < SPIKE_MIN_HISTORY:
                continue
            typical = float(np.quantile(history, SPIKE_QUANTILE))
            if typical > 0 and norm > SPIKE_FACTOR * typical:
                return (
                    f"{name} gradient norm {norm:.3g} > {SPIKE_FACTOR:g} x the recent steps' "
                    f"{SPIKE_QUANTILE:g} quantile {typical:.3g}"
                )
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
        self._epoch_batches += 1
        chunk = self._chunk(batch)
        opt = self.optimizers()
        opt.zero_grad(set_to_none=True)
        reason, message, loss = None, None, None
        norms: list[float] = []
        try:
            loss, warned = counted_rollout_loss(self.model, chunk)
            self._count_warned("train", warned)
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
            if reason in ("gradient_spike", "nonfinite_grad"):  # a finite loss: counted
                self._add_train_loss(loss.detach(), chunk.shape[0])
            if reason == "gradient_spike":
                self._record_norms(norms)
            self._epoch_skipped[reason] += 1
            self.skipped_total[reason] += 1
            if self._epoch_first_error is None:
                self._epoch_first_error = f"{reason}: {message}"
            return None
        self._record_norms(norms)
        opt.step()
        self._step_schedule()
        value = loss.detach()
        self._add_train_loss(value, chunk.shape[0])
        self.log(
            "train/loss_step", value, on_step=True, on_epoch=False, prog_bar=True,
            batch_size=chunk.shape[0],
        )  # fmt: skip
        return None

    def _count_warned(self, phase: str, message: str | None) -> None:
        """Count a batch whose rollout warned (``message``: its warning, or None)."""
        if message is not None:
            self._warned[phase] += 1
            self._warned_first = self._warned_first or message

    def _add_train_loss(self, value: Tensor, n: int) -> None:
        """Add a batch's loss to the epoch's train loss: every batch with a finite loss,
        skipped ones included, so that a skipped batch is not hidden by the mean."""
        self._train_sum += float(value) * n
        self._train_count += n

    def validation_step(self, batch: Any, batch_idx: int) -> None:
        chunk = self._chunk(batch)
        try:
            loss, warned = counted_rollout_loss(self.model, chunk)
            self._count_warned("val", warned)
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
    def on_train_start(self) -> None:
        # the learning rates of the next step from the schedule's factor at that step:
        # a checkpoint holds those the run had when it was written, which a run resumed
        # with more epochs (a longer cosine) would otherwise take for its first step (the
        # same values where the length did not change)
        scheduler = self.lr_schedulers()
        if scheduler is not None:
            factor = self._cosine_factor(scheduler.last_epoch)
            groups = scheduler.optimizer.param_groups
            for group, base in zip(groups, scheduler.base_lrs, strict=True):
                group["lr"] = base * factor
        # resumed in the middle of an epoch: Lightning does not start that epoch again
        # (no on_train_epoch_start), so its sums so far come from the checkpoint
        state, self._resumed_epoch = self._resumed_epoch, None
        if state and state.get("epoch") == self.current_epoch:
            self._reset_epoch()
            self._epoch_batches = int(state["batches"])
            self._epoch_skipped.update(state["skipped"])
            self._epoch_first_error = state["first_error"]
            if self.global_rank == 0:  # the sums over all ranks (reduced when saved)
                self._train_sum = float(state["train_sum"])
                self._train_count = int(state["train_count"])
            self._epoch_start -= float(state["seconds"])

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
        metrics = self.model.metrics()
        learned = getattr(self.model, "learned_parameters", None)
        params = learned() if callable(learned) else metrics
        self.log("train/loss_epoch", train_loss, on_epoch=True)
        self.log("train/skipped", float(n_skipped), on_epoch=True)
        self.log("time/epoch_s", time.perf_counter() - self._epoch_start, on_epoch=True)
        for name, value in metrics.items():
            self.log(name, float(value), on_epoch=True)
        if n_skipped and self.trainer.is_global_zero:
            detail = ", ".join(f"{c} {r.replace('_', ' ')}" for r, c in skipped_by.items() if c)
            first = f"; first: {self._epoch_first_error}" if self._epoch_first_error else ""
            # (counted from 1, as the epoch's summary line that follows)
            log.warning("epoch %d: skipped %d step(s) (%s)%s", epoch + 1, n_skipped, detail, first)
        warned = self._reduce_sum(self._warned["train"], self._warned["val"])
        if any(warned) and self.trainer.is_global_zero:
            log.warning(
                "epoch %d: the rollouts of %d training and %d validation batch(es) warned "
                "(tunnelling, constraint drift); first: %s",
                epoch + 1, *map(int, warned), self._warned_first,
            )  # fmt: skip
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
            write_learned(self.run_dir, self.last_epoch_summary)
        if self.report_epochs and self.trainer.is_global_zero:
            print(epoch_line(self.last_epoch_summary, self.trainer.max_epochs), flush=True)

    # -------------------------------------------------------------- checkpoints
    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        # every rank saves (rank 0 writes): the running epoch's loss sums over all ranks
        train_sum, train_count = self._reduce_sum(self._train_sum, self._train_count)
        checkpoint["diffcontact"] = {
            "skipped_total": dict(self.skipped_total),
            "grad_norm_history": [list(h) for h in self.grad_norm_history],
            "model_format": MODEL_FORMAT_VERSION,
            "version": __version__,
            "epoch_state": {  # the running epoch's sums (complete at the end of an epoch)
                "epoch": int(self.current_epoch),
                "batches": self._epoch_batches,
                "skipped": dict(self._epoch_skipped),
                "first_error": self._epoch_first_error,
                "train_sum": train_sum,
                "train_count": int(train_count),
                "seconds": time.perf_counter() - self._epoch_start,
            },
        }

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        extra = checkpoint.get("diffcontact", {})
        self._resumed_epoch = extra.get("epoch_state")
        self.skipped_total.update(extra.get("skipped_total", {}))
        if "grad_norm_history" in extra:
            self.grad_norm_history = [list(h) for h in extra["grad_norm_history"]]


def _values(name: str, values: Any) -> str | None:
    """``"mu 0.31"``, ``"mu 0.31 0.29"`` or ``"mu 30 values in [0.12, 0.45]"`` (None: no values)."""
    if values is None:
        return None
    vals = [float(v) for v in np.atleast_1d(np.asarray(values, dtype=float)).reshape(-1)]
    if not vals:
        return None
    if len(set(vals)) == 1:
        return f"{name} {vals[0]:.4g}"
    if len(vals) <= 4:
        return f"{name} " + " ".join(f"{v:.4g}" for v in vals)
    return f"{name} {len(vals)} values in [{min(vals):.4g}, {max(vals):.4g}]"


def epoch_line(summary: dict[str, Any], epochs: int | None = None) -> str:
    """One line for an epoch's summary: losses, skipped steps and the learned physical parameters.

    ``epoch 3/100: loss 1.234e-03 (val 1.456e-03); m_i/m_1 2.01 1.49; mu 0.51; e_P 0.02``
    """
    n = int(summary["epoch"]) + 1
    head = f"epoch {n}/{epochs}" if epochs else f"epoch {n}"
    parts = [f"{head}: loss {summary['train_loss']:.4g} (val {summary['val_loss']:.4g})"]
    skipped = sum(summary.get("skipped_steps", {}).values())
    if skipped:
        parts[0] += f", {skipped} step(s) skipped"
    learned = summary.get("learned") or {}
    if "mass_ratios" in learned or "mu" in learned:
        ratios = learned.get("mass_ratios")
        texts = [
            _values("m_i/m_1", ratios[1:] if ratios else None),
            _values("mu", learned.get("mu")),
            _values("e_P", learned.get("cor")),
            _values("eps", learned.get("eps")),
        ]
    else:  # another registered model: its metrics()
        texts = [_values(k.removeprefix("param/"), v) for k, v in list(learned.items())[:6]]
    return "; ".join(parts + [t for t in texts if t])


@rank_zero_only
def write_learned(run_dir: Path, summary: dict[str, Any]) -> None:
    """Write ``learned.json`` (the epoch summary, learned parameters as plain numbers)."""
    atomic_write_json(run_dir / "learned.json", summary)
