"""Simulated datasets: :func:`generate_dataset` (``diffcontact generate TASK``)."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from diffcontact.contact.registry import create_contact_model
from diffcontact.io import jsonable, parse_device
from diffcontact.learning.data.checks import check_seed, float_arg, int_arg
from diffcontact.learning.data.chunks import chunk_split, contact_states
from diffcontact.learning.data.format import SPLITS, split_seeds
from diffcontact.learning.data.write import prepare_folder, write_dataset
from diffcontact.systems import load_system

__all__ = ["generate_dataset"]


def generate_dataset(
    spec: Any,
    out_dir: str | Path,
    *,
    n_train: int = 800,
    n_val: int = 100,
    n_test: int = 100,
    seed: int = 0,
    noise_std: float = 0.0,
    chunk_length: int = 5,
    contact_fraction: float = 0.5,
    progress: bool = True,
    device: str | torch.device = "cpu",
    contact_model: str = "CM",
    stride: int | None = None,
) -> Path:
    """Simulate, chunk and save a train/val/test dataset of a task (``docs/data.md``).

    Initial conditions are sampled with the seeds ``seed * 1000 + 0/1/2``
    (train/val/test), full trajectories (``horizon / dt`` states, float64) are
    simulated, the states in contact (any gap < 0) marked, one chunk of
    ``chunk_length`` states per trajectory picked whose first state is out of
    contact (``select_chunks``; about ``contact_fraction`` of the chunks
    contain a contact), and Gaussian noise added to the chunks only (for a
    chain pendulum on the link angles and angular velocities).

    Args:
        spec: built-in task name, ``.yaml``/``.json`` config path or dict.
        out_dir: dataset folder (created; must be empty, or hold a dataset
            made with the same arguments, which is then reused).
        n_train, n_val, n_test: trajectories per split (``n_train >= 1``).
        seed: base seed; the splits use ``seed * 1000 + 0/1/2``
            (``split_seeds``), so they hold different trajectories.
        noise_std: std of the Gaussian noise added to the chunks only (for a
            chain pendulum to the link angles and angular velocities).
        chunk_length: states per chunk (``>= 2``).
        contact_fraction: target share of chunks containing a contact.
        progress: progress bars and messages (including "reusing ...").
        device: where to simulate (the files are the same float64 arrays).
        contact_model: the registered contact model that simulates the ground
            truth (``diffcontact.contact.contact_models()``); recorded in
            ``metadata.json``, and evaluation re-simulates with it.
        stride: ``None`` (default, the paper's set-up): one chunk per
            trajectory; an integer ``k``: every window starting at states
            ``0, k, 2k, ...`` (out of contact) is a chunk, and
            ``contact_fraction`` becomes a sampling weight in training
            (``docs/data.md``, "Windows").

    Returns:
        The dataset folder.

    Raises:
        ValueError: bad arguments or config; ``out_dir`` holds a dataset made
            with different arguments (the message names them), other files, or
            a reused dataset whose files fail their checksums.
    """
    counts = {
        "train": int_arg("n_train", n_train, 1),
        "val": int_arg("n_val", n_val, 0),
        "test": int_arg("n_test", n_test, 0),
    }
    seed = check_seed(seed)
    noise_std = float_arg("noise_std", noise_std, 0.0, math.inf)
    chunk_length = int_arg("chunk_length", chunk_length, 2)
    contact_fraction = float_arg("contact_fraction", contact_fraction, 0.0, 1.0)
    if stride is not None:
        stride = int_arg("stride", stride, 1)
    dev = parse_device(device)
    system = load_system(spec)
    if not isinstance(contact_model, str):
        raise ValueError(f"contact_model must be a registered name, got {contact_model!r}")
    create_contact_model(contact_model)  # an unknown name lists the registered ones
    T = system.default_steps + 1
    if T < chunk_length:
        raise ValueError(
            f"{system.name}'s trajectories hold {T} states (horizon / dt), fewer than "
            f"chunk_length={chunk_length}"
        )
    arguments = {
        "source": "simulated",
        "config": jsonable(system.config.model_dump(mode="json")),
        "n_train": counts["train"],
        "n_val": counts["val"],
        "n_test": counts["test"],
        "seed": seed,
        "noise_std": noise_std,
        "chunk_length": chunk_length,
        "contact_fraction": contact_fraction,
    }
    if contact_model != "CM":  # CM datasets keep the arguments of earlier versions (reuse)
        arguments["contact_model"] = contact_model
    if stride is not None:  # so do datasets of one chunk per trajectory
        arguments["stride"] = stride
    folder = Path(out_dir)
    if prepare_folder(folder, arguments, progress):
        return folder

    seeds = split_seeds(seed)
    P, d = system.n_points, system.dim
    splits: dict[str, dict[str, np.ndarray]] = {}
    for name in SPLITS:
        n = counts[name]
        if n == 0:
            traj = np.zeros((0, T, 2, P, d))
        else:
            if progress:
                print(f"{system.name} {name}: {n} trajectories of {T} states", file=sys.stderr)
            with torch.no_grad():
                z0 = system.sample_initial_conditions(n, seed=seeds[name], device=dev)
                traj_t = system.simulate(
                    z0, steps=T - 1, progress=progress, contact_model=contact_model
                )
            traj = traj_t.to(torch.float64).cpu().numpy()
        contact = contact_states(system, traj)
        splits[name] = chunk_split(
            system, traj, contact, seeds[name], chunk_length, contact_fraction, noise_std,
            stride, name,
        )  # fmt: skip
    write_dataset(folder, system, splits, arguments, device=str(dev))
    return folder
