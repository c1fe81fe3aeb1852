"""Gauss-Newton refit of a trained model's potential output layer and physical parameters.

Adam brings the potential network close, but not to the precision a chaotic
system's rollout needs: on CP3 after 1000 epochs the test rollout error was
5.7e-3 where the true potential with the learned masses gives 1.4e-5
(docs/training.md, "Refit"; results.md's "before refit" column). The network's
last hidden layer can represent the truth far better than that:
``V(x) = w . phi(x)`` is *linear* in the output weights ``w`` (256 numbers), so
once the hidden features ``phi`` are trained, fitting ``w`` is a small
least-squares problem that Gauss-Newton solves in one or two iterations.

:func:`refit` minimises the mean squared error of the rolled-out training
chunks (the training loss is the MAE; its minimiser is the same for exact
data) over

- ``w``, the potential MLP's output weights, whose Jacobian is exact: each chunk
  gets its own copy of ``w`` (a leaf ``(N, H)``), so one backward pass per
  residual coordinate gives every chunk's row of the Jacobian at once (a loop
  over the ``(L - 1) * 2 * P * dim`` coordinates of a chunk, not over chunks);
- the physical parameters that are free (the mass ratios, second moments,
  ``mu`` where it is above zero, ``e_P`` where it is strictly inside [0, 1]),
  by central finite differences (:data:`FD_STEP`), one column per scalar; the
  common mass scale is left out (the data do not fix it; ``w`` carries the
  potential's scale),

with Levenberg-Marquardt damping ``lam * diag(J^T J)``: each iteration solves
the normal equations for every ``lam`` in :data:`LAMBDAS` and keeps the step
with the smallest *validation* MSE, and only if it is smaller than before
(otherwise the refit stops and the model is unchanged by that iteration). The
hidden layers are not touched.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from diffcontact.contact import ConeQPError
from diffcontact.learning.training.module import _is_nonfinite_error

__all__ = [
    "FD_STEP",
    "LAMBDAS",
    "PENDING",
    "RefitReport",
    "refit",
    "refit_run",
    "rollout_residual",
]

LAMBDAS = (1e-12, 1e-10, 1e-8, 1e-6, 1e-4)
"""Levenberg-Marquardt damping factors tried in each iteration (the best on validation wins)."""
FD_STEP = 1e-6
"""Central finite-difference step of the physical parameters' Jacobian columns (raw units)."""
CHUNKS_PER_PASS = 1000
"""Chunks rolled out in one graph when accumulating the normal equations (memory bound)."""
PENDING = "refit.pending.json"
"""The journal of :func:`refit_run`'s writes, in the run folder while they are under way:
the SHA-256 of the new ``model.pt`` and the ``learned.json`` and ``refit.json`` that go
with it (a refit killed between its writes is finished by the next ``refit_run``)."""


@dataclass
class RefitReport:
    """What :func:`refit` did: the MSEs before and after, and one record per iteration."""

    train_mse_before: float
    val_mse_before: float
    train_mse: float
    val_mse: float
    parameters: list[str]
    iterations: list[dict[str, Any]] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        """Plain data for ``refit.json``."""
        return {
            "train_mse_before": self.train_mse_before,
            "val_mse_before": self.val_mse_before,
            "train_mse": self.train_mse,
            "val_mse": self.val_mse,
            "parameters": list(self.parameters),
            "iterations": [dict(it) for it in self.iterations],
        }


class _PerChunkOutput(nn.Module):
    """``V(x) = phi(x) . W[n]``: the potential with one output-weight row per chunk ``n``."""

    def __init__(self, base: nn.Module, W: Tensor) -> None:
        super().__init__()
        self.base = base
        self.W = W  # (N, H)

    def forward(self, x: Tensor) -> Tensor:
        phi = self.base.features(x, self.W.dtype)  # (N, H)
        if phi.shape[:-1] != self.W.shape[:-1]:
            raise RuntimeError(
                f"refit: the simulator evaluated the potential on a batch of shape "
                f"{tuple(x.shape)}, not one state per chunk ({self.W.shape[0]})"
            )
        return (phi * self.W).sum(-1).to(x.dtype)


def rollout_residual(model: Any) -> Callable[..., tuple[Tensor, Tensor]]:
    """``residual(chunks, w, leaf=False)``: the rollout of ``model`` with output weights
    ``w (H,)`` minus ``chunks (N, L, 2, P, dim)`` over states 1..L-1, ``(N, R)``, and the
    per-chunk copy ``W (N, H)`` of ``w`` (a leaf requiring grad with ``leaf``)."""
    base = model.potential

    def residual(chunks: Tensor, w: Tensor, leaf: bool = False) -> tuple[Tensor, Tensor]:
        W = w.expand(chunks.shape[0], -1).clone().requires_grad_(leaf)
        model.potential = _PerChunkOutput(base, W)
        try:
            pred = model.simulate(chunks[:, 0], chunks.shape[1] - 1, check_overlap=False)
        finally:
            model.potential = base
        return (pred[:, 1:] - chunks[:, 1:]).flatten(1), W

    return residual


def _free_entries(model: Any) -> list[tuple[str, nn.Parameter, int]]:
    """``(label, parameter, flat index)`` of the physical parameters the refit moves."""
    out: list[tuple[str, nn.Parameter, int]] = []
    for i in range(1, model.log_mass_rel.numel()):
        out.append((f"log_mass_rel[{i}]", model.log_mass_rel, i))
    if model.log_second_moments is not None:
        for i in range(model.log_second_moments.numel()):
            out.append((f"log_second_moments[{i}]", model.log_second_moments, i))
    mu = model.raw_mu.detach().flatten()
    for i in range(mu.numel()):
        if mu[i] > 0:  # relu: at or below 0 the data have no slope to follow
            out.append((f"raw_mu[{i}]", model.raw_mu, i))
    cor = model.raw_cor.detach().flatten()
    for i in range(cor.numel()):
        if 0 < cor[i] < 1:  # e_P = clamp(raw_cor, 0, 1)
            out.append((f"raw_cor[{i}]", model.raw_cor, i))
    return out


def _check_model(model: Any) -> nn.Linear:
    potential = getattr(model, "potential", None)
    if potential is None or not hasattr(potential, "features") or not hasattr(model, "raw_mu"):
        name = getattr(model, "model_name", type(model).__name__)
        raise ValueError(
            f"refit needs a physical model with a potential network (CM/CMr/LCP/Coulomb-CD-"
            f"CLNN/CHNN), got {name}"
        )
    return potential.layers[-1]


def refit(
    model: Any,
    train_chunks: Tensor,
    val_chunks: Tensor,
    iterations: int = 2,
    *,
    lambdas: Sequence[float] = LAMBDAS,
    log: Callable[[str], None] | None = print,
) -> RefitReport:
    """Gauss-Newton refit of ``model``'s potential output layer and free physical parameters.

    Args:
        model: a trained :class:`~diffcontact.learning.models.LearnedModel` (changed in place;
            its parameters must be float64, as ``train`` leaves them).
        train_chunks: ``(N, L, 2, P, dim)`` training chunks (chunks holding NaN are left out).
        val_chunks: ``(M, L, 2, P, dim)`` validation chunks: they choose the damping and
            decide whether a step is kept.
        iterations: the most Gauss-Newton iterations (it stops early once a step no longer
            lowers the validation MSE).
        lambdas: damping factors tried in each iteration.
        log: called with one line per iteration (``None``: silent).

    Returns:
        A :class:`RefitReport`.

    Raises:
        ValueError: not a physical model with a potential network, parameters not float64,
            bad chunk shapes, no chunk or no finite chunk, or ``iterations < 0``.
    """
    out_layer = _check_model(model)
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 0:
        raise ValueError(f"iterations must be a non-negative integer, got {iterations!r}")
    if out_layer.weight.dtype != torch.float64:
        raise ValueError(f"refit needs float64 parameters, got {out_layer.weight.dtype}")
    train_chunks = _finite_chunks(train_chunks, "train_chunks")
    val_chunks = _finite_chunks(val_chunks, "val_chunks")
    free = _free_entries(model)
    say = log or (lambda _line: None)

    residual = rollout_residual(model)

    def mse(chunks: Tensor, w: Tensor) -> float:
        try:
            with torch.no_grad():
                total = sum(
                    float(residual(c, w)[0].pow(2).sum()) for c in chunks.split(CHUNKS_PER_PASS)
                )
        except ConeQPError:
            return math.inf
        except ValueError as err:  # a trial step whose rollout blew up
            if not _is_nonfinite_error(err):
                raise
            return math.inf
        value = total / chunks[:, 1:].numel()
        return value if math.isfinite(value) else math.inf

    w = out_layer.weight.detach().clone().squeeze(0)  # (H,)
    train0, val0 = mse(train_chunks, w), mse(val_chunks, w)
    report = RefitReport(train0, val0, train0, val0, [label for label, _, _ in free])
    say(f"refit: train MSE {train0:.3e}, val MSE {val0:.3e}; {w.numel()} output weights "
        f"and {len(free)} physical parameters")  # fmt: skip
    for it in range(iterations):
        t0 = time.perf_counter()
        JtJ, Jtr = _normal_equations(residual, train_chunks, w, free)
        scale = JtJ.diagonal().clamp_min(0).sqrt()
        scale = torch.where(scale > 0, scale, torch.ones_like(scale))
        A = JtJ / scale[:, None] / scale[None, :]
        b = Jtr / scale
        best: tuple[float, float, Tensor] | None = None
        for lam in lambdas:
            eye = torch.eye(len(b), dtype=b.dtype, device=b.device)
            try:
                step = -torch.linalg.solve(A + lam * eye, b) / scale
            except RuntimeError:  # singular at this damping
                continue
            with _applied(free, step[w.numel() :]):
                v = mse(val_chunks, w + step[: w.numel()])
            if best is None or v < best[0]:
                best = (v, lam, step)
        record: dict[str, Any] = {"iteration": it + 1}
        if best is None or not best[0] < report.val_mse:
            record.update(accepted=False, seconds=time.perf_counter() - t0)
            report.iterations.append(record)
            say(f"refit iteration {it + 1}: no damping lowered the val MSE; stopped")
            break
        v, lam, step = best
        w = w + step[: w.numel()]
        _apply(free, step[w.numel() :])
        with torch.no_grad():
            out_layer.weight.copy_(w[None])
        report.train_mse, report.val_mse = mse(train_chunks, w), v
        record.update(
            accepted=True, lam=lam, train_mse=report.train_mse, val_mse=v,
            step_norm=float(step.norm()), seconds=time.perf_counter() - t0,
        )  # fmt: skip
        report.iterations.append(record)
        say(f"refit iteration {it + 1}: train MSE {report.train_mse:.3e}, val MSE {v:.3e} "
            f"(damping {lam:g}, {record['seconds']:.0f} s)")  # fmt: skip
    return report


def _finite_chunks(chunks: Tensor, name: str) -> Tensor:
    if not isinstance(chunks, Tensor) or chunks.dim() != 5 or chunks.shape[1] < 2:
        shape = tuple(chunks.shape) if isinstance(chunks, Tensor) else type(chunks).__name__
        raise ValueError(f"{name} must have shape (N, L, 2, P, dim) with L >= 2, got {shape}")
    if chunks.shape[0] == 0:  # (said "no chunk without NaN or infinite values")
        raise ValueError(f"{name} holds no chunk (shape {tuple(chunks.shape)})")
    chunks = chunks.to(torch.float64)
    keep = torch.isfinite(chunks.flatten(1)).all(1)
    if not bool(keep.any()):
        raise ValueError(f"{name}: no chunk without NaN or infinite values")
    return chunks[keep]


def _apply(free: list[tuple[str, nn.Parameter, int]], delta: Tensor) -> None:
    with torch.no_grad():
        for (_, param, i), d in zip(free, delta, strict=True):
            param.view(-1)[i] += d


class _applied:
    """Context: the physical parameters moved by ``delta`` inside, put back on exit."""

    def __init__(self, free: list[tuple[str, nn.Parameter, int]], delta: Tensor) -> None:
        self.free, self.delta = free, delta

    def __enter__(self) -> None:
        self.saved = [param.detach().view(-1)[i].clone() for _, param, i in self.free]
        _apply(self.free, self.delta)

    def __exit__(self, *exc: object) -> None:
        with torch.no_grad():
            for (_, param, i), value in zip(self.free, self.saved, strict=True):
                param.view(-1)[i] = value


def _normal_equations(
    residual: Callable[..., tuple[Tensor, Tensor]],
    chunks: Tensor,
    w: Tensor,
    free: list[tuple[str, nn.Parameter, int]],
) -> tuple[Tensor, Tensor]:
    """``J^T J (K, K)`` and ``J^T r (K,)`` over all chunks, ``K = H + len(free)``."""
    H = w.numel()
    K = H + len(free)
    JtJ = torch.zeros(K, K, dtype=w.dtype, device=w.device)
    Jtr = torch.zeros(K, dtype=w.dtype, device=w.device)
    for part in chunks.split(CHUNKS_PER_PASS):
        cols = []
        for j in range(len(free)):  # central differences, one column per free scalar
            delta = torch.zeros(len(free), dtype=w.dtype, device=w.device)
            delta[j] = FD_STEP
            with torch.no_grad(), _applied(free, delta):
                plus = residual(part, w)[0]
            with torch.no_grad(), _applied(free, -delta):
                minus = residual(part, w)[0]
            cols.append((plus - minus) / (2 * FD_STEP))
        J_phys = torch.stack(cols, -1) if cols else None  # (n, R, F)
        r, W = residual(part, w, leaf=True)
        R = r.shape[1]
        for c in range(R):  # one backward per residual coordinate: every chunk's row at once
            (g,) = torch.autograd.grad(r[:, c].sum(), W, retain_graph=c < R - 1)
            row = g if J_phys is None else torch.cat([g, J_phys[:, c]], -1)  # (n, K)
            JtJ += row.T @ row
            Jtr += row.T @ r[:, c].detach()
    return JtJ, Jtr


def refit_run(
    run_dir: str | os.PathLike[str],
    iterations: int = 2,
    *,
    data_dir: str | os.PathLike[str] | None = None,
    log: Callable[[str], None] | None = print,
) -> RefitReport:
    """:func:`refit` a finished run in place: ``model.pt`` and ``learned.json`` are rewritten.

    The model before the refit is kept as ``model_adam.pt`` (written by the first refit
    after training: ``train`` removes it whenever it writes a new ``model.pt``, so a second
    refit keeps it); ``refit.json`` records the report. Files are written
    atomically, and together through a journal (:data:`PENDING`, written before
    ``model.pt``, removed after ``refit.json``): a ``refit_run`` that finds one left by a
    refit killed between its writes first finishes them (``learned.json`` and
    ``refit.json`` of the ``model.pt`` written) or, where ``model.pt`` is not the one the
    journal names, removes it; ``log`` says which. The data are the run's dataset
    (``run.json``'s ``data_dir``) unless ``data_dir`` is given. A refit that lowers
    nothing leaves every file as it was.

    Raises:
        ValueError: no finished run in ``run_dir`` (no ``model.pt``), a run folder that
            cannot be written (checked before any work, e.g. read-only storage), an
            unreadable journal, a model without a potential network, an unreadable
            dataset or one whose train or validation split holds no chunk, or a bad
            ``iterations``.
    """
    from diffcontact.io import atomic_write_bytes, atomic_write_json, check_writable_folder
    from diffcontact.learning.data.format import load_dataset
    from diffcontact.learning.models.storage import load_model, model_bytes

    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 0:
        # (checked before the model and the dataset are loaded; True ran one iteration)
        raise ValueError(f"iterations must be a non-negative integer, got {iterations!r}")
    if not isinstance(run_dir, (str, os.PathLike)):
        raise ValueError(f"run_dir must be a path, got {type(run_dir).__name__}")
    run = Path(run_dir)
    if not run.exists():
        raise ValueError(f"run directory {run} does not exist")
    if not (run / "model.pt").is_file():
        raise ValueError(f"{run}: no model.pt (not a finished run of diffcontact train)")
    try:  # before the iterations (minutes), not when their result is written
        check_writable_folder(run)
    except OSError as err:
        raise ValueError(
            f"cannot refit {run}: {err} (refit rewrites model.pt and learned.json there; "
            "copy the run to writable storage)"
        ) from None
    _finish_interrupted(run, log)
    info = _read_json(run / "run.json")
    source = data_dir if data_dir is not None else info.get("data_dir")
    if source is None:
        raise ValueError(f"{run}/run.json names no data_dir: pass data_dir")
    model = load_model(run)
    _check_model(model)
    dataset = load_dataset(source)
    train_chunks = dataset.split("train", dtype=torch.float64).chunks
    val_chunks = dataset.split("val", dtype=torch.float64).chunks
    for name, chunks in (("train", train_chunks), ("val", val_chunks)):
        if chunks.shape[0] == 0:  # train's wording (training.run._read_data)
            raise ValueError(
                f"{source}: its validation split is empty, and refit chooses the damping "
                "and keeps a step by the validation MSE: generate the dataset with a "
                "--val-fraction (or --n-val) above 0"
                if name == "val"
                else f"{source}: its train split is empty: nothing to refit to"
            )
    why = dataset.mismatch(model, torch.cat([train_chunks[:64, 0, 0], val_chunks[:64, 0, 0]]))
    if why is not None:
        raise ValueError(f"{source}: {why}: data of another system, not refit to")
    report = refit(model.double(), train_chunks, val_chunks, iterations, log=log)
    if not any(it.get("accepted") for it in report.iterations):
        return report  # nothing changed: model.pt is still what it was
    if not (run / "model_adam.pt").is_file():  # model.pt is Adam's (train removes a stale copy)
        atomic_write_bytes(run / "model_adam.pt", (run / "model.pt").read_bytes())
    weights = model_bytes(model)
    learned = _read_json(run / "learned.json")
    learned["learned"] = model.learned_parameters()
    learned["refit"] = {"iterations": len(report.iterations), "val_mse": report.val_mse}
    refit_json = report.as_dict() | {"data_dir": str(source)}
    # three files, each written atomically; the journal makes them one write (a kill between
    # them leaves it, and the next refit_run finishes them: _finish_interrupted)
    journal = {"model_sha256": hashlib.sha256(weights).hexdigest()}
    atomic_write_json(run / PENDING, journal | {"learned": learned, "refit": refit_json})
    atomic_write_bytes(run / "model.pt", weights)
    atomic_write_json(run / "learned.json", learned)
    atomic_write_json(run / "refit.json", refit_json)
    (run / PENDING).unlink()
    return report


def _finish_interrupted(run: Path, log: Callable[[str], None] | None) -> None:
    """Finish the writes of a refit of ``run`` killed between them, named by its journal
    (:data:`PENDING`), or remove a journal whose ``model.pt`` was never written."""
    from diffcontact.io import atomic_write_json

    pending = run / PENDING
    if not pending.is_file():
        return
    say = log or (lambda _line: None)
    journal = _read_json(pending)
    journal = journal if isinstance(journal, dict) else {}
    digest, learned, report = (journal.get(k) for k in ("model_sha256", "learned", "refit"))
    if not (isinstance(digest, str) and isinstance(learned, dict) and isinstance(report, dict)):
        raise ValueError(
            f"{pending} is not a refit journal (no model_sha256, learned or refit): was it "
            "edited? remove it, and check learned.json against model.pt"
        )
    if hashlib.sha256((run / "model.pt").read_bytes()).hexdigest() != digest:
        pending.unlink()
        say(f"refit: removed {pending}: model.pt is not the one it names (a refit "
            "interrupted before writing model.pt, or a model.pt written since)")  # fmt: skip
        return
    atomic_write_json(run / "learned.json", learned)
    atomic_write_json(run / "refit.json", report)
    pending.unlink()
    say(f"refit: finished the writes of an interrupted refit of {run}: learned.json and "
        "refit.json now match its model.pt")  # fmt: skip


def _read_json(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path} is not readable JSON: {err}") from None
