"""The training log: Lightning's ``metrics.csv`` read per epoch, its columns classified.

:func:`find_training_log` finds a run's log, :func:`read_training_log` reads
it per epoch and :func:`classify_columns` sorts its columns into losses and
learned parameters (mass ratios, mu, e_P, eps) for the training plot.
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["classify_columns", "find_training_log", "read_training_log"]


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


# learned-parameter columns are the models' metrics(): "param/<quantity>" or
# "param/<quantity>_<index>" (the DynamicsModel protocol); these quantities get panels
_CATEGORY = {"mass_ratio": "mass_ratios", "mass": "mass", "mu": "mu", "cor": "cor", "eps": "eps"}


def _parameter(base: str) -> tuple[str, int | None] | None:
    """``"param/mu_3"`` -> ``("mu", 3)``, ``"param/cor"`` -> ``("cor", None)``; else None."""
    if not base.startswith("param/"):
        return None
    name = base[len("param/") :]
    head, _, tail = name.rpartition("_")
    if head and tail.isdigit():
        return head, int(tail)
    return name, None


def classify_columns(log: Mapping[str, np.ndarray]) -> dict[str, dict[Any, str]]:
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
        parsed = _parameter(base)
        if parsed is None or parsed[0] not in _CATEGORY:
            continue
        groups.setdefault(_CATEGORY[parsed[0]], {})[parsed[1]] = col
    return groups
