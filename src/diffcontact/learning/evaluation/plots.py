"""The evaluation plots: relative error, energy and the training curves (PNG).

matplotlib ``Figure`` objects with the Agg canvas (no pyplot state), saved
atomically.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import MaxNLocator

from diffcontact.io import atomic_path
from diffcontact.learning.evaluation.log import classify_columns
from diffcontact.learning.evaluation.metrics import energy_drifts, mean_ci95

__all__ = ["plot_energy", "plot_rel_error", "plot_training"]


def _figure(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height))
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: Path, dpi: int = 110) -> Path:
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    return path


def plot_rel_error(err: np.ndarray, dt: float, path: Path, title: str, n_left_out: int = 0) -> Path:
    """Mean relative error per step with its 95% band (log y), faint single runs.

    ``err: (N, T)``: the finite rollouts' errors; ``n_left_out`` rollouts that diverged
    (non-finite) are named in the legend. With no finite rollout the figure says so
    instead of drawing anything. Exact zeros (e.g. before the first contact) cannot be
    drawn on a log axis: they sit on the bottom edge, at most 1e-6 (or a tenth of the
    smallest positive mean, if lower), which the figure labels.
    """
    fig = _figure(6.4, 3.8)
    ax = fig.subplots()
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("time (s)")
    ax.set_ylabel(r"$\|z_{pred} - z_{true}\| \,/\, \|z_{true}\|$")
    if len(err) == 0:
        ax.text(
            0.5, 0.5, f"no finite rollout: all {n_left_out} diverged (NaN or infinite)",
            ha="center", va="center", transform=ax.transAxes, fontsize=11, color="#b00000",
        )  # fmt: skip
        ax.set_xticks([])
        ax.set_yticks([])
        return _save(fig, path)
    t = np.arange(err.shape[1]) * dt
    sl = slice(1, None) if err.shape[1] > 1 else slice(None)  # step 0 is exact
    mean, half = mean_ci95(err, axis=0)
    mean = np.atleast_1d(mean)[sl]
    half = np.nan_to_num(np.atleast_1d(half))[sl]
    t = t[sl]
    positive = mean[mean > 0]
    floor = 0.1 * float(positive.min()) if positive.size else 1e-16
    zeros = bool((mean <= 0).any())
    if zeros:  # far enough below anything measured not to read as a value
        floor = min(floor, 1e-6)
    for e in err[:30]:
        ax.plot(t, np.maximum(e[sl], floor), color="#9aa6b2", lw=0.5, alpha=0.6)
    # the symmetric interval reaches far below every trajectory on the log axis where the
    # errors are skewed; the mean is never below the smallest of them: cut there
    lowest = np.min(err, axis=0)[sl]
    ax.fill_between(
        t,
        np.maximum(np.maximum(mean - half, lowest), floor),
        np.maximum(mean + half, floor),
        color="#1f77b4",
        alpha=0.25,
        lw=0,
        label="95% CI of the mean (cut at the smallest trajectory)",
    )
    n = len(err)
    runs = f"mean of {n} test trajector{'y' if n == 1 else 'ies'}" + (
        f" ({n_left_out} diverged, left out)" if n_left_out else ""
    )
    ax.plot(t, np.maximum(mean, floor), color="#1f77b4", lw=2.0, label=runs)
    ax.plot([], [], color="#9aa6b2", lw=0.8, label="single trajectories")
    if zeros:
        ax.plot([], [], ls="none", label=f"exact zeros drawn at the bottom edge ({floor:.0e})")
    ax.set_yscale("log")
    ax.set_ylim(bottom=floor)
    ax.grid(True, which="major", lw=0.3, alpha=0.6)
    ax.legend(fontsize=8, loc="lower right")
    return _save(fig, path)


def plot_energy(
    E_pred: np.ndarray, E_true: np.ndarray, scale: float, dt: float, path: Path, title: str
) -> Path:
    """Left: true energy along a few true (solid) and predicted (dashed) rollouts.
    Right: mean relative drift from the initial energy, with 95% bands, of the truth and
    the model over the same trajectories (:func:`~.metrics.energy_drifts`: those whose
    predicted energy is finite; the title says how many when some are left out)."""
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
    ax1.set_ylabel("true energy E (J)")
    ax1.set_title("true energy along trajectories", fontsize=10)
    drift_pred, drift_true, rows = energy_drifts(E_pred, E_true, scale)
    n, N = int(rows.sum()), len(rows)
    for d, label, color, ls in (
        (drift_true, "ground truth", "#444444", "-"),
        (drift_pred, "model", "#d62728", "--"),
    ):
        d = d[rows]
        if len(d) == 0:
            continue
        mean, half = mean_ci95(d, axis=0)
        mean, half = np.atleast_1d(mean), np.nan_to_num(np.atleast_1d(half))
        # edged: the truth's and the model's bands stay apart where they overlap
        ax2.fill_between(
            t, np.maximum(mean - half, 0.0), mean + half, color=color, alpha=0.15,
            lw=0.8, ls=ls, edgecolor=color,
        )  # fmt: skip
        ax2.plot(t, mean, color=color, lw=1.8, ls=ls, label=label)
    ax2.set_ylabel(r"$|E(t) - E_{true}(0)| \,/\, \overline{T_{true}}$")
    what = "energy change from E(0): contacts and drift (mean, 95% CI)"
    if n < N:  # both curves over the trajectories whose rollout stayed finite
        what += f"\nover the {n} of {N} trajectories whose predicted energy is finite"
    ax2.set_title(what, fontsize=10)
    if n:
        ax2.legend(fontsize=8)
    else:
        why = (
            f"no trajectory to compare: all {N} predicted energies diverged"
            if np.isfinite(drift_true).all()
            else "no drift: the true trajectories hold no kinetic energy (the unit)"
        )
        ax2.text(
            0.5, 0.5, why, ha="center", va="center", transform=ax2.transAxes, fontsize=10,
            color="#b00000",
        )  # fmt: skip
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


FEW_EPOCHS = 20
"""Training curves of at most this many epochs mark each epoch's value with a dot."""

_SHOWN = {"mu": "mu", "cor": "e_P"}
"""The learned-parameter columns' names as the docs write them (``cor`` is e_P)."""


def _training_series(
    log: Mapping[str, np.ndarray],
    true: Mapping[str, list[float]] | None,
    n_bodies: int,
    final: Mapping[str, Any] | None = None,
) -> dict[str, list[tuple[str, np.ndarray, Any, float | None]]]:
    """Per panel: ``(label, values per epoch, true value, list of them, or None, final
    value or None)``.

    ``true=None``: the true values are unknown (recorded data); none is given.
    ``final``: the model's learned parameters (``learned_parameters()``) where they
    differ from the log's last epoch (a refit), else ``None``.
    """

    def last(cat: str, k: int | None) -> float | None:
        values = None if final is None else final.get(cat)
        if values is None:
            return None
        values = list(values) if isinstance(values, (list, tuple)) else [values]
        k = 0 if k is None else k
        return float(values[k]) if k < len(values) else None

    groups = classify_columns(log)
    panels: dict[str, list[tuple[str, np.ndarray, Any]]] = {}
    if "loss" in groups:
        panels["loss"] = [(c, log[c], None, None) for c in sorted(groups["loss"])]
    series: list[tuple[str, np.ndarray]] = []
    ratios = groups.get("mass_ratios")
    masses = groups.get("mass")
    if ratios is not None:
        cols = [ratios[k] for k in sorted(ratios, key=lambda k: -1 if k is None else k)]
        if len(cols) == n_bodies:
            cols = cols[1:]  # the first body's ratio (1)
        series = [(f"m{k + 2}/m1", log[c]) for k, c in enumerate(cols)]  # body k + 1
    elif masses is not None and None not in masses and len(masses) > 1:
        # raw masses per body: ratios to the first
        cols = [masses[k] for k in sorted(masses)]
        series = [(f"m{k + 2}/m1", log[c] / log[cols[0]]) for k, c in enumerate(cols[1:])]
    if series:
        tr = [] if true is None else true["mass_ratios"]
        panels["mass_ratios"] = [
            (label, v, tr[k] if len(series) == len(tr) else None, last("mass_ratios", k + 1))
            for k, (label, v) in enumerate(series)
        ]
    for cat in ("mu", "cor"):
        if cat not in groups:
            continue
        tv = None if true is None else true[cat]
        items = []
        name = _SHOWN[cat]
        for idx in sorted(groups[cat], key=lambda k: -1 if k is None else k):
            col = groups[cat][idx]
            label = name if idx is None else f"{name}[{idx}]"
            if tv is None:
                items.append((label, log[col], None, last(cat, idx)))
            elif idx is None or len(groups[cat]) == 1:
                # one shared learned value: every distinct true value is a reference
                items.append((name, log[col], sorted(set(tv)), last(cat, idx)))
            else:
                ref = tv[idx] if idx < len(tv) else None
                items.append((label, log[col], ref, last(cat, idx)))
        panels[cat] = items
    if "eps" in groups:
        eps = None if final is None or final.get("eps") is None else float(final["eps"])
        panels["eps"] = [("eps", log[c], None, eps) for c in groups["eps"].values()]
    return panels


def plot_training(
    log: Mapping[str, np.ndarray],
    true: Mapping[str, list[float]] | None,
    n_bodies: int,
    path: Path,
    title: str,
    refit: Mapping[str, Any] | None = None,
) -> Path | None:
    """Losses and learned parameters per epoch; true values dashed in the same colour.

    ``true=None`` (recorded data without declared parameters): no true values
    are drawn and the title says that they are unknown. ``refit``: the model's learned
    parameters after ``diffcontact refit`` (``learned_parameters()``), drawn as a marker
    each after the last epoch (the log ends where Adam left them).
    """
    panels = _training_series(log, true, n_bodies, refit)
    if not panels:
        return None
    epochs = log["epoch"]
    fig = _figure(3.6 * len(panels) + 0.4, 3.5)
    axes = np.atleast_1d(fig.subplots(1, len(panels)))
    for ax, (cat, series) in zip(axes, panels.items(), strict=True):
        many = len(series) > 10
        cmap = matplotlib.colormaps["viridis" if many else "tab10"]
        drawn_true: set[float] = set()
        for k, (label, values, ref, after) in enumerate(series):
            color = cmap(k / max(len(series) - 1, 1)) if many else cmap(k % 10)
            ok = np.isfinite(values)
            # few epochs: a marker at each (one epoch drew a line through one point: nothing)
            dots = {"marker": "o", "ms": 2.5 if many else 3.5} if ok.sum() <= FEW_EPOCHS else {}
            ax.plot(
                epochs[ok], values[ok], color=color, lw=1.0 if many else 1.5, label=label, **dots
            )
            if after is not None and len(epochs):
                ax.plot([epochs[-1] + 0.5], [after], marker="D", ms=4, color=color, ls="none")
            refs = [] if ref is None else ref if isinstance(ref, list) else [ref]
            for r in refs:
                if r in drawn_true and (many or len(refs) > 1):
                    continue
                grey = many or len(refs) > 1
                ax.axhline(r, color="#555555" if grey else color, lw=1.0, ls="--")
                drawn_true.add(r)
        if cat == "loss":
            vals = np.concatenate([v[np.isfinite(v)] for _, v, _, _ in series])
            # log where the loss spans a decade or more (else its ticks crowd, 1.125e-1 ...)
            if vals.size and (vals > 0).all() and vals.max() >= 10 * vals.min():
                ax.set_yscale("log")
            ax.set_ylabel("mean absolute error")
        if len(series) <= 6:
            ax.legend(fontsize=7)
        else:
            what = "ratios" if cat == "mass_ratios" else "contacts"  # (not "9 contacts")
            ax.text(
                0.98, 1.01, f"{len(series)} {what}", transform=ax.transAxes,
                ha="right", va="bottom", fontsize=7,
            )  # fmt: skip
        ax.set_title(_PANEL_TITLES.get(cat, cat), fontsize=10)
        ax.set_xlabel("epoch")
        # integer epochs, also for one epoch (min_n_ticks=1: the default 2 found no
        # integer in the +-0.05 around a single point and fell back to -0.045, -0.030 ...)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True, min_n_ticks=1))
        if len(epochs) and epochs[-1] - epochs[0] < 1:  # one epoch: room around its point
            ax.set_xlim(epochs[0] - 0.5, epochs[-1] + (1.0 if refit is not None else 0.5))
        ax.grid(True, lw=0.3, alpha=0.6)
    note = "dashed: true values" if true is not None else "true values unknown: recorded data"
    if refit is not None:
        note += "; diamonds: after the refit"
    fig.suptitle(f"{title} ({note})" if title else note, fontsize=10)
    return _save(fig, path)
