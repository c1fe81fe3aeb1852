"""Writing a dataset folder: checks against an existing one, atomic files, metadata.

Writes are atomic (temporary file + rename); ``metadata.json`` is written last
(with its own checksum, ``metadata_sha256``), so a folder without it is
unfinished. Re-running with the same arguments reuses the files (writing nothing,
so a finished dataset on read-only storage is reused too); different
arguments never overwrite them (``ValueError``). A split file can be written
on its own (:func:`write_split`) while the marker is in place, as soon as the
split is ready: ``generate_dataset`` does so, and a re-run after an interruption
reuses the split files already written (``write_dataset(..., on_disk=...)``
then hashes them instead of writing them again).
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Callable, Collection
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from diffcontact import __version__
from diffcontact.io import atomic_save_npz, atomic_write_json, jsonable, read_json_object
from diffcontact.learning.data.format import (
    ARRAYS,
    FORMAT_VERSION,
    MARKER,
    METADATA,
    METADATA_CHECKSUM,
    SPLITS,
    TMP_NAME,
    WINDOW_ARRAYS,
    DatasetError,
    metadata_checksum,
    read_metadata,
    sha256_file,
    split_seeds,
    verify_files,
)
from diffcontact.systems import System

__all__ = ["prepare_folder", "say", "split_keys", "write_dataset", "write_split"]


def say(progress: bool, message: str) -> None:
    if progress:
        print(message, flush=True)


def _now() -> str:
    """The current UTC time, ISO 8601 to the second."""
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _short(value: Any) -> str:
    text = json.dumps(value)
    return text if len(text) <= 40 else text[:37] + "..."


# config keys added after datasets were first written, each with whether a requested
# config (a dump) behaves as a dataset made before the key existed: such a request matches
# that dataset (another, e.g. the rope's position projection, does not)
ADDED_CONFIG_KEYS: dict[str, Callable[[dict[str, Any]], bool]] = {
    "position_projection": lambda config: config["position_projection"] == 0,
    "integrator": lambda config: config["integrator"] == "rk4",
    # the velocities are projected only where the positions are
    "velocity_projection": lambda config: (
        not config["velocity_projection"] or not config.get("position_projection")
    ),
    # crossings are foreseen only where the velocities are projected
    "foresee_crossings": lambda config: (
        not config["foresee_crossings"]
        or not config.get("velocity_projection")
        or not config.get("position_projection")
    ),
}


def _differences(old: Any, new: Any, name: str = "") -> list[str]:
    """Human-readable differences between recorded (``old``) and requested (``new``) arguments."""
    if isinstance(old, dict) and isinstance(new, dict):
        out: list[str] = []
        keys = list(new) + [k for k in old if k not in new]
        for key in keys:
            sub = f"{name}.{key}" if name else str(key)
            added = name == "config" and key in ADDED_CONFIG_KEYS
            if key not in old and added and ADDED_CONFIG_KEYS[key](new):
                continue  # made before the key existed, with the behaviour requested
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


def _is_ours(path: Path) -> bool:
    names = {f"{s}.npz" for s in SPLITS} | {METADATA, MARKER}
    return path.name in names or bool(TMP_NAME.match(path.name))


def _remove_stale_marker(folder: Path) -> None:
    """Remove the marker a run killed between ``metadata.json`` and its removal left behind.

    Nothing is written when there is none (``unlink`` fails with ``EROFS`` on read-only
    storage even for a missing file), and a marker that cannot be removed stays: next to
    ``metadata.json`` it means nothing.
    """
    marker = folder / MARKER
    if marker.exists():
        with contextlib.suppress(OSError):
            marker.unlink()


def output_folder(out_dir: Any) -> Path:
    """``out_dir`` as a ``Path``; a ``ValueError`` for anything but a ``str`` or an
    ``os.PathLike`` (an int had given pathlib's ``TypeError``)."""
    if isinstance(out_dir, (str, os.PathLike)) and str(out_dir):
        return Path(out_dir)
    raise ValueError(f"out_dir must be a path (str or os.PathLike), got {out_dir!r}")


def prepare_folder(folder: Path, arguments: dict[str, Any], progress: bool) -> bool:
    """Check ``folder`` against ``arguments``; True when a finished dataset is reused.

    Reusing a finished dataset writes nothing (it works on read-only storage).
    Otherwise the folder exists afterwards, holds at most the leftovers of an
    interrupted run with the same arguments, and carries the marker file.
    """
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"output folder {folder} exists and is not a folder")
    if (folder / METADATA).exists():
        meta = read_metadata(folder)
        diff = _differences(jsonable(meta.get("arguments")), arguments)
        if diff:
            raise ValueError(
                f"{folder} already holds a dataset made with different arguments: "
                f"{'; '.join(diff)}. It is never overwritten: use another output folder "
                "or delete this one"
            )
        verify_files(folder, meta)
        _remove_stale_marker(folder)
        say(progress, f"reusing the dataset in {folder} (same arguments, checksums verified)")
        return True
    if folder.is_dir():
        entries = sorted(folder.iterdir())
        if entries:
            marker = folder / MARKER
            if not marker.is_file():
                names = ", ".join(p.name for p in entries[:5]) + (" ..." * (len(entries) > 5))
                raise ValueError(
                    f"output folder {folder} is not empty and holds no dataset (no "
                    f"{METADATA}; found {names}): choose an empty or new folder"
                )
            old = read_json_object(marker, "marker of an interrupted run", DatasetError).get(
                "arguments"
            )
            diff = _differences(jsonable(old), arguments)
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
                if TMP_NAME.match(p.name):
                    p.unlink(missing_ok=True)
            say(progress, f"finishing the interrupted dataset in {folder}")
    else:
        try:
            folder.mkdir(parents=True)
        except OSError as err:
            raise ValueError(f"cannot create output folder {folder}: {err}") from None
    try:
        atomic_write_json(folder / MARKER, {"arguments": arguments, "started": _now()})
    except OSError as err:
        raise ValueError(f"cannot write to output folder {folder}: {err}") from None
    return False


def split_keys(arrays: dict[str, np.ndarray]) -> tuple[str, ...]:
    """The arrays a split file holds: ``ARRAYS``, then those of ``WINDOW_ARRAYS`` present."""
    return ARRAYS + tuple(k for k in WINDOW_ARRAYS if k in arrays)


def write_split(folder: Path, name: str, arrays: dict[str, np.ndarray]) -> Path:
    """Write split ``name``'s file ``folder/<name>.npz`` atomically; return its path.

    ``arrays``: those of :func:`~diffcontact.learning.data.chunks.chunk_split`
    (``traj (N, T, 2, P, d)``, ``chunks (M, L, 2, P, d)``, ``chunk_start (M,)``,
    ``chunk_has_contact (M,)``, ``contact (N, T)``, with windows ``chunk_traj
    (M,)``); the file holds :func:`split_keys` of them, byte for byte the same
    for the same arrays.
    """
    path = folder / f"{name}.npz"
    atomic_save_npz(path, **{key: arrays[key] for key in split_keys(arrays)})
    return path


def write_dataset(
    folder: Path,
    system: System,
    splits: dict[str, dict[str, np.ndarray]],
    arguments: dict[str, Any],
    *,
    on_disk: Collection[str] = (),
    **extra: Any,
) -> None:
    """Write the split files, then ``metadata.json`` (with their checksums), atomically.

    The metadata records the system, the split sizes and statistics and the
    ``arguments`` the dataset was made with (``source``, ``seed``,
    ``chunk_length``, ``contact_fraction``, ``noise_std`` when noise was
    added, ``stride`` when the chunks are windows, ``true_parameters`` when
    recorded data declares its config's parameters true); ``extra`` entries
    (e.g. the simulation's ``device``) follow ``parameters_known``.

    ``on_disk``: splits whose files are already in ``folder`` and hold
    ``splits[name]`` (written by :func:`write_split` as the run went, or reused
    from an interrupted run): they are not written again, their checksums are
    computed from the files. The other splits' files are written here.
    """
    files: dict[str, str] = {}
    for name in SPLITS:
        path = folder / f"{name}.npz"
        if name not in on_disk:
            write_split(folder, name, splits[name])
        files[path.name] = sha256_file(path)
    seed = arguments["seed"]
    simulated = arguments["source"] == "simulated"
    metadata = {
        "format_version": FORMAT_VERSION,
        "task": system.name,
        "source": arguments["source"],
        "config": jsonable(system.config.model_dump(mode="json")),
        "seed": seed,
        "seeds": split_seeds(seed),
        "dt": system.dt,
        "n_states": int(splits["train"]["traj"].shape[1]),
        **{f"n_{s}": len(splits[s]["traj"]) for s in SPLITS},
        "contact_model": arguments.get("contact_model", "CM" if simulated else None),
        "noise_std": arguments.get("noise_std", 0.0),
        "chunk_length": arguments["chunk_length"],
        "contact_fraction": arguments["contact_fraction"],
        "stride": arguments.get("stride"),
        "parameters_known": simulated or bool(arguments.get("true_parameters", False)),
        **extra,
        "diffcontact_version": __version__,
        "created": _now(),
        "stats": {s: _split_stats(splits[s]) for s in SPLITS},
        "arguments": arguments,
        "files": files,
    }
    metadata = jsonable(metadata)
    metadata[METADATA_CHECKSUM] = metadata_checksum(metadata)
    atomic_write_json(folder / METADATA, metadata)
    (folder / MARKER).unlink(missing_ok=True)


def _split_stats(arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    """Counts of a split for the metadata: trajectories, chunks and states in contact."""
    contact = arrays["contact"]
    return {
        "n": int(contact.shape[0]),
        "n_chunks": int(arrays["chunk_has_contact"].shape[0]),
        "chunks_with_contact": int(arrays["chunk_has_contact"].sum()),
        "trajectories_with_contact": int(contact.any(1).sum()),
        "share_of_states_in_contact": float(contact.mean()) if contact.size else 0.0,
    }
