"""Evaluation of a learned model: rollout error, energy, learned parameters, plots and GIFs.

Protocol (paper-facts.md, "Training set-up"): from the first state of every
test trajectory, roll the model out for ``max(horizon, 100 dt)`` (that is
``max(horizon / dt, 100)`` states, ``steps = states - 1``) and compare with the
ground truth. When the stored test trajectories are shorter than that (e.g.
the rope, 20 states), the ground truth is simulated from the same initial
states with the true system (``load_system(config)``, float64).

Metrics (``docs/evaluation.md`` has the definitions):

- :func:`relative_error`: ``||z_pred - z_true|| / ||z_true||`` per trajectory
  and step, the norm over the whole state ``(2, P, dim)``;
- :func:`mean_ci95`: mean and the half-width of a Student-t 95% confidence
  interval over independent samples (the per-trajectory mean errors);
- :func:`energy_rel_drift`: the *true* energy along predicted and true
  trajectories, relative to the true initial energy;
- :func:`true_parameters`: mass ratios ``m_i / m_1`` (i >= 2), ``mu`` and ``e_P``
  per contact (contact numbering of ``docs/conventions.md``).

:func:`evaluate` runs the protocol on a training run and writes
``metrics.json``, ``rollout.npz``, PNG plots and a GIF; :func:`register_cli`
adds the ``diffcontact evaluate`` subcommand. torch and matplotlib are
imported inside the functions that need them.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import re
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from diffcontact.cli_args import int_at_least
from diffcontact.io import atomic_path, atomic_save_npz, atomic_write_bytes

__all__ = [
    "EvaluationInputError",
    "energy_rel_drift",
    "evaluate",
    "find_training_log",
    "mean_ci95",
    "read_training_log",
    "register_cli",
    "relative_error",
    "rollout_steps",
    "t_quantile_975",
    "true_energy",
    "true_parameters",
]

METRICS_FORMAT_VERSION = 1
MIN_EVAL_STATES = 100  # paper-facts.md: roll out for max(horizon, 100 dt)


class EvaluationInputError(ValueError):
    """Bad input to :func:`evaluate` (missing run, checkpoint, test data or config)."""


# ---------------------------------------------------------------------------
# metric functions (pure; numpy in, numpy out; torch tensors are accepted)
# ---------------------------------------------------------------------------


def _np(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor, without importing torch
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def relative_error(pred: Any, true: Any) -> np.ndarray:
    """Relative error of predicted states: ``||z_pred - z_true|| / ||z_true||``.

    The norm is the Euclidean norm over the whole state (positions and
    velocities of all points, ``2 * P * dim`` numbers).

    Args:
        pred: ``(N, T, 2, P, dim)`` predicted trajectories (numpy or torch;
            any leading dims work, the last three are the state).
        true: same shape, the ground truth.

    Returns:
        ``(N, T)`` float64. NaN/inf where the prediction is not finite or the
        true state is zero.
    """
    p, t = _np(pred), _np(true)
    if p.shape != t.shape:
        raise ValueError(f"pred and true must have the same shape, got {p.shape} and {t.shape}")
    if p.ndim < 3:
        raise ValueError(f"expected states (..., 2, P, dim), got shape {p.shape}")
    lead = p.shape[:-3]
    num = np.linalg.norm((p - t).reshape(*lead, -1), axis=-1)
    den = np.linalg.norm(t.reshape(*lead, -1), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return num / den


# two-sided 95% Student-t quantiles t_{0.975, df} for df = 1..30
_T975 = (
    12.706205, 4.302653, 3.182446, 2.776445, 2.570582, 2.446912, 2.364624, 2.306004,
    2.262157, 2.228139, 2.200985, 2.178813, 2.160369, 2.144787, 2.131450, 2.119905,
    2.109816, 2.100922, 2.093024, 2.085963, 2.079614, 2.073873, 2.068658, 2.063899,
    2.059539, 2.055529, 2.051831, 2.048407, 2.045230, 2.042272,
)  # fmt: skip
_Z975 = 1.959963984540054


def t_quantile_975(df: int) -> float:
    """The 0.975 quantile of Student's t with ``df`` degrees of freedom.

    Tabulated for ``df <= 30``; above, the Cornish-Fisher expansion (error
    below 1e-7). ``nan`` for ``df < 1``.
    """
    if df < 1:
        return math.nan
    if df <= len(_T975):
        return _T975[df - 1]
    z, n = _Z975, float(df)
    return (
        z
        + (z**3 + z) / (4 * n)
        + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * n**2)
        + (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / (384 * n**3)
        + (79 * z**9 + 776 * z**7 + 1482 * z**5 - 1920 * z**3 - 945 * z) / (92160 * n**4)
    )


def mean_ci95(x: Any, axis: int = 0) -> tuple[Any, Any]:
    """Sample mean and the half-width of its 95% confidence interval.

    The interval is Student-t: ``t_{0.975, n-1} * s / sqrt(n)`` with ``s`` the
    sample standard deviation (``ddof=1``) of the ``n`` samples along ``axis``.
    For the headline number pass one value per test trajectory (its mean error
    over time), so the samples are independent; passing ``(N, T)`` errors with
    ``axis=0`` gives the mean and band per time step.

    Args:
        x: samples, e.g. ``(N,)`` or ``(N, T)``.
        axis: the axis of the samples.

    Returns:
        ``(mean, halfwidth)``: floats for 1-d input, else arrays of the other
        dims. The half-width is ``nan`` for a single sample. Non-finite
        samples propagate (filter them first).
    """
    a = np.moveaxis(_np(x), axis, 0)
    n = a.shape[0]
    if n == 0:
        raise ValueError("mean_ci95 needs at least one sample")
    mean = a.mean(0)
    if n == 1:
        half = np.full_like(mean, np.nan)
    else:
        half = t_quantile_975(n - 1) * a.std(0, ddof=1) / math.sqrt(n)
    if np.ndim(mean) == 0:
        return float(mean), float(half)
    return mean, half


def rollout_steps(system: Any) -> int:
    """Steps of an evaluation rollout: ``max(horizon / dt, 100) - 1``.

    The rollout then holds ``max(horizon, 100 dt) / dt`` states, the first
    being the test initial state (paper-facts.md, "Training set-up").
    """
    return max(round(system.horizon / system.dt), MIN_EVAL_STATES) - 1


def true_energy(system: Any, traj: Any) -> np.ndarray:
    """Energy of the true system along trajectories (no gradient, float64).

    Args:
        system: the ground-truth ``System`` (its ``energy``).
        traj: ``(..., 2, P, dim)`` states, e.g. ``(N, T, 2, P, dim)``.

    Returns:
        ``(...)`` float64 numpy, e.g. ``(N, T)``.
    """
    import torch

    z = torch.as_tensor(_np(traj), dtype=torch.float64)
    with torch.no_grad():
        return system.energy(z).detach().cpu().numpy().astype(np.float64)


def energy_scale(system: Any, true: Any) -> float:
    """The energy unit of the drift metrics: the mean kinetic energy of the true motion.

    ``mean over n and t of T(true[n, t])``. Unlike ``E(0)`` it does not depend
    on the potential's arbitrary zero (the pendulum's pivot height), it is
    positive whenever anything moves, and unlike the *initial* kinetic energy
    it includes what a fall converts from potential energy (a pendulum
    released nearly at rest).

    Args:
        system: the ground-truth ``System`` (its ``kinetic_energy``).
        true: ``(N, T, 2, P, dim)`` true trajectories.
    """
    import torch

    z = torch.as_tensor(_np(true), dtype=torch.float64)
    with torch.no_grad():
        T = system.kinetic_energy(z).detach().cpu().numpy().astype(np.float64)
    return float(np.mean(T)) if T.size else math.nan


def _drift(E: np.ndarray, E0: np.ndarray, scale: float) -> np.ndarray:
    """``|E[n, t] - E0[n]| / scale``; all NaN when ``scale`` is not positive."""
    if not (scale > 0 and math.isfinite(scale)):
        return np.full(E.shape, np.nan)
    return np.abs(E - E0[:, None]) / scale


def _finite_mean(curves: np.ndarray) -> float:
    """Mean over the rows that are finite at every step of their per-row means."""
    ok = np.isfinite(curves).all(-1)
    return float(curves[ok].mean()) if ok.any() else math.nan


def energy_rel_drift(system: Any, pred: Any, true: Any) -> dict[str, float]:
    """Relative drift of the true energy along predicted and true trajectories.

    With ``E`` the true system's energy, ``E0[n] = E(true[n, 0])`` and
    ``scale`` the mean kinetic energy along the true trajectories (:func:`energy_scale`)::

        drift_X[n, t] = |E(X[n, t]) - E0[n]| / scale,   X in {pred, true}
        result[X]     = mean over n of (mean over t = 0..T-1 of drift_X[n, t])

    Trajectories with a non-finite value (a diverged prediction) are left out
    of the mean. For an
    energy-conserving task both numbers should be ~0 (``true`` measures the
    simulator's own drift); for a dissipative task ``true`` is the real energy
    loss and ``pred`` should match it.

    Args:
        system: the ground-truth ``System``.
        pred, true: ``(N, T, 2, P, dim)``.

    Returns:
        ``{"pred": float, "true": float}``.
    """
    p, t = _np(pred), _np(true)
    if p.shape != t.shape or p.ndim != 5:
        raise ValueError(f"pred and true must both be (N, T, 2, P, dim), got {p.shape}, {t.shape}")
    E_pred, E_true = true_energy(system, p), true_energy(system, t)
    E0, scale = E_true[:, 0], energy_scale(system, t)
    return {
        "pred": _finite_mean(_drift(E_pred, E0, scale)),
        "true": _finite_mean(_drift(E_true, E0, scale)),
    }


def true_parameters(system: Any) -> dict[str, list[float]]:
    """The physical parameters a model should learn, as plain numbers.

    Args:
        system: a ``System`` (or anything ``load_system`` accepts).

    Returns:
        ``mass_ratios``: ``m_i / m_1`` for bodies 2..B (Tables S.1-S.3; empty
        for one body); ``mu`` and ``cor``: one value per candidate contact in
        the contact numbering of ``docs/conventions.md``.
    """
    if not hasattr(system, "mass"):
        from diffcontact.systems import load_system

        system = load_system(system)
    m = _np(system.mass).reshape(-1)
    K = int(system.n_contacts)
    return {
        "mass_ratios": (m[1:] / m[0]).tolist(),
        "mu": np.broadcast_to(_np(system.mu), (K,)).tolist(),
        "cor": np.broadcast_to(_np(system.cor), (K,)).tolist(),
    }


# ---------------------------------------------------------------------------
# learned parameters
# ---------------------------------------------------------------------------


def _floats(value: Any) -> list[float] | None:
    if value is None:
        return None
    arr = _np(value).reshape(-1)
    return [float(v) for v in arr]


def _learned(raw: Mapping[str, Any], n_bodies: int) -> dict[str, Any]:
    """Normalise ``model.learned_parameters()``: mass ratios ``m_i/m_1`` for i >= 2."""
    out: dict[str, Any] = {}
    ratios = _floats(raw.get("mass_ratios"))
    if ratios is None and raw.get("mass") is not None:
        mass = _floats(raw["mass"])
        ratios = [m / mass[0] for m in mass] if mass else None
    if ratios is not None and len(ratios) == n_bodies:
        # the model's list includes the first body (ratio 1): drop it
        ratios = [r / ratios[0] for r in ratios[1:]] if ratios[0] != 0 else ratios[1:]
    out["mass_ratios"] = ratios
    out["mu"] = _floats(raw.get("mu"))
    out["cor"] = _floats(raw.get("cor"))
    eps = raw.get("eps")
    out["eps"] = None if eps is None else _floats(eps)
    if out["eps"] is not None and len(out["eps"]) == 1:
        out["eps"] = out["eps"][0]
    return out


def _compare(learned: list[float] | None, true: list[float], relative: bool) -> dict[str, Any]:
    entry: dict[str, Any] = {"learned": learned, "true": true}
    key = "max_rel_error" if relative else "max_abs_error"
    if learned is not None and len(learned) == len(true):
        if len(true) == 0:
            entry[key] = 0.0
        else:
            lv, tv = np.asarray(learned), np.asarray(true)
            diff = np.abs(lv - tv)
            if relative:
                diff = diff / np.abs(tv)
            entry[key] = float(diff.max())
    elif learned is not None and len(learned) == 1 and len(true) > 1:
        # one shared learned value against per-contact truth
        entry[key] = float(np.max(np.abs(np.asarray(true) - learned[0])))
    else:
        entry[key] = None
    return entry


# ---------------------------------------------------------------------------
# run directory, dataset and model
# ---------------------------------------------------------------------------


def _read_json(path: Path, what: str) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except OSError as err:
        raise EvaluationInputError(f"cannot read {what} {path}: {err.strerror or err}") from None
    except json.JSONDecodeError as err:
        raise EvaluationInputError(f"{what} {path} is not valid JSON: {err}") from None
    if not isinstance(data, dict):
        raise EvaluationInputError(f"{what} {path} must hold a JSON object")
    return data


def _has_checkpoint(run_dir: Path) -> bool:
    if (run_dir / "model.pt").is_file():
        return True
    ckpts = run_dir / "checkpoints"
    return ckpts.is_dir() and any(ckpts.glob("*.ckpt"))


def _resolve_data_dir(run_dir: Path | None, run: Mapping[str, Any], data_dir: Any) -> Path:
    if data_dir is not None:
        return Path(data_dir)
    value = run.get("data_dir")
    if not value:
        if run_dir is None:
            raise EvaluationInputError("no test data: give data_dir when there is no run directory")
        raise EvaluationInputError(
            f"no test data: {run_dir / 'run.json'} names no data_dir (pass --data DIR)"
        )
    path = Path(str(value))
    if path.is_absolute() or path.exists() or run_dir is None:
        return path
    near = run_dir / path  # relative to the run directory
    return near if near.exists() else path


def _load_test(data_dir: Path) -> np.ndarray:
    path = data_dir / "test.npz"
    if not path.is_file():
        what = "data directory" if not data_dir.is_dir() else "test split"
        raise EvaluationInputError(f"test data not found: {path} (missing {what})")
    try:
        with np.load(path, allow_pickle=False) as f:
            if "traj" not in f.files:
                raise EvaluationInputError(f"{path} has no 'traj' array (found {f.files})")
            traj = np.asarray(f["traj"], dtype=np.float64)
    except (OSError, ValueError) as err:
        if isinstance(err, EvaluationInputError):
            raise
        raise EvaluationInputError(f"cannot read {path}: {err}") from None
    if traj.ndim != 5 or traj.shape[2] != 2 or traj.shape[0] == 0 or traj.shape[1] == 0:
        raise EvaluationInputError(
            f"{path}: traj must have shape (N, T, 2, P, dim) with N, T >= 1, got {traj.shape}"
        )
    if not np.isfinite(traj[:, 0]).all():
        raise EvaluationInputError(f"{path}: the initial states contain NaN or inf")
    return traj


def _model_label(model: Any, run: Mapping[str, Any]) -> str:
    for value in (getattr(model, "model_name", None), run.get("model")):
        if isinstance(value, str) and value:
            return value
        if isinstance(value, Mapping):
            name = value.get("model") or value.get("name")
            if isinstance(name, str) and name:
                return name
    return type(model).__name__


def _jsonable(x: Any) -> Any:
    if isinstance(x, Mapping):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


# ---------------------------------------------------------------------------
# training log (Lightning CSVLogger)
# ---------------------------------------------------------------------------


def find_training_log(run_dir: str | os.PathLike[str]) -> Path | None:
    """The newest ``metrics.csv`` under ``RUN_DIR/logs`` (Lightning's CSV logger), or None."""
    logs = Path(run_dir) / "logs"
    if not logs.is_dir():
        return None
    found = sorted(logs.rglob("metrics.csv"), key=lambda p: (p.stat().st_mtime, str(p)))
    return found[-1] if found else None


def _to_float(text: str | None) -> float:
    if text is None or text.strip() == "":
        return math.nan
    try:
        return float(text)
    except ValueError:
        return math.nan


def read_training_log(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Per-epoch values of every numeric column of a Lightning ``metrics.csv``.

    Lightning writes one row per logging call with empty cells elsewhere; the
    rows are grouped by ``epoch`` and each column keeps its last value in the
    epoch (NaN when it has none). Without an ``epoch`` column each row is one
    point. Columns with no number at all and ``step`` are left out.

    Returns:
        ``{"epoch": (E,), column: (E,), ...}``.
    """
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        return {}
    columns = [c for c in rows[0] if c is not None and c not in ("epoch", "step")]
    if "epoch" in rows[0]:
        epochs = np.array([_to_float(r.get("epoch")) for r in rows])
    else:
        epochs = np.arange(len(rows), dtype=np.float64)
    keys = np.unique(epochs[np.isfinite(epochs)])
    out: dict[str, np.ndarray] = {"epoch": keys}
    for c in columns:
        values = np.array([_to_float(r.get(c)) for r in rows])
        col = np.full(len(keys), np.nan)
        for i, e in enumerate(keys):
            v = values[(epochs == e) & np.isfinite(values)]
            if v.size:
                col[i] = v[-1]
        if np.isfinite(col).any():
            out[c] = col
    return out


_PARAM_RE = re.compile(
    r"(?:^|[/_.\s-])(mass_ratios?|mass|mu|cor|e_p|restitution|eps)(?:[_\[\s.:/-]*(\d+)\]?)?$"
)
_CATEGORY = {
    "mass_ratio": "mass_ratios",
    "mass_ratios": "mass_ratios",
    "mass": "mass",
    "mu": "mu",
    "cor": "cor",
    "e_p": "cor",
    "restitution": "cor",
    "eps": "eps",
}


def _classify_columns(log: Mapping[str, np.ndarray]) -> dict[str, dict[Any, str]]:
    """``{category: {index or None: column}}`` for learned parameters, plus ``loss``."""
    groups: dict[str, dict[Any, str]] = {}
    names = set(log)
    for col in log:
        if col == "epoch":
            continue
        name = col.lower()
        if name.endswith("_step") and col[: -len("_step")] + "_epoch" in names:
            continue  # Lightning's per-step twin of an epoch column
        base = name[: -len("_epoch")] if name.endswith("_epoch") else name
        if "loss" in base:
            groups.setdefault("loss", {})[col] = col
            continue
        m = _PARAM_RE.search(base)
        if m is None:
            continue
        cat = _CATEGORY[m.group(1)]
        idx = None if m.group(2) is None else int(m.group(2))
        groups.setdefault(cat, {})[idx] = col
    return groups


# ---------------------------------------------------------------------------
# plots (matplotlib Figure + Agg canvas, no pyplot state)
# ---------------------------------------------------------------------------


def _figure(width: float, height: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height))
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: Path, dpi: int = 110) -> Path:
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    return path


def _plot_rel_error(err: np.ndarray, dt: float, path: Path, title: str) -> Path:
    """Mean relative error per step with its 95% band (log y), faint single runs.

    Values at or below the bottom of the axis (a tenth of the smallest positive
    mean, e.g. exact zeros before the first contact) are drawn on the bottom edge.
    """
    fig = _figure(6.4, 3.8)
    ax = fig.subplots()
    t = np.arange(err.shape[1]) * dt
    sl = slice(1, None) if err.shape[1] > 1 else slice(None)  # step 0 is exact
    mean, half = mean_ci95(err, axis=0)
    mean = np.atleast_1d(mean)[sl]
    half = np.nan_to_num(np.atleast_1d(half))[sl]
    t = t[sl]
    positive = mean[mean > 0]
    floor = 0.1 * float(positive.min()) if positive.size else 1e-16
    for e in err[:30]:
        ax.plot(t, np.maximum(e[sl], floor), color="#9aa6b2", lw=0.5, alpha=0.6)
    ax.fill_between(
        t,
        np.maximum(mean - half, floor),
        np.maximum(mean + half, floor),
        color="#1f77b4",
        alpha=0.25,
        lw=0,
        label="95% CI of the mean",
    )
    ax.plot(t, np.maximum(mean, floor), color="#1f77b4", lw=2.0, label=f"mean ({len(err)} runs)")
    ax.plot([], [], color="#9aa6b2", lw=0.8, label="single trajectories")
    ax.set_yscale("log")
    ax.set_ylim(bottom=floor)
    ax.set_xlabel("time (s)")
    ax.set_ylabel(r"$\|z_{pred} - z_{true}\| \,/\, \|z_{true}\|$")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="major", lw=0.3, alpha=0.6)
    ax.legend(fontsize=8, loc="lower right")
    return _save(fig, path)


def _plot_energy(
    E_pred: np.ndarray, E_true: np.ndarray, scale: float, dt: float, path: Path, title: str
) -> Path:
    """Left: true energy along a few true (solid) and predicted (dashed) rollouts.
    Right: mean relative drift from the initial energy, with 95% bands."""
    from matplotlib.lines import Line2D

    palette = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b")
    fig = _figure(10.0, 3.8)
    ax1, ax2 = fig.subplots(1, 2)
    t = np.arange(E_true.shape[1]) * dt
    for i in range(min(len(E_true), len(palette))):
        ax1.plot(t, E_true[i], color=palette[i], lw=1.4)
        ax1.plot(t, E_pred[i], color=palette[i], lw=1.4, ls="--")
    ax1.legend(
        [Line2D([], [], color="k", lw=1.4), Line2D([], [], color="k", lw=1.4, ls="--")],
        ["ground truth", "model"],
        fontsize=8,
    )
    ax1.set_ylabel("true energy E")
    ax1.set_title("true energy along trajectories", fontsize=10)
    E0 = E_true[:, 0]
    for E, label, color, ls in (
        (E_true, "ground truth", "#444444", "-"),
        (E_pred, "model", "#d62728", "--"),
    ):
        d = _drift(E, E0, scale)
        d = d[np.isfinite(d).all(-1)]
        if len(d) == 0:
            continue
        mean, half = mean_ci95(d, axis=0)
        mean, half = np.atleast_1d(mean), np.nan_to_num(np.atleast_1d(half))
        ax2.fill_between(t, np.maximum(mean - half, 0.0), mean + half, color=color, alpha=0.2, lw=0)
        ax2.plot(t, mean, color=color, lw=1.8, ls=ls, label=label)
    ax2.set_ylabel(r"$|E(t) - E_{true}(0)| \,/\, \overline{T_{true}}$")
    ax2.set_title("relative energy drift (mean, 95% CI)", fontsize=10)
    ax2.legend(fontsize=8)
    for ax in (ax1, ax2):
        ax.set_xlabel("time (s)")
        ax.grid(True, lw=0.3, alpha=0.6)
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


_PANEL_TITLES = {
    "loss": "loss",
    "mass_ratios": r"mass ratios $m_i / m_1$",
    "mu": r"friction $\mu$",
    "cor": r"restitution $e_P$",
    "eps": r"CMr $\epsilon$",
}


def _training_series(
    log: Mapping[str, np.ndarray], true: Mapping[str, list[float]], n_bodies: int
) -> dict[str, list[tuple[str, np.ndarray, Any]]]:
    """Per panel: ``(label, values per epoch, true value, list of them, or None)``."""
    groups = _classify_columns(log)
    panels: dict[str, list[tuple[str, np.ndarray, Any]]] = {}
    if "loss" in groups:
        panels["loss"] = [(c, log[c], None) for c in sorted(groups["loss"])]
    series: list[tuple[str, np.ndarray]] = []
    ratios = groups.get("mass_ratios")
    masses = groups.get("mass")
    if ratios is not None:
        cols = [ratios[k] for k in sorted(ratios, key=lambda k: -1 if k is None else k)]
        if len(cols) == n_bodies:
            cols = cols[1:]  # the first body's ratio (1)
        series = [(f"m{k + 2}/m1", log[c]) for k, c in enumerate(cols)]
    elif masses is not None and None not in masses and len(masses) > 1:
        # raw masses per body: ratios to the first
        cols = [masses[k] for k in sorted(masses)]
        series = [(f"m{k + 2}/m1", log[c] / log[cols[0]]) for k, c in enumerate(cols[1:])]
    if series:
        tr = true["mass_ratios"]
        panels["mass_ratios"] = [
            (label, v, tr[k] if len(series) == len(tr) else None)
            for k, (label, v) in enumerate(series)
        ]
    for cat in ("mu", "cor"):
        if cat not in groups:
            continue
        tv = true[cat]
        items = []
        for idx in sorted(groups[cat], key=lambda k: -1 if k is None else k):
            col = groups[cat][idx]
            if idx is None or len(groups[cat]) == 1:
                # one shared learned value: every distinct true value is a reference
                items.append((cat, log[col], sorted(set(tv))))
            else:
                items.append((f"{cat}[{idx}]", log[col], tv[idx] if idx < len(tv) else None))
        panels[cat] = items
    if "eps" in groups:
        panels["eps"] = [("eps", log[c], None) for c in groups["eps"].values()]
    return panels


def _plot_training(
    log: Mapping[str, np.ndarray],
    true: Mapping[str, list[float]],
    n_bodies: int,
    path: Path,
    title: str,
) -> Path | None:
    """Losses and learned parameters per epoch; true values dashed in the same colour."""
    panels = _training_series(log, true, n_bodies)
    if not panels:
        return None
    import matplotlib
    from matplotlib.ticker import MaxNLocator

    epochs = log["epoch"]
    fig = _figure(3.6 * len(panels) + 0.4, 3.5)
    axes = np.atleast_1d(fig.subplots(1, len(panels)))
    for ax, (cat, series) in zip(axes, panels.items(), strict=True):
        many = len(series) > 10
        cmap = matplotlib.colormaps["viridis" if many else "tab10"]
        drawn_true: set[float] = set()
        for k, (label, values, ref) in enumerate(series):
            color = cmap(k / max(len(series) - 1, 1)) if many else cmap(k % 10)
            ok = np.isfinite(values)
            ax.plot(epochs[ok], values[ok], color=color, lw=1.0 if many else 1.5, label=label)
            refs = [] if ref is None else ref if isinstance(ref, list) else [ref]
            for r in refs:
                if r in drawn_true and (many or len(refs) > 1):
                    continue
                grey = many or len(refs) > 1
                ax.axhline(r, color="#555555" if grey else color, lw=1.0, ls="--")
                drawn_true.add(r)
        if cat == "loss":
            vals = np.concatenate([v[np.isfinite(v)] for _, v, _ in series])
            if vals.size and (vals > 0).all():
                ax.set_yscale("log")
        if len(series) <= 6:
            ax.legend(fontsize=7)
        else:
            ax.text(
                0.98, 0.98, f"{len(series)} contacts", transform=ax.transAxes,
                ha="right", va="top", fontsize=7,
            )  # fmt: skip
        ax.set_title(_PANEL_TITLES.get(cat, cat), fontsize=10)
        ax.set_xlabel("epoch")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(True, lw=0.3, alpha=0.6)
    fig.suptitle(f"{title} (dashed: true values)" if title else "dashed: true values", fontsize=10)
    return _save(fig, path)


# ---------------------------------------------------------------------------
# evaluate
# ---------------------------------------------------------------------------


def evaluate(
    run_dir: str | os.PathLike[str] | None,
    out_dir: str | os.PathLike[str] | None = None,
    *,
    model: Any = None,
    data_dir: str | os.PathLike[str] | None = None,
    n_gif: int = 4,
    device: str = "cpu",
    steps: int | None = None,
    n_test: int | None = None,
    gif_frames: int = 100,
) -> dict[str, Any]:
    """Evaluate a learned model on the test set and write metrics, plots and a GIF.

    Args:
        run_dir: a training run (``run.json`` with ``data_dir``, ``model.pt`` or
            ``checkpoints/``, ``logs/``). May be ``None`` when ``model`` and
            ``data_dir`` (and ``out_dir``) are given.
        out_dir: where to write (default ``RUN_DIR/evaluation``; created).
        model: an object with ``simulate(z0, steps)`` (``(N, 2, P, dim)`` ->
            ``(N, steps + 1, 2, P, dim)``) and ``learned_parameters()`` (dict
            with ``mass_ratios``, ``mu``, ``cor``, optionally ``eps``); default
            ``load_model(run_dir)``.
        data_dir: the dataset (``test.npz``, ``metadata.json``); default
            ``run.json``'s ``data_dir`` (as given, else relative to the run).
        n_gif: test trajectories in the GIF (0: no GIF).
        device: ``"cpu"`` or ``"cuda"`` for the rollouts.
        steps: rollout steps (default ``max(horizon / dt, 100) - 1``).
        n_test: use only the first ``n_test`` test trajectories.
        gif_frames: at most this many GIF frames.

    Returns:
        The metrics dict written to ``metrics.json`` (see ``docs/evaluation.md``).

    Raises:
        EvaluationInputError: missing run directory, checkpoint, test data or
            config; bad arguments; CUDA requested but unavailable.
    """
    import torch

    from diffcontact import __version__
    from diffcontact.systems import load_system

    # ---- arguments and files
    if not isinstance(n_gif, int) or isinstance(n_gif, bool) or n_gif < 0:
        raise EvaluationInputError(f"n_gif must be a non-negative integer, got {n_gif!r}")
    for name, value in (("steps", steps), ("n_test", n_test)):
        if value is not None and (
            not isinstance(value, int) or isinstance(value, bool) or value < 1
        ):
            raise EvaluationInputError(f"{name} must be a positive integer, got {value!r}")
    if device not in ("cpu", "cuda") and not str(device).startswith("cuda:"):
        raise EvaluationInputError(f"device must be 'cpu' or 'cuda', got {device!r}")
    if str(device).startswith("cuda") and not torch.cuda.is_available():
        raise EvaluationInputError("device 'cuda' requested but CUDA is not available (use cpu)")
    run_path = None if run_dir is None else Path(run_dir)
    run: dict[str, Any] = {}
    if run_path is not None:
        if not run_path.is_dir():
            raise EvaluationInputError(f"run directory {run_path} does not exist")
        if (run_path / "run.json").is_file():
            run = _read_json(run_path / "run.json", "run file")
        elif model is None:
            raise EvaluationInputError(f"{run_path} is not a training run (no run.json)")
        if model is None and not _has_checkpoint(run_path):
            raise EvaluationInputError(
                f"no trained model in {run_path}: expected model.pt or checkpoints/*.ckpt"
            )
    elif model is None:
        raise EvaluationInputError("give a run directory or a model")
    data_path = _resolve_data_dir(run_path, run, data_dir)
    traj = _load_test(data_path)
    metadata: dict[str, Any] = {}
    if (data_path / "metadata.json").is_file():
        metadata = _read_json(data_path / "metadata.json", "dataset metadata")
    config = metadata.get("config") or run.get("config") or getattr(model, "config", None)
    if config is None:
        raise EvaluationInputError(
            f"no system config: {data_path}/metadata.json and run.json hold none"
        )
    try:
        system = load_system(config)
    except ValueError as err:
        raise EvaluationInputError(f"bad system config: {err}") from None
    if tuple(traj.shape[2:]) != system.state_shape:
        raise EvaluationInputError(
            f"{data_path}/test.npz: states have shape {tuple(traj.shape[2:])}, but the system "
            f"{system.name} has {system.state_shape}"
        )
    if out_dir is None:
        if run_path is None:
            raise EvaluationInputError("give out_dir when there is no run directory")
        out_dir = run_path / "evaluation"
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise EvaluationInputError(f"cannot create output folder {out}: {err}") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise EvaluationInputError(f"output folder {out} is not writable")

    # ---- model
    if model is None:
        from diffcontact.learning.model import load_model

        try:
            model = load_model(run_path)
        except (FileNotFoundError, ValueError) as err:
            raise EvaluationInputError(f"cannot load the model of {run_path}: {err}") from None
    dev = torch.device(device)
    if isinstance(model, torch.nn.Module):
        model = model.to(dev).eval()

    # ---- rollouts
    dt = system.dt
    steps = rollout_steps(system) if steps is None else steps
    if n_test is not None:
        traj = traj[:n_test]
    N = traj.shape[0]
    z0 = torch.as_tensor(traj[:, 0], dtype=torch.float64, device=dev)
    with torch.no_grad():
        if traj.shape[1] >= steps + 1:
            true = traj[:, : steps + 1]
            source = "test set"
        else:
            true = _np(system.simulate(z0, steps))
            source = "simulated (test trajectories shorter than the rollout)"
        pred = _np(model.simulate(z0, steps))
    if pred.shape != true.shape:
        raise RuntimeError(
            f"model.simulate returned shape {pred.shape}, expected {true.shape} "
            "(N, steps + 1, 2, P, dim)"
        )

    # ---- metrics
    err = relative_error(pred, true)  # (N, T)
    finite = np.isfinite(err).all(1)
    n_bad = int((~finite).sum())
    err_ok = err[finite]
    later = slice(1, None) if err.shape[1] > 1 else slice(None)  # step 0 is exact
    if len(err_ok):
        rel_mean, rel_ci = mean_ci95(err_ok[:, later].mean(1))
        curve_mean, curve_ci = mean_ci95(err_ok, axis=0)
    else:
        rel_mean = rel_ci = math.nan
        curve_mean = curve_ci = np.full(err.shape[1], np.nan)
    E_pred, E_true = true_energy(system, pred), true_energy(system, true)
    E0, scale = E_true[:, 0], energy_scale(system, true)
    drift_pred, drift_true = _drift(E_pred, E0, scale), _drift(E_true, E0, scale)
    gap = np.abs(E_pred - E_true) / scale if scale > 0 else np.full(E_pred.shape, np.nan)

    truth = true_parameters(system)
    learned = _learned(model.learned_parameters(), system.n_bodies)
    task = str(metadata.get("task") or system.name)
    label = _model_label(model, run)
    metrics: dict[str, Any] = {
        "format_version": METRICS_FORMAT_VERSION,
        "task": task,
        "model": label,
        "n_test": N,
        "n_nonfinite": n_bad,
        "steps": steps,
        "dt": dt,
        "duration": steps * dt,
        "ground_truth": source,
        "rel_err_mean": rel_mean,
        "rel_err_ci95": rel_ci,
        "rel_err_final": float(np.atleast_1d(curve_mean)[-1]),
        "rel_err_curve": {"mean": curve_mean, "ci95": curve_ci},
        "energy_rel_drift": {
            "pred": _finite_mean(drift_pred),
            "true": _finite_mean(drift_true),
        },
        "energy_rel_error": _finite_mean(gap),
        "mass_ratios": _compare(learned["mass_ratios"], truth["mass_ratios"], relative=True),
        "mu": _compare(learned["mu"], truth["mu"], relative=False),
        "cor": _compare(learned["cor"], truth["cor"], relative=False),
        "eps": learned["eps"],
        "contact_names": list(getattr(system, "contact_names", [])),
        "device": str(device),
        "run_dir": None if run_path is None else str(run_path),
        "data_dir": str(data_path),
        "diffcontact_version": __version__,
    }

    # ---- files
    files = ["metrics.json", "rollout.npz"]
    atomic_save_npz(
        out / "rollout.npz",
        compress=True,
        pred=pred,
        true=true,
        rel_err=err,
        energy_pred=E_pred,
        energy_true=E_true,
        t=np.arange(steps + 1, dtype=np.float64) * dt,
    )
    title = f"{task}: {label}"
    _plot_rel_error(err_ok if len(err_ok) else err, dt, out / "rel_error.png", title)
    files.append("rel_error.png")
    _plot_energy(E_pred, E_true, scale, dt, out / "energy.png", title)
    files.append("energy.png")
    log_path = None if run_path is None else find_training_log(run_path)
    if log_path is not None:
        log = read_training_log(log_path)
        if log and _plot_training(log, truth, system.n_bodies, out / "training.png", title):
            files.append("training.png")
    if n_gif > 0:
        from diffcontact.viz import animate, scene_from_system

        k = min(n_gif, N)
        animate(
            true[:k],
            scene_from_system(system, title=f"{task}: truth (filled) vs {label} (dashed)"),
            out / "rollout.gif",
            overlay=pred[:k],
            dt=dt,
            max_trajectories=k,
            max_frames=gif_frames,
            labels=("ground truth", label),
        )
        files.append("rollout.gif")
    metrics["files"] = sorted(files)
    metrics = _jsonable(metrics)
    text = json.dumps(metrics, indent=2, allow_nan=False) + "\n"
    atomic_write_bytes(out / "metrics.json", text.encode())
    return metrics


# ---------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------


def register_cli(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``evaluate RUN_DIR [--out DIR --device cpu|cuda --n-gif 4 ...]`` to a CLI.

    ``subparsers`` is what ``ArgumentParser.add_subparsers()`` returns. The
    handler is set as ``func``; it returns the exit status (0; 2 for bad
    input with a one-line message on stderr; 1 when the evaluation fails).
    """
    p = subparsers.add_parser(
        "evaluate",
        help="evaluate a trained model: rollout error, energy, learned parameters, plots",
        description=(
            "Roll the trained model of RUN_DIR out from every test initial state for "
            "max(horizon, 100 dt), compare with the ground truth and write metrics.json, "
            "rollout.npz, rel_error.png, energy.png, training.png and rollout.gif."
        ),
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="training run directory")
    p.add_argument(
        "--out", default=None, metavar="DIR", help="output folder (default RUN_DIR/evaluation)"
    )
    p.add_argument(
        "--device", choices=("cpu", "cuda"), default="cpu", help="rollout device (default cpu)"
    )
    p.add_argument(
        "--n-gif",
        type=int_at_least(0),
        default=4,
        help="test trajectories in the GIF (default 4; 0: none)",
    )
    p.add_argument(
        "--steps",
        type=int_at_least(1),
        default=None,
        help="rollout steps (default max(horizon/dt, 100) - 1)",
    )
    p.add_argument(
        "--n-test", type=int_at_least(1), default=None, help="use the first N test trajectories"
    )
    p.add_argument(
        "--data", default=None, metavar="DIR", help="dataset folder (default: run.json's)"
    )
    p.set_defaults(func=_cmd_evaluate)
    return p


def _one_line(err: BaseException) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    return "; ".join(lines) if lines else type(err).__name__


def _fmt(x: Any) -> str:
    if x is None:
        return "-"
    return f"{x:.4g}"


def _param_rows(
    name: str, entry: Mapping[str, Any], labels: Sequence[str], shared: bool = True
) -> list[str]:
    learned, true = entry.get("learned"), entry.get("true") or []
    if learned is None:
        return [f"  {name:<16} {'-':>10} {'(not learned)':>10}"]
    if shared and len(set(learned)) <= 1 and len(set(true)) <= 1 and true:
        return [f"  {name:<16} {learned[0]:>10.4f} {true[0]:>10.4f}"]
    if len(learned) == len(true) and len(true) <= 12:
        return [
            f"  {lab:<16} {lv:>10.4f} {tv:>10.4f}"
            for lab, lv, tv in zip(labels, learned, true, strict=True)
        ]
    err = entry.get("max_abs_error", entry.get("max_rel_error"))
    return [
        f"  {name:<16} {len(learned)} learned, {len(true)} true values; "
        f"max error {_fmt(err)} (see metrics.json)"
    ]


def _cmd_evaluate(args: argparse.Namespace) -> int:
    prog = "diffcontact evaluate"
    try:
        m = evaluate(
            args.run_dir,
            args.out,
            data_dir=args.data,
            n_gif=args.n_gif,
            device=args.device,
            steps=args.steps,
            n_test=args.n_test,
        )
    except EvaluationInputError as err:
        print(f"{prog}: error: {_one_line(err)}", file=sys.stderr)
        return 2
    except (RuntimeError, ValueError, OSError) as err:
        print(
            f"{prog}: error: evaluation failed: {type(err).__name__}: {_one_line(err)}",
            file=sys.stderr,
        )
        return 1
    out = Path(args.out) if args.out else Path(args.run_dir) / "evaluation"
    print(
        f"{m['task']}: {m['model']}, {m['n_test']} test trajectories x {m['steps']} steps "
        f"(dt {m['dt']:g} s; ground truth: {m['ground_truth']})"
    )
    if m["n_nonfinite"]:
        print(f"  WARNING: {m['n_nonfinite']} rollouts diverged (non-finite); left out below")
    print(
        f"  relative error   {_fmt(m['rel_err_mean'])} ± {_fmt(m['rel_err_ci95'])} (95% CI), "
        f"final step {_fmt(m['rel_err_final'])}"
    )
    drift = m["energy_rel_drift"]
    print(
        f"  energy drift     model {_fmt(drift['pred'])}, ground truth {_fmt(drift['true'])} "
        "(true energy, per mean kinetic energy)"
    )
    print(f"  {'parameter':<16} {'learned':>10} {'true':>10}")
    n_ratios = len(m["mass_ratios"]["true"])
    labels = [f"m{i + 2}/m1" for i in range(n_ratios)]
    rows = _param_rows("mass ratios", m["mass_ratios"], labels, shared=False)
    for key, sym in (("mu", "mu"), ("cor", "e_P")):
        K = len(m[key]["true"])
        rows += _param_rows(sym, m[key], [f"{sym}[{k}]" for k in range(K)])
    if m.get("eps") is not None:
        rows.append(f"  {'eps (CMr)':<16} {_fmt(m['eps']):>10} {'-':>10}")
    print("\n".join(rows))
    print(f"  wrote {out}{os.sep}: {', '.join(m['files'])}")
    return 0
