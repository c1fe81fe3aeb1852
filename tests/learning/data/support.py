"""Constants and helpers shared by the dataset tests."""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
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


def read_only_storage(monkeypatch: pytest.MonkeyPatch, folder: Path) -> list[str]:
    """Make every write under ``folder`` fail as on read-only storage; return the attempts.

    Creating files (``tempfile.mkstemp``, as ``diffcontact.io``'s atomic writers do),
    making folders, renaming and removing files raise ``OSError(EROFS)``, removing one
    even when it does not exist, as Linux does (so ``Path.unlink(missing_ok=True)``
    fails there), and ``os.access(..., W_OK)`` is False. Works for root, whom
    permission bits do not stop.
    """
    root = os.path.abspath(folder)
    attempts: list[str] = []

    def inside(path: object) -> bool:
        text = os.path.abspath(os.fspath(path))  # type: ignore[arg-type]
        return text == root or text.startswith(root + os.sep)

    def refuse(name: str, path: object) -> None:
        if path is not None and inside(path):
            attempts.append(f"{name} {os.fspath(path)}")  # type: ignore[arg-type]
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), os.fspath(path))  # type: ignore[arg-type]

    def one_path(name: str):
        real = getattr(os, name)

        def wrapper(path, *args, **kwargs):
            refuse(name, path)
            return real(path, *args, **kwargs)

        return wrapper

    def two_paths(name: str):
        real = getattr(os, name)

        def wrapper(src, dst, *args, **kwargs):
            refuse(name, src)
            refuse(name, dst)
            return real(src, dst, *args, **kwargs)

        return wrapper

    real_mkstemp = tempfile.mkstemp

    def mkstemp(suffix=None, prefix=None, dir=None, text=False):
        refuse("mkstemp", dir if dir is not None else tempfile.gettempdir())
        return real_mkstemp(suffix, prefix, dir, text)

    real_access = os.access

    def access(path, mode, *args, **kwargs):
        if mode & os.W_OK and inside(path):
            return False  # access(2) answers EROFS there, for root too
        return real_access(path, mode, *args, **kwargs)

    monkeypatch.setattr(os, "access", access)
    for name in ("unlink", "remove", "rmdir", "mkdir"):
        monkeypatch.setattr(os, name, one_path(name))
    for name in ("replace", "rename"):
        monkeypatch.setattr(os, name, two_paths(name))
    monkeypatch.setattr(tempfile, "mkstemp", mkstemp)
    return attempts
