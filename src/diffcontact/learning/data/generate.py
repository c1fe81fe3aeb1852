"""Simulated datasets: :func:`generate_dataset` (``diffcontact generate TASK``).

The splits are simulated one after the other, and each split's file is written
(atomically) as soon as it is ready, while the marker of the run in progress is in
place; ``metadata.json`` comes last. Re-running an interrupted run with the same
arguments reuses every split file it finished (the seeds make a split
deterministic, so a reused split equals a simulated one) and simulates the others;
a leftover file that does not load as that split is removed and simulated again.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from diffcontact.contact.registry import create_contact_model
from diffcontact.io import jsonable, parse_device, read_npz
from diffcontact.learning.data.checks import check_seed, check_stride, float_arg, int_arg
from diffcontact.learning.data.chunks import chunk_split, contact_states
from diffcontact.learning.data.format import ARRAYS, SPLITS, WINDOW_ARRAYS, split_seeds
from diffcontact.learning.data.write import (
    output_folder,
    prepare_folder,
    say,
    write_dataset,
    write_split,
)
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

    Each split's file is written as soon as the split is ready, ``metadata.json``
    last. A run interrupted before ``metadata.json`` is finished by re-running
    it with the same arguments: the split files it wrote are reused (when they
    load as complete splits of the requested sizes; others are removed and
    simulated again), the missing splits simulated.

    Args:
        spec: built-in task name, ``.yaml``/``.json`` config path or dict.
        out_dir: dataset folder (created; must be empty, or hold a dataset
            made with the same arguments, which is then reused, or the
            leftovers of an interrupted run with the same arguments, which is
            then finished).
        n_train, n_val, n_test: trajectories per split (``n_train >= 1``).
        seed: base seed; the splits use ``seed * 1000 + 0/1/2``
            (``split_seeds``), so they hold different trajectories.
        noise_std: std of the Gaussian noise added to the chunks only (for a
            chain pendulum to the link angles and angular velocities).
        chunk_length: states per chunk (``>= 2``).
        contact_fraction: target share of chunks containing a contact.
        progress: progress bars and messages (including "reusing ...", for a
            finished dataset or a split of an interrupted run).
        device: where to simulate (the files are the same float64 arrays).
        contact_model: the registered contact model that simulates the ground
            truth (``diffcontact.contact.contact_models()``); recorded in
            ``metadata.json``, and evaluation re-simulates with it.
        stride: ``None`` (default, the paper's set-up): one chunk per
            trajectory; an integer ``k``: every window starting at states
            ``0, k, 2k, ...`` (out of contact) is a chunk (``k`` of
            ``T - chunk_length + 1`` or more: the window at state 0 only), and
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
    if stride is not None:
        stride = check_stride(stride, T, chunk_length)
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
    folder = output_folder(out_dir)
    if prepare_folder(folder, arguments, progress):
        return folder

    seeds = split_seeds(seed)
    P, d = system.n_points, system.dim
    keys = ARRAYS + (WINDOW_ARRAYS if stride is not None else ())
    splits: dict[str, dict[str, np.ndarray]] = {}
    for name in SPLITS:
        n = counts[name]
        path = folder / f"{name}.npz"
        if path.exists():  # left by an interrupted run with the same arguments
            arrays, problem = _leftover_split(path, keys, n, (T, 2, P, d), chunk_length, stride)
            if arrays is not None:
                say(progress, f"reusing the {name} split of the interrupted run ({n} trajectories)")
                splits[name] = arrays
                continue
            path.unlink()
            say(
                progress,
                f"{path.name} of the interrupted run is not a complete {name} split "
                f"({problem}): removed, simulating the {name} split again",
            )
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
        write_split(folder, name, splits[name])  # a later crash keeps this split
    write_dataset(folder, system, splits, arguments, on_disk=SPLITS, device=str(dev))
    return folder


def _leftover_split(
    path: Path,
    keys: tuple[str, ...],
    n: int,
    state: tuple[int, ...],
    chunk_length: int,
    stride: int | None,
) -> tuple[dict[str, np.ndarray] | None, str]:
    """A split file an interrupted run left, if it is a complete split: ``(arrays, "")``.

    Complete: it reads, holds exactly the arrays ``keys`` with their dtypes, and
    their shapes agree with ``n`` trajectories of ``state = (T, 2, P, d)``:
    ``traj (n, T, 2, P, d)``, ``chunks (M, L, 2, P, d)``, ``chunk_start``,
    ``chunk_has_contact`` (and with windows ``chunk_traj``) ``(M,)``, ``contact
    (n, T)``, ``M = n`` for one chunk per trajectory. Otherwise ``(None, why)``.
    """
    try:
        arrays, members = read_npz(path)
    except (OSError, ValueError) as err:
        return None, f"unreadable: {err}"
    if sorted(members) != sorted(keys):
        return None, f"arrays {sorted(members)}, expected {sorted(keys)}"
    ints, bools = ("chunk_start", "chunk_traj"), ("chunk_has_contact", "contact")
    for key, arr in arrays.items():
        dtype = np.int64 if key in ints else np.bool_ if key in bools else np.float64
        if arr.dtype != dtype:
            return None, f"{key} of dtype {arr.dtype}"
    M = arrays["chunk_start"].shape[0] if arrays["chunk_start"].ndim == 1 else -1
    T = state[0]
    expected = {
        "traj": (n, *state),
        "chunks": (M, chunk_length, *state[1:]),
        "chunk_start": (M,),
        "chunk_has_contact": (M,),
        "contact": (n, T),
        "chunk_traj": (M,),
    }
    for key, arr in arrays.items():
        if arr.shape != expected[key]:
            return None, f"{key} of shape {arr.shape}, expected {expected[key]}"
    if stride is None and M != n:
        return None, f"{M} chunks for {n} trajectories"
    start, owner = arrays["chunk_start"], arrays.get("chunk_traj")
    if M and not (start.min() >= 0 and start.max() <= T - chunk_length):
        return None, "chunk starts out of range"
    if M and owner is not None and not (owner.min() >= 0 and owner.max() < n):
        return None, "chunk trajectories out of range"
    return arrays, ""
