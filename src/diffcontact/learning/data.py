"""Datasets: simulated or recorded trajectories, chunked for training (``docs/data.md``).

A dataset is a folder (``docs/conventions.md``, "Learning")::

    metadata.json   arguments, config, seeds, counts, sha256 of every file
    train.npz       traj (N, T, 2, P, d) float64, chunks (N, L, 2, P, d) float64,
    val.npz         chunk_start (N,) int64, chunk_has_contact (N,) bool,
    test.npz        contact (N, T) bool

- :func:`generate_dataset` samples initial conditions with the seeds
  ``seed * 1000 + 0/1/2`` (train/val/test), simulates full trajectories
  (``horizon / dt`` states, float64), marks the states in contact (any gap
  < 0), picks one chunk of ``chunk_length`` states per trajectory whose first
  state is out of contact (:func:`select_chunks`; about ``contact_fraction``
  of the chunks contain a contact) and adds Gaussian noise to the chunks only
  (for a chain pendulum on the link angles and angular velocities).
- :func:`dataset_from_arrays` writes the same format from trajectories
  recorded elsewhere (validated against the config's geometry).
- :func:`load_dataset` reads a folder back (checksums verified) into a
  :class:`Dataset`.

Writes are atomic (temporary file + rename); ``metadata.json`` is written last,
so a folder without it is unfinished. Re-running with the same arguments
reuses the files; different arguments never overwrite them (``ValueError``).
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import math
import re
import sys
import time
from dataclasses import dataclass, fields
from datetime import datetime, timezone
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from diffcontact import __version__
from diffcontact.cli_args import int_at_least
from diffcontact.io import atomic_save_npz, atomic_write_bytes
from diffcontact.mechanics.bodies import chain_points_2d
from diffcontact.systems import System, load_config, load_system

__all__ = [
    "FORMAT_VERSION",
    "SPLITS",
    "DataSplit",
    "Dataset",
    "DatasetError",
    "add_chunk_noise",
    "contact_states",
    "dataset_from_arrays",
    "generate_dataset",
    "load_dataset",
    "register_cli",
    "select_chunks",
    "split_seeds",
]

FORMAT_VERSION = 1
SPLITS = ("train", "val", "test")
METADATA = "metadata.json"
ARRAYS = ("traj", "chunks", "chunk_start", "chunk_has_contact", "contact")
_MARKER = ".generating.json"  # arguments of a run in progress; removed after metadata.json
_TMP = re.compile(r"^\.(train|val|test|metadata|\.generating)\.tmp-")
# numpy SeedSequence streams derived from one seed (see split_seeds)
_STREAM_CHUNKS, _STREAM_NOISE, _STREAM_SPLIT = 1, 2, 3


class DatasetError(ValueError):
    """A dataset folder is missing, incomplete, corrupted or of an unknown format."""


# --------------------------------------------------------------------------- helpers


def split_seeds(seed: int) -> dict[str, int]:
    """Seeds of the splits: ``seed * 1000 + 0, 1, 2`` for train, val, test.

    Each split seed seeds the initial conditions
    (``System.sample_initial_conditions``); the chunk choice and the noise of
    that split use ``numpy.random.default_rng([split_seed, 1])`` and
    ``default_rng([split_seed, 2])``.
    """
    return {name: seed * 1000 + k for k, name in enumerate(SPLITS)}


def _int_arg(name: str, value: Any, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)


def _float_arg(name: str, value: Any, low: float, high: float, *, high_open=False) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if isinstance(value, bool) or not (low <= x <= high) or (high_open and x == high):
        bracket = ")" if high_open else "]"
        raise ValueError(f"{name} must lie in [{low:g}, {high:g}{bracket}, got {value!r}")
    return x


def _device_arg(device: Any) -> torch.device:
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise ValueError(f"device must be 'cpu' or 'cuda', got {device!r}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} requested but CUDA is not available (use 'cpu')")
    return dev


def _jsonable(obj: Any) -> Any:
    """``obj`` after a JSON round trip (tuples become lists), for comparisons."""
    return json.loads(json.dumps(obj))


def _sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _short(value: Any) -> str:
    text = json.dumps(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _differences(old: Any, new: Any, name: str = "") -> list[str]:
    """Human-readable differences between recorded (``old``) and requested (``new``) arguments."""
    if isinstance(old, dict) and isinstance(new, dict):
        out: list[str] = []
        keys = list(new) + [k for k in old if k not in new]
        for key in keys:
            sub = f"{name}.{key}" if name else str(key)
            if key not in old:
                out.append(f"{sub} (not recorded there, requested {_short(new[key])})")
            elif key not in new:
                out.append(f"{sub} ({_short(old[key])} there, not requested)")
            else:
                out += _differences(old[key], new[key], sub)
        return out
    if old != new:
        return [f"{name or 'arguments'} ({_short(old)} there, {_short(new)} requested)"]
    return []


def _one_line(err: BaseException) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    if not lines:
        return type(err).__name__
    return lines[0] if len(lines) == 1 else f"{lines[0].rstrip(':')}: " + "; ".join(lines[1:])


def _say(progress: bool, message: str) -> None:
    if progress:
        print(message, flush=True)


# ------------------------------------------------------------------ contacts, chunks


def contact_states(system: System, traj: Tensor | np.ndarray) -> np.ndarray:
    """States in contact: ``(N, T)`` bool, any candidate gap < 0 at the state's positions.

    For simulated data these are the states at which a contact was resolved.

    Args:
        system: the system whose geometry (radii, walls, limits) decides.
        traj: ``(N, T, 2, P, d)`` trajectories.
    """
    z = torch.as_tensor(traj)
    if not z.is_floating_point():
        z = z.to(torch.float64)
    with torch.no_grad():
        gaps = system.gaps(z[..., 0, :, :])  # (N, T, K)
    return (gaps < 0).any(-1).cpu().numpy()


def select_chunks(
    contact: np.ndarray,
    chunk_length: int = 5,
    contact_fraction: float = 0.5,
    rng: np.random.Generator | int | None = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """One chunk per trajectory whose first state is out of contact.

    A start ``s`` (``0 <= s <= T - L``) is valid when ``contact[n, s]`` is
    False; its chunk holds the states ``s .. s + L - 1`` and "contains a
    contact" when any of them is in contact. Trajectories that only have
    contact chunks (or only contact-free ones) take one of those; of the
    others, randomly chosen ones take a contact chunk until
    ``round(contact_fraction * N)`` chunks contain a contact (or no more can),
    the rest a contact-free one. The start is uniform among the valid starts
    of the chosen kind. Vectorised over trajectories.

    Args:
        contact: ``(N, T)`` bool, states in contact (:func:`contact_states`).
        chunk_length: ``L``, states per chunk.
        contact_fraction: target share of chunks that contain a contact.
        rng: a ``numpy.random.Generator`` or a seed.

    Returns:
        ``start (N,)`` int64 and ``has_contact (N,)`` bool.

    Raises:
        ValueError: ``T < L``, or trajectories whose every possible start is
            in contact (the message lists them).
    """
    contact = np.asarray(contact, dtype=bool)
    if contact.ndim != 2:
        raise ValueError(f"contact must have shape (N, T), got {contact.shape}")
    L = _int_arg("chunk_length", chunk_length, 1)
    frac = _float_arg("contact_fraction", contact_fraction, 0.0, 1.0)
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    N, T = contact.shape
    S = T - L + 1
    if S < 1:
        raise ValueError(f"trajectories hold {T} states, fewer than chunk_length={L}")
    windows = np.lib.stride_tricks.sliding_window_view(contact, L, axis=1)  # (N, S, L)
    has = windows.any(-1)  # (N, S)
    ok = ~contact[:, :S]
    can_c = (ok & has).any(1)
    can_f = (ok & ~has).any(1)
    stuck = ~(can_c | can_f)
    if stuck.any():
        rows = np.flatnonzero(stuck)
        listed = ", ".join(map(str, rows[:10])) + (" ..." if rows.size > 10 else "")
        raise ValueError(
            f"{rows.size} of {N} trajectories ({listed}) are in contact (gap < 0) at every "
            f"state that could start a chunk (states 0..{S - 1}), so no chunk can start "
            "out of contact"
        )
    forced = can_c & ~can_f
    flexible = can_c & can_f
    target = math.floor(frac * N + 0.5)
    extra = int(np.clip(target - forced.sum(), 0, flexible.sum()))
    keys = gen.random(N)
    keys[~flexible] = np.inf
    want = forced.copy()
    want[np.argsort(keys, kind="stable")[:extra]] = True
    allowed = ok & (has == want[:, None])
    scores = gen.random((N, S))
    scores[~allowed] = -1.0
    start = scores.argmax(1).astype(np.int64)
    return start, has[np.arange(N), start]


def _chain_angles(z: Tensor, pivot: Tensor) -> tuple[Tensor, Tensor]:
    """Absolute link angles (from straight down) and rates of chain states ``(..., 2, P, 2)``."""
    x, v = z[..., 0, :, :], z[..., 1, :, :]
    prev_x = torch.cat([pivot.expand_as(x[..., :1, :]), x[..., :-1, :]], dim=-2)
    prev_v = torch.cat([torch.zeros_like(v[..., :1, :]), v[..., :-1, :]], dim=-2)
    seg, dv = x - prev_x, v - prev_v
    q = torch.atan2(seg[..., 0], -seg[..., 1])
    qdot = (seg[..., 0] * dv[..., 1] - seg[..., 1] * dv[..., 0]) / (seg * seg).sum(-1)
    return q, qdot


def add_chunk_noise(
    system: System, chunks: np.ndarray, noise_std: float, rng: np.random.Generator | int
) -> np.ndarray:
    """Gaussian noise of std ``noise_std`` on chunks ``(N, L, 2, P, d)`` (float64).

    Cartesian positions and velocities get independent noise, except for a
    chain pendulum: its states are converted to absolute link angles and
    angular velocities, noise is added there and the Cartesian states are
    rebuilt (:func:`~diffcontact.mechanics.bodies.chain_points_2d`), so the
    link lengths stay exact.
    """
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    chunks = np.asarray(chunks, dtype=np.float64)
    if noise_std == 0 or chunks.size == 0:
        return chunks.copy()
    if system.type != "chain_pendulum":
        return chunks + noise_std * gen.standard_normal(chunks.shape)
    cfg = system.config
    z = torch.from_numpy(chunks)
    pivot = torch.tensor(cfg.pivot, dtype=z.dtype)
    q, qdot = _chain_angles(z, pivot)
    q = q + noise_std * torch.from_numpy(gen.standard_normal(tuple(q.shape)))
    qdot = qdot + noise_std * torch.from_numpy(gen.standard_normal(tuple(qdot.shape)))
    lengths = torch.tensor(cfg.link_lengths, dtype=z.dtype)
    return chain_points_2d(q, qdot, lengths, pivot).numpy()


def _chunk_split(
    system: System,
    traj: np.ndarray,
    contact: np.ndarray,
    split_seed: int,
    chunk_length: int,
    contact_fraction: float,
    noise_std: float,
) -> dict[str, np.ndarray]:
    """The arrays of one split file from its clean trajectories ``(N, T, 2, P, d)``."""
    rng = np.random.default_rng([split_seed, _STREAM_CHUNKS])
    start, has = select_chunks(contact, chunk_length, contact_fraction, rng)
    idx = start[:, None] + np.arange(chunk_length)  # (N, L)
    chunks = np.take_along_axis(traj, idx[:, :, None, None, None], axis=1)
    if noise_std > 0:
        noise_rng = np.random.default_rng([split_seed, _STREAM_NOISE])
        chunks = add_chunk_noise(system, chunks, noise_std, noise_rng)
    return {
        "traj": np.ascontiguousarray(traj, dtype=np.float64),
        "chunks": np.ascontiguousarray(chunks, dtype=np.float64),
        "chunk_start": start.astype(np.int64),
        "chunk_has_contact": has.astype(bool),
        "contact": contact.astype(bool),
    }


def _stats(arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    contact = arrays["contact"]
    return {
        "n": int(contact.shape[0]),
        "chunks_with_contact": int(arrays["chunk_has_contact"].sum()),
        "trajectories_with_contact": int(contact.any(1).sum()),
        "share_of_states_in_contact": float(contact.mean()) if contact.size else 0.0,
    }


# ------------------------------------------------------------------------ folders


def _read_json(path: Path, what: str) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise DatasetError(f"cannot read {what} {path}: {err}") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{what} {path} does not hold a JSON object")
    return data


def _is_ours(path: Path) -> bool:
    names = {f"{s}.npz" for s in SPLITS} | {METADATA, _MARKER}
    return path.name in names or bool(_TMP.match(path.name))


def _verify_files(folder: Path, meta: dict[str, Any]) -> None:
    files = meta.get("files")
    expected = {f"{s}.npz" for s in SPLITS}
    if not isinstance(files, dict) or set(files) != expected:
        raise DatasetError(
            f"{folder / METADATA}: 'files' must map {sorted(expected)} to sha256 checksums, "
            f"got {files!r}"
        )
    for name in sorted(files):
        path = folder / name
        if not path.is_file():
            raise DatasetError(
                f"{path} is missing (metadata.json lists it): the dataset is incomplete; "
                f"delete {folder} and generate it again"
            )
        if _sha256_file(path) != files[name]:
            raise DatasetError(
                f"{path} does not match its sha256 checksum in metadata.json (the file was "
                f"changed or is corrupted); delete {folder} and generate it again"
            )


def _prepare_folder(folder: Path, arguments: dict[str, Any], progress: bool) -> bool:
    """Check ``folder`` against ``arguments``; True when a finished dataset is reused.

    Otherwise the folder exists afterwards, holds at most the leftovers of an
    interrupted run with the same arguments, and carries the marker file.
    """
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"output folder {folder} exists and is not a folder")
    meta_path = folder / METADATA
    if meta_path.exists():
        meta = _read_json(meta_path, "dataset metadata")
        diff = _differences(_jsonable(meta.get("arguments")), arguments)
        if diff:
            raise ValueError(
                f"{folder} already holds a dataset made with different arguments: "
                f"{'; '.join(diff)}. It is never overwritten: use another output folder "
                "or delete this one"
            )
        _verify_files(folder, meta)
        (folder / _MARKER).unlink(missing_ok=True)
        _say(progress, f"reusing the dataset in {folder} (same arguments, checksums verified)")
        return True
    if folder.is_dir():
        entries = sorted(folder.iterdir())
        if entries:
            marker = folder / _MARKER
            if not marker.is_file():
                names = ", ".join(p.name for p in entries[:5]) + (" ..." * (len(entries) > 5))
                raise ValueError(
                    f"output folder {folder} is not empty and holds no dataset (no "
                    f"{METADATA}; found {names}): choose an empty or new folder"
                )
            old = _read_json(marker, "marker of an interrupted run").get("arguments")
            diff = _differences(_jsonable(old), arguments)
            if diff:
                raise ValueError(
                    f"{folder} holds an unfinished dataset (an interrupted run) made with "
                    f"different arguments: {'; '.join(diff)}. Re-run with the same arguments "
                    "to finish it, or delete the folder"
                )
            strangers = [p.name for p in entries if not _is_ours(p)]
            if strangers:
                raise ValueError(
                    f"output folder {folder} holds files that are not part of a dataset: "
                    f"{', '.join(strangers[:5])}; choose an empty or new folder"
                )
            for p in entries:
                if _TMP.match(p.name):
                    p.unlink(missing_ok=True)
            _say(progress, f"finishing the interrupted dataset in {folder}")
    else:
        try:
            folder.mkdir(parents=True)
        except OSError as err:
            raise ValueError(f"cannot create output folder {folder}: {err}") from None
    payload = {"arguments": arguments, "started": _now()}
    try:
        atomic_write_bytes(folder / _MARKER, json.dumps(payload, indent=2).encode())
    except OSError as err:
        raise ValueError(f"cannot write to output folder {folder}: {err}") from None
    return False


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _write_dataset(
    folder: Path, splits: dict[str, dict[str, np.ndarray]], metadata: dict[str, Any]
) -> None:
    """Write the split files, then ``metadata.json`` (with their checksums), atomically."""
    files: dict[str, str] = {}
    for name in SPLITS:
        path = folder / f"{name}.npz"
        atomic_save_npz(path, **{key: splits[name][key] for key in ARRAYS})
        files[path.name] = _sha256_file(path)
    metadata = {**metadata, "files": files}
    text = json.dumps(metadata, indent=2) + "\n"
    atomic_write_bytes(folder / METADATA, text.encode())
    (folder / _MARKER).unlink(missing_ok=True)


def _base_metadata(system: System, source: str, seed: int, n_states: int) -> dict[str, Any]:
    return {
        "format_version": FORMAT_VERSION,
        "task": system.name,
        "source": source,
        "config": _jsonable(system.config.model_dump(mode="json")),
        "seed": seed,
        "seeds": split_seeds(seed),
        "dt": system.dt,
        "n_states": n_states,
    }


# ----------------------------------------------------------------------- generate


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
) -> Path:
    """Simulate, chunk and save a train/val/test dataset of a task (``docs/data.md``).

    Args:
        spec: built-in task name, ``.yaml``/``.json`` config path or dict.
        out_dir: dataset folder (created; must be empty, or hold a dataset
            made with the same arguments, which is then reused).
        n_train, n_val, n_test: trajectories per split (``n_train >= 1``).
        seed: base seed; the splits use ``seed * 1000 + 0/1/2``
            (:func:`split_seeds`), so they hold different trajectories.
        noise_std: std of the Gaussian noise added to the chunks only (for a
            chain pendulum to the link angles and angular velocities).
        chunk_length: states per chunk (``>= 2``).
        contact_fraction: target share of chunks containing a contact.
        progress: progress bars and messages (including "reusing ...").
        device: where to simulate (the files are the same float64 arrays).

    Returns:
        The dataset folder.

    Raises:
        ValueError: bad arguments or config; ``out_dir`` holds a dataset made
            with different arguments (the message names them), other files, or
            a reused dataset whose files fail their checksums.
    """
    return _generate(
        spec,
        out_dir,
        n_train=n_train,
        n_val=n_val,
        n_test=n_test,
        seed=seed,
        noise_std=noise_std,
        chunk_length=chunk_length,
        contact_fraction=contact_fraction,
        progress=progress,
        device=device,
    )[0]


def _generate(
    spec: Any,
    out_dir: str | Path,
    *,
    n_train: int,
    n_val: int,
    n_test: int,
    seed: int,
    noise_std: float,
    chunk_length: int,
    contact_fraction: float,
    progress: bool,
    device: str | torch.device,
) -> tuple[Path, bool]:
    counts = {
        "train": _int_arg("n_train", n_train, 1),
        "val": _int_arg("n_val", n_val, 0),
        "test": _int_arg("n_test", n_test, 0),
    }
    seed = _int_arg("seed", seed, 0)
    if seed * 1000 + 2 >= 2**63:
        raise ValueError(f"seed must be below {(2**63 - 3) // 1000}, got {seed}")
    noise_std = _float_arg("noise_std", noise_std, 0.0, math.inf)
    chunk_length = _int_arg("chunk_length", chunk_length, 2)
    contact_fraction = _float_arg("contact_fraction", contact_fraction, 0.0, 1.0)
    dev = _device_arg(device)
    system = load_system(spec)
    T = system.default_steps + 1
    if T < chunk_length:
        raise ValueError(
            f"{system.name}'s trajectories hold {T} states (horizon / dt), fewer than "
            f"chunk_length={chunk_length}"
        )
    config = _jsonable(system.config.model_dump(mode="json"))
    arguments = {
        "source": "simulated",
        "config": config,
        "n_train": counts["train"],
        "n_val": counts["val"],
        "n_test": counts["test"],
        "seed": seed,
        "noise_std": noise_std,
        "chunk_length": chunk_length,
        "contact_fraction": contact_fraction,
    }
    folder = Path(out_dir)
    if _prepare_folder(folder, arguments, progress):
        return folder, True

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
                traj_t = system.simulate(z0, steps=T - 1, progress=progress)
            traj = traj_t.to(torch.float64).cpu().numpy()
        contact = contact_states(system, traj)
        splits[name] = _chunk_split(
            system, traj, contact, seeds[name], chunk_length, contact_fraction, noise_std
        )
    metadata = {
        **_base_metadata(system, "simulated", seed, T),
        **{f"n_{s}": counts[s] for s in SPLITS},
        "noise_std": noise_std,
        "chunk_length": chunk_length,
        "contact_fraction": contact_fraction,
        "device": str(dev),
        "diffcontact_version": __version__,
        "created": _now(),
        "stats": {s: _stats(splits[s]) for s in SPLITS},
        "arguments": arguments,
    }
    _write_dataset(folder, splits, metadata)
    return folder, False


# ------------------------------------------------------------------ recorded data


def _as_array(trajectories: Any) -> np.ndarray:
    if isinstance(trajectories, Tensor):
        trajectories = trajectories.detach().cpu().numpy()
    try:
        arr = np.asarray(trajectories)
    except (TypeError, ValueError) as err:
        raise ValueError(f"trajectories must be a numeric array: {err}") from None
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"trajectories must be a numeric array, got dtype {arr.dtype}")
    return arr


def dataset_from_arrays(
    trajectories: Any,
    config: Any,
    out_dir: str | Path,
    *,
    dt: float | None = None,
    val_fraction: float = 0.1,
    test_fraction: float = 0.1,
    seed: int = 0,
    chunk_length: int = 5,
    contact_fraction: float = 0.5,
    progress: bool = True,
) -> Path:
    """Write a dataset folder (same format as :func:`generate_dataset`) from recorded data.

    The trajectories are split at random into train/val/test, marked for
    contact with the config's geometry and chunked like simulated data (no
    noise is added: recorded data carries its own).

    Args:
        trajectories: ``(N, T, 2, P, d)`` array (numpy or torch): positions then
            velocities of the config's P points in d dimensions, sampled every
            ``dt`` (the config's).
        config: the known geometry and dt: built-in task name, ``.yaml``/``.json``
            path or dict.
        out_dir: dataset folder (as in :func:`generate_dataset`).
        dt: the recording's time step, checked against the config's ``dt``.
        val_fraction, test_fraction: shares of the trajectories for val and
            test (at least one each when positive; at least one left for train).
        seed: seed of the split (``numpy.random.default_rng([seed, 3])``) and,
            through :func:`split_seeds`, of the chunk choice.
        chunk_length, contact_fraction: as in :func:`generate_dataset`.
        progress: print messages (e.g. that an existing dataset was reused).

    Returns:
        The dataset folder.

    Raises:
        ValueError: a message naming the problem: wrong shape (expected vs
            got), NaN/inf (which trajectory and state), dt different from the
            config's, fewer states than ``chunk_length``, trajectories in
            contact at every possible chunk start, bad fractions, or an output
            folder as in :func:`generate_dataset`.
    """
    system = load_system(config)
    seed = _int_arg("seed", seed, 0)
    if seed * 1000 + 2 >= 2**63:
        raise ValueError(f"seed must be below {(2**63 - 3) // 1000}, got {seed}")
    chunk_length = _int_arg("chunk_length", chunk_length, 2)
    contact_fraction = _float_arg("contact_fraction", contact_fraction, 0.0, 1.0)
    vf = _float_arg("val_fraction", val_fraction, 0.0, 1.0, high_open=True)
    tf = _float_arg("test_fraction", test_fraction, 0.0, 1.0, high_open=True)
    if vf + tf >= 1:
        raise ValueError(
            f"val_fraction + test_fraction must be below 1 (some data must be left to "
            f"train on), got {vf} + {tf}"
        )
    if dt is not None:
        dt_f = _float_arg("dt", dt, 0.0, math.inf)
        if not math.isclose(dt_f, system.dt, rel_tol=1e-6, abs_tol=1e-12):
            raise ValueError(
                f"dt={dt_f:g} of the data differs from the config's dt={system.dt:g}; models "
                "step with the config's dt: set dt in the config to the recording's step "
                "(or resample the data)"
            )

    arr = _as_array(trajectories)
    P, d = system.n_points, system.dim
    want = f"(N, T, 2, {P}, {d})"
    if arr.ndim != 5 or arr.shape[2:] != (2, P, d):
        hint = ""
        if arr.ndim == 4 and arr.shape[1:] == (2, P, d):
            hint = " (a single trajectory? add a leading axis: traj[None])"
        raise ValueError(
            f"trajectories must have shape {want} for {system.name}: N trajectories of T "
            f"states, positions then velocities of its {P} points in {d}D (from the "
            f"config); got {arr.shape}{hint}"
        )
    N, T = arr.shape[:2]
    if N == 0:
        raise ValueError(f"trajectories hold no trajectory (shape {arr.shape})")
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    bad = ~np.isfinite(arr).reshape(N, T, -1).all(-1)
    if bad.any():
        rows, cols = np.nonzero(bad)
        where = ", ".join(
            f"trajectory {r} state {c} (t = {c * system.dt:g} s)"
            for r, c in zip(rows[:5].tolist(), cols[:5].tolist(), strict=True)
        )
        more = f" and {rows.size - 5} more states" if rows.size > 5 else ""
        raise ValueError(f"trajectories contain NaN or infinite values at {where}{more}")
    if T < chunk_length:
        raise ValueError(
            f"trajectories hold {T} states, fewer than chunk_length={chunk_length}: each "
            f"trajectory needs at least {chunk_length} states"
        )
    n_val = math.floor(vf * N + 0.5) if vf > 0 else 0
    n_test = math.floor(tf * N + 0.5) if tf > 0 else 0
    n_val, n_test = (max(n_val, 1) if vf > 0 else 0), (max(n_test, 1) if tf > 0 else 0)
    n_train = N - n_val - n_test
    if n_train < 1:
        raise ValueError(
            f"{N} trajectories are too few for val_fraction={vf:g} and test_fraction={tf:g} "
            "(at least one each): no trajectory is left for training"
        )

    contact = contact_states(system, arr)
    S = T - chunk_length + 1
    stuck = contact[:, :S].all(1)
    if stuck.any():
        rows = np.flatnonzero(stuck)
        with torch.no_grad():
            gaps = system.gaps(torch.from_numpy(arr[rows[0], 0, 0]))
        k = int(gaps.argmin())
        listed = ", ".join(map(str, rows[:10].tolist())) + (" ..." if rows.size > 10 else "")
        raise ValueError(
            f"{rows.size} of {N} trajectories ({listed}) are in contact (gap < 0: overlapping "
            f"bodies or a violated limit) at every state that could start a chunk "
            f"(states 0..{S - 1}), so they cannot be chunked (a chunk must start out of "
            f"contact); e.g. trajectory {rows[0]} state 0: {system.contact_names[k]} "
            f"(gap {float(gaps[k]):.3g}). Drop them, or check that the config's geometry "
            "(radii, walls, limits) matches the data"
        )

    config_json = _jsonable(system.config.model_dump(mode="json"))
    digest = hashlib.sha256(repr(arr.shape).encode() + arr.tobytes()).hexdigest()
    arguments = {
        "source": "arrays",
        "config": config_json,
        "traj_sha256": digest,
        "n_trajectories": N,
        "n_states": T,
        "val_fraction": vf,
        "test_fraction": tf,
        "seed": seed,
        "chunk_length": chunk_length,
        "contact_fraction": contact_fraction,
    }
    folder = Path(out_dir)
    if _prepare_folder(folder, arguments, progress):
        return folder

    perm = np.random.default_rng([seed, _STREAM_SPLIT]).permutation(N)
    index = {
        "test": np.sort(perm[:n_test]),
        "val": np.sort(perm[n_test : n_test + n_val]),
        "train": np.sort(perm[n_test + n_val :]),
    }
    seeds = split_seeds(seed)
    splits = {
        name: _chunk_split(
            system,
            arr[index[name]],
            contact[index[name]],
            seeds[name],
            chunk_length,
            contact_fraction,
            0.0,
        )
        for name in SPLITS
    }
    metadata = {
        **_base_metadata(system, "arrays", seed, T),
        "n_train": n_train,
        "n_val": n_val,
        "n_test": n_test,
        "noise_std": 0.0,
        "chunk_length": chunk_length,
        "contact_fraction": contact_fraction,
        "source_indices": {name: index[name].tolist() for name in SPLITS},
        "diffcontact_version": __version__,
        "created": _now(),
        "stats": {s: _stats(splits[s]) for s in SPLITS},
        "arguments": arguments,
    }
    _write_dataset(folder, splits, metadata)
    return folder


# -------------------------------------------------------------------------- load


@dataclass(frozen=True)
class DataSplit:
    """One split of a dataset as tensors (``N`` trajectories of ``T`` states, chunks of ``L``).

    Attributes:
        name: ``"train"``, ``"val"`` or ``"test"``.
        traj: ``(N, T, 2, P, d)`` clean full trajectories.
        chunks: ``(N, L, 2, P, d)`` training chunks (noisy when the dataset's
            ``noise_std > 0``).
        chunk_start: ``(N,)`` int64, index of each chunk's first state in ``traj``.
        chunk_has_contact: ``(N,)`` bool, the chunk contains a state in contact.
        contact: ``(N, T)`` bool, states in contact (a contact was resolved there).
    """

    name: str
    traj: Tensor
    chunks: Tensor
    chunk_start: Tensor
    chunk_has_contact: Tensor
    contact: Tensor

    def __len__(self) -> int:
        return int(self.traj.shape[0])

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> DataSplit:
        """A copy with the tensors on ``device`` and the float ones (traj, chunks) in ``dtype``."""
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, Tensor):
                value = value.to(device=device, dtype=dtype if value.is_floating_point() else None)
            out[f.name] = value
        return DataSplit(**out)


class Dataset:
    """A dataset folder read by :func:`load_dataset`.

    Attributes:
        path: the folder.
        metadata: ``metadata.json`` as a dict.
        config: the validated system config.
        system: a :class:`~diffcontact.systems.System` built from the config
            (created on first use).
        task, dt, chunk_length, noise_std, n_states, counts: from the metadata.

    ``split(name)`` (or ``.train``, ``.val``, ``.test``) reads a split as a
    :class:`DataSplit`; the bytes read are checked against their checksum.
    """

    def __init__(self, path: Path, metadata: dict[str, Any], config: Any) -> None:
        self.path = path
        self.metadata = metadata
        self.config = config

    @cached_property
    def system(self) -> System:
        return load_system(self.metadata["config"])

    @property
    def task(self) -> str:
        return str(self.metadata["task"])

    @property
    def dt(self) -> float:
        return float(self.metadata["dt"])

    @property
    def chunk_length(self) -> int:
        return int(self.metadata["chunk_length"])

    @property
    def noise_std(self) -> float:
        return float(self.metadata["noise_std"])

    @property
    def n_states(self) -> int:
        return int(self.metadata["n_states"])

    @property
    def counts(self) -> dict[str, int]:
        return {s: int(self.metadata[f"n_{s}"]) for s in SPLITS}

    def __repr__(self) -> str:
        c = self.counts
        return (
            f"Dataset({str(self.path)!r}, task={self.task!r}, train={c['train']}, "
            f"val={c['val']}, test={c['test']}, states={self.n_states}, "
            f"chunk_length={self.chunk_length}, noise_std={self.noise_std:g})"
        )

    def split(
        self,
        name: str,
        *,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
    ) -> DataSplit:
        """Read split ``name`` (``"train"``, ``"val"`` or ``"test"``) as tensors.

        Args:
            name: the split.
            dtype: float dtype of ``traj`` and ``chunks`` (stored as float64).
            device: where to put the tensors.

        Raises:
            ValueError: an unknown split name.
            DatasetError: the file is missing, fails its checksum or lacks an array.
        """
        if name not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {name!r}")
        path = self.path / f"{name}.npz"
        try:
            data = path.read_bytes()
        except OSError as err:
            raise DatasetError(f"cannot read {path}: {err}") from None
        if _sha256_bytes(data) != self.metadata["files"][path.name]:
            raise DatasetError(
                f"{path} does not match its sha256 checksum in metadata.json (the file was "
                f"changed or is corrupted); delete {self.path} and generate it again"
            )
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            missing = [key for key in ARRAYS if key not in npz.files]
            if missing:
                raise DatasetError(f"{path} lacks the arrays {missing}")
            arrays = {key: npz[key] for key in ARRAYS}
        N, T, L = self.counts[name], self.n_states, self.chunk_length
        shape = arrays["traj"].shape
        chunk_shape = (N, L, *shape[2:])
        if len(shape) != 5 or shape[:3] != (N, T, 2) or arrays["chunks"].shape != chunk_shape:
            raise DatasetError(
                f"{path}: traj {shape} / chunks {arrays['chunks'].shape} do not match the "
                f"metadata (N={N}, T={T}, chunk_length={L})"
            )
        out = {key: torch.from_numpy(arrays[key]) for key in ARRAYS}
        return DataSplit(name=name, **out).to(device=device, dtype=dtype)

    @property
    def train(self) -> DataSplit:
        return self.split("train")

    @property
    def val(self) -> DataSplit:
        return self.split("val")

    @property
    def test(self) -> DataSplit:
        return self.split("test")


_REQUIRED = (
    "format_version", "config", "task", "seed", "seeds", "dt", "n_train", "n_val", "n_test",
    "n_states", "noise_std", "chunk_length", "files", "arguments",
)  # fmt: skip


def load_dataset(data_dir: str | Path) -> Dataset:
    """Read a dataset folder written by :func:`generate_dataset` or :func:`dataset_from_arrays`.

    Every file's sha256 is checked against ``metadata.json``.

    Raises:
        DatasetError (a ``ValueError``): the folder or a file is missing, a
            checksum does not match, or the metadata is unreadable or of
            another format version.
    """
    folder = Path(data_dir)
    if not folder.is_dir():
        raise DatasetError(f"dataset folder {folder} does not exist")
    meta_path = folder / METADATA
    if not meta_path.is_file():
        unfinished = " (an interrupted run left it unfinished)" * (folder / _MARKER).exists()
        raise DatasetError(
            f"{folder} has no {METADATA}: not a finished dataset{unfinished}; create one "
            "with `diffcontact generate`"
        )
    meta = _read_json(meta_path, "dataset metadata")
    missing = [key for key in _REQUIRED if key not in meta]
    if missing:
        raise DatasetError(f"{meta_path} lacks the keys {missing}")
    if meta["format_version"] != FORMAT_VERSION:
        raise DatasetError(
            f"{meta_path}: format_version {meta['format_version']!r} is not supported "
            f"(this diffcontact reads version {FORMAT_VERSION})"
        )
    _verify_files(folder, meta)
    try:
        config = load_config(meta["config"])
    except ValueError as err:
        raise DatasetError(f"{meta_path}: invalid config: {err}") from None
    return Dataset(folder, meta, config)


# --------------------------------------------------------------------------- CLI


def _cli_float(low: float, high: float = math.inf):
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must lie in [{low:g}, {high:g}], got {value:g}")
        return value

    return parse


def register_cli(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``generate`` subcommand to an argparse ``subparsers`` object; return its parser.

    The handler (``args.func``) returns the exit status: 0, 2 for bad input
    (one line on stderr) or 1 when the simulation or writing fails.
    """
    p = subparsers.add_parser(
        "generate",
        help="simulate and chunk a train/val/test dataset (or import recorded trajectories)",
        description=(
            "Simulate full trajectories of a task for the train, val and test splits "
            "(seeds SEED*1000 + 0, 1, 2), pick one chunk per trajectory starting out of "
            "contact (about half containing a contact), optionally add noise to the "
            "chunks, and write train.npz, val.npz, test.npz and metadata.json to --out. "
            "With --from-arrays, split and chunk recorded trajectories instead. "
            "Re-running with the same arguments reuses the folder; see docs/data.md."
        ),
    )
    p.add_argument(
        "task",
        metavar="TASK_OR_CONFIG",
        nargs="?",
        default=None,
        help="built-in task (e.g. BP5, CP3) or a .yaml/.json config "
        "(with --from-arrays: the config of the recorded system, like --config)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="dataset folder")
    p.add_argument("--n-train", metavar="N", type=int_at_least(1), default=None, help="default 800")
    p.add_argument("--n-val", metavar="N", type=int_at_least(0), default=None, help="default 100")
    p.add_argument("--n-test", metavar="N", type=int_at_least(0), default=None, help="default 100")
    p.add_argument(
        "--seed", metavar="N", type=int_at_least(0), default=0, help="base seed (default 0)"
    )
    p.add_argument(
        "--noise-std",
        metavar="STD",
        type=_cli_float(0.0),
        default=None,
        help="Gaussian noise std added to the chunks (default 0; chain pendulum: on the "
        "angles and angular velocities)",
    )
    p.add_argument(
        "--chunk-length",
        metavar="L",
        type=int_at_least(2),
        default=5,
        help="states per chunk (default 5)",
    )
    p.add_argument(
        "--contact-fraction",
        metavar="F",
        type=_cli_float(0.0, 1.0),
        default=0.5,
        help="target share of chunks containing a contact (default 0.5)",
    )
    p.add_argument(
        "--device", choices=("cpu", "cuda"), default=None, help="where to simulate (default cpu)"
    )
    p.add_argument(
        "--from-arrays",
        metavar="FILE",
        default=None,
        help="recorded trajectories: an .npz with an array 'traj' (N, T, 2, P, d) (optional "
        "'dt' and 'config' entries, as written by `diffcontact simulate`) or an .npy",
    )
    p.add_argument("--config", metavar="CONFIG", default=None, help="config of the recorded system")
    p.add_argument(
        "--val-fraction",
        metavar="F",
        type=_cli_float(0.0, 1.0),
        default=None,
        help="with --from-arrays: share for val (default 0.1)",
    )
    p.add_argument(
        "--test-fraction",
        metavar="F",
        type=_cli_float(0.0, 1.0),
        default=None,
        help="with --from-arrays: share for test (default 0.1)",
    )
    p.add_argument(
        "--dt",
        metavar="DT",
        type=_cli_float(0.0),
        default=None,
        help="with --from-arrays: the recording's time step, checked against the config",
    )
    p.add_argument("--quiet", action="store_true", help="no progress and no summary")
    p.set_defaults(func=run_generate_cli)
    return p


def _read_arrays_file(path: str) -> tuple[np.ndarray, float | None, Any]:
    """``traj`` and, when present, ``dt`` and ``config`` (JSON) of an .npz (or an .npy array)."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"--from-arrays file {path!r} does not exist")
    try:
        data = np.load(p, allow_pickle=False)
    except (OSError, ValueError, EOFError) as err:
        raise ValueError(f"cannot read {path} as .npz or .npy: {_one_line(err)}") from None
    if isinstance(data, np.ndarray):
        return data, None, None
    with data:
        keys = list(data.files)
        if "traj" not in keys:
            raise ValueError(
                f"{path} has no array named 'traj' (found: {', '.join(keys) or 'nothing'}); "
                "save the trajectories with numpy.savez(FILE, traj=...)"
            )
        traj = data["traj"]
        dt = float(data["dt"]) if "dt" in keys else None
        config = None
        if "config" in keys:
            try:
                config = json.loads(str(data["config"]))
            except json.JSONDecodeError as err:
                raise ValueError(f"{path}: entry 'config' is not JSON: {err}") from None
    return traj, dt, config


def _cli_generate(args: argparse.Namespace) -> int:
    quiet = args.quiet
    if args.task is not None and args.config is not None and args.task != args.config:
        raise ValueError(
            f"give the config once: TASK_OR_CONFIG {args.task!r} and --config {args.config!r}"
        )
    spec = args.task if args.task is not None else args.config
    start = time.perf_counter()
    if args.from_arrays is not None:
        for flag, value in (
            ("--n-train", args.n_train), ("--n-val", args.n_val), ("--n-test", args.n_test),
            ("--noise-std", args.noise_std), ("--device", args.device),
        ):  # fmt: skip
            if value is not None:
                raise ValueError(
                    f"{flag} does not apply with --from-arrays (split sizes come from "
                    "--val-fraction/--test-fraction; recorded data gets no noise)"
                )
        traj, file_dt, file_config = _read_arrays_file(args.from_arrays)
        if spec is None:
            if file_config is None:
                raise ValueError(
                    "--from-arrays needs the system's config: --config CONFIG (a task name "
                    "or a .yaml/.json file)"
                )
            spec = file_config
        dt = args.dt if args.dt is not None else file_dt
        folder = Path(args.out)
        reused = (folder / METADATA).is_file()
        dataset_from_arrays(
            traj,
            spec,
            folder,
            dt=dt,
            val_fraction=0.1 if args.val_fraction is None else args.val_fraction,
            test_fraction=0.1 if args.test_fraction is None else args.test_fraction,
            seed=args.seed,
            chunk_length=args.chunk_length,
            contact_fraction=args.contact_fraction,
            progress=not quiet,
        )
    else:
        for flag, value in (
            ("--val-fraction", args.val_fraction),
            ("--test-fraction", args.test_fraction),
            ("--dt", args.dt),
            ("--config", args.config if args.task is None else None),
        ):
            if value is not None:
                raise ValueError(f"{flag} applies only with --from-arrays")
        if spec is None:
            raise ValueError("give TASK_OR_CONFIG (a built-in task or a .yaml/.json config)")
        folder, reused = _generate(
            spec,
            args.out,
            n_train=800 if args.n_train is None else args.n_train,
            n_val=100 if args.n_val is None else args.n_val,
            n_test=100 if args.n_test is None else args.n_test,
            seed=args.seed,
            noise_std=0.0 if args.noise_std is None else args.noise_std,
            chunk_length=args.chunk_length,
            contact_fraction=args.contact_fraction,
            progress=not quiet,
            device="cpu" if args.device is None else args.device,
        )
    if not quiet:
        _print_summary(folder, reused, time.perf_counter() - start)
    return 0


def _plural(n: int) -> str:
    return "trajectory" if n == 1 else "trajectories"


def _print_summary(folder: Path, reused: bool, elapsed: float) -> None:
    meta = json.loads((folder / METADATA).read_text())
    action = "reused" if reused else f"written in {elapsed:.1f} s"
    print(f"{meta['task']} dataset ({meta['source']}) {action}: {folder}")
    total = with_contact = 0
    for name in SPLITS:
        st = meta["stats"][name]
        n, c = st["n"], st["chunks_with_contact"]
        total, with_contact = total + n, with_contact + c
        share = f"{100 * c / n:.0f}%" if n else "-"
        k = st["trajectories_with_contact"]
        print(
            f"  {name:5s}: {n} {_plural(n)} x {meta['n_states']} states; {share} of chunks "
            f"contain a contact ({c}/{n}); {k} {_plural(k)} {'has' if k == 1 else 'have'} one"
        )
    share = f"{100 * with_contact / total:.1f}%" if total else "-"
    print(
        f"  chunks of {meta['chunk_length']} states, noise std {meta['noise_std']:g}; "
        f"{share} of all chunks contain a contact"
    )
    files = ", ".join(str(folder / f) for f in (*meta["files"], METADATA))
    print(f"  files: {files}")


def run_generate_cli(args: argparse.Namespace) -> int:
    """Handler of ``diffcontact generate``: 0 on success, 2 on bad input, 1 on failure."""
    try:
        return _cli_generate(args)
    except ValueError as err:
        print(f"diffcontact generate: error: {_one_line(err)}", file=sys.stderr)
        return 2
    except (RuntimeError, OSError) as err:
        print(
            f"diffcontact generate: error: {type(err).__name__}: {_one_line(err)}",
            file=sys.stderr,
        )
        return 1
