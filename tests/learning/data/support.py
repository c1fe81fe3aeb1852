"""Constants and helpers shared by the dataset tests."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np
import torch

from diffcontact.learning.data.format import load_dataset
from diffcontact.systems import load_config

SIZES = {"n_train": 6, "n_val": 3, "n_test": 3}
L = 5


def short_config(task: str, horizon: float) -> dict:
    """A built-in task with a shorter horizon (fewer states: faster tests)."""
    return load_config(task, horizon=horizon).model_dump(mode="json")


BP5 = short_config("BP5", 0.2)  # 20 states
CP3 = short_config("CP3", 0.3)  # 30 states


def copy_dataset(src: Path, tmp_path: Path) -> Path:
    dst = tmp_path / src.name
    shutil.copytree(src, dst)
    return dst


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def window_contact(
    contact: torch.Tensor, start: torch.Tensor, owner: torch.Tensor | None = None
) -> torch.Tensor:
    """The flags ``(M, L)`` of chunks starting at ``start`` in trajectories ``owner`` (all)."""
    idx = start[:, None] + torch.arange(L)
    return (contact if owner is None else contact[owner]).gather(1, idx)


def all_trajectories(folder: Path) -> np.ndarray:
    ds = load_dataset(folder)
    return torch.cat([ds.split(s).traj for s in ("train", "val", "test")]).numpy()
