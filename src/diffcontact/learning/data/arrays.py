"""Recorded data: :func:`dataset_from_arrays` (``diffcontact generate --from-arrays``)."""

from __future__ import annotations

import hashlib
import json
import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from diffcontact.cli_args import one_line
from diffcontact.io import jsonable, read_npz
from diffcontact.learning.data.checks import (
    DT_RTOL,
    check_seed,
    check_stride,
    constraint_violation,
    float_arg,
    int_arg,
)
from diffcontact.learning.data.chunks import (
    DEFAULT_IMPACT_TOL,
    chunk_split,
    contact_cues,
    merge_cues,
)
from diffcontact.learning.data.convert import VELOCITY_MISMATCH_WARN, velocity_mismatch
from diffcontact.learning.data.format import SPLITS, STREAM_SPLIT, split_seeds
from diffcontact.learning.data.write import output_folder, prepare_folder, write_dataset
from diffcontact.systems import System, load_system

__all__ = ["dataset_from_arrays", "read_arrays_file", "read_flag_entries"]


def _as_array(trajectories: Any) -> np.ndarray:
    if isinstance(trajectories, Tensor):
        trajectories = trajectories.detach().cpu().numpy()
    if isinstance(trajectories, (list, tuple)):  # one array per trajectory: one length
        shapes = [tuple(np.shape(t)) for t in trajectories]
        if len(set(shapes)) > 1:
            first = shapes[0]
            i = next(i for i, sh in enumerate(shapes) if sh != first)
            raise ValueError(
                f"trajectories must share one shape (T, 2, P, d): trajectory 0 has {first}, "
                f"trajectory {i} {shapes[i]}; cut them to a common length T (or split the "
                "longer ones into several trajectories)"
            )
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
    stride: int | None = 1,
    true_parameters: bool = False,
    impact_tol: float = DEFAULT_IMPACT_TOL,
    gap_tol: float = 0.0,
    contact: Any = None,
    event_times: Any = None,
) -> Path:
    """Write a dataset folder (same format as ``generate_dataset``) from recorded data.

    The trajectories are split at random into train/val/test, their states
    flagged for contact (the config's geometry, velocity jumps of impacts
    between samples, and the flags or event times given; ``contact_flags``)
    and cut into chunks: by default every window of ``chunk_length`` states
    (``stride=1``) that starts out of contact, the contact fraction being a
    sampling weight in training (no noise is added: recorded data carries its
    own).

    Args:
        trajectories: ``(N, T, 2, P, d)`` array (numpy or torch): positions then
            velocities of the config's P points in d dimensions, sampled every
            ``dt`` (the config's).
        config: the known geometry and dt: built-in task name, ``.yaml``/``.json``
            path or dict.
        out_dir: dataset folder (as in ``generate_dataset``).
        dt: the recording's time step, checked against the config's ``dt``.
        val_fraction, test_fraction: shares of the trajectories for val and
            test (at least one each when positive; at least one left for train).
        seed: seed of the split (``numpy.random.default_rng([seed, 3])``) and,
            through ``split_seeds``, of the chunk choice.
        chunk_length: states per chunk.
        contact_fraction: the share of training draws that contain a contact
            (a sampling weight over the windows; with ``stride=None``, the
            target share of the one chunk per trajectory, as in
            ``generate_dataset``). A warning says when it cannot be met.
        progress: print messages (e.g. that an existing dataset was reused).
        stride: states between the starts of the windows cut from every
            trajectory (1: all windows; ``T - chunk_length + 1`` or more: the
            window at state 0 only); ``None``: one chunk per trajectory.
        true_parameters: declare the config's masses, mu and e_P the true
            values of the recorded system, so that evaluation compares the
            learned ones with them (default: unknown, nothing is compared).
        impact_tol: a velocity jump beyond ``impact_tol`` times the
            trajectory's RMS speed flags an impact between samples
            (``impact_intervals``; ``inf``: off).
        gap_tol: a state with a gap below this (length units) is flagged (0:
            penetration only).
        contact: optional ``(N, T)`` bool flags of states in contact (added to
            the detected ones).
        event_times: optional ``(N, E)`` impact times in seconds from each
            trajectory's first state, NaN-padded (``event_states``).

    Returns:
        The dataset folder.

    Raises:
        ValueError: a message naming the problem: wrong shape (expected vs
            got), NaN/inf (which trajectory and state), dt different from the
            config's, fewer states than ``chunk_length``, trajectories in contact
            at every possible chunk start, a train or val split in contact at every start the
            stride uses (it would get no chunk), bad fractions, or an output
            folder as in ``generate_dataset``.

    Warns:
        RuntimeWarning: velocities that do not match the positions' motion
        (``velocity_mismatch`` above 0.25, as ``diffcontact convert`` warns:
        other units, frame or order of points, or data sampled at another step
        than the config's ``dt``), and trajectories that get no chunk at the
        starts the stride uses.
    """
    system = load_system(config)
    seed = check_seed(seed)
    chunk_length = int_arg("chunk_length", chunk_length, 2)
    contact_fraction = float_arg("contact_fraction", contact_fraction, 0.0, 1.0)
    if stride is not None:
        stride = int_arg("stride", stride, 1)
    if not isinstance(true_parameters, bool):
        raise ValueError(f"true_parameters must be True or False, got {true_parameters!r}")
    impact_tol = float_arg("impact_tol", impact_tol, 0.0, math.inf, infinite=True)  # inf: off
    gap_tol = float_arg("gap_tol", gap_tol, 0.0, math.inf)
    vf = float_arg("val_fraction", val_fraction, 0.0, 1.0, high_open=True)
    tf = float_arg("test_fraction", test_fraction, 0.0, 1.0, high_open=True)
    if vf + tf >= 1:
        raise ValueError(
            f"val_fraction + test_fraction must be below 1 (some data must be left to "
            f"train on), got {vf} + {tf}"
        )
    if dt is not None:
        dt_f = float_arg("dt", dt, 0.0, math.inf, low_open=True)
        if not math.isclose(dt_f, system.dt, rel_tol=DT_RTOL, abs_tol=1e-12):
            raise ValueError(
                f"dt={dt_f!r} of the data differs from the config's dt={system.dt!r}; models "
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
    if T < chunk_length:  # (before the checks below: T = 0 broke their reshape)
        raise ValueError(
            f"trajectories hold {T} states, fewer than chunk_length={chunk_length}: each "
            f"trajectory needs at least {chunk_length} states"
        )
    if stride is not None:
        stride = check_stride(stride, T, chunk_length)
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
    broken = constraint_violation(system, arr[:, :, 0])
    if broken is not None:
        raise ValueError(broken)
    n_val = math.floor(vf * N + 0.5) if vf > 0 else 0
    n_test = math.floor(tf * N + 0.5) if tf > 0 else 0
    n_val, n_test = (max(n_val, 1) if vf > 0 else 0), (max(n_test, 1) if tf > 0 else 0)
    n_train = N - n_val - n_test
    if n_train < 1:
        raise ValueError(
            f"{N} {'trajectory is' if N == 1 else 'trajectories are'} too few for "
            f"val_fraction={vf:g} and test_fraction={tf:g} "
            "(at least one each): no trajectory is left for training"
        )

    cues = contact_cues(
        system, arr, gap_tol=gap_tol, impact_tol=impact_tol, contact=contact,
        event_times=event_times,
    )  # fmt: skip
    contact, flag_counts = merge_cues(cues)
    S = T - chunk_length + 1
    stuck = contact[:, :S].all(1)
    if stuck.any():
        raise ValueError(_stuck_message(system, arr, cues, np.flatnonzero(stuck), S, gap_tol))
    perm = np.random.default_rng([seed, STREAM_SPLIT]).permutation(N)
    index = {
        "test": np.sort(perm[:n_test]),
        "val": np.sort(perm[n_test : n_test + n_val]),
        "train": np.sort(perm[n_test + n_val :]),
    }
    if stride is not None and stride > 1:
        _check_stride_starts(cues, contact, index, stride, S, gap_tol)
    mismatch = _velocity_mismatch_message(system, arr)  # (after the refusals: one line each)
    if mismatch is not None:
        warnings.warn(mismatch, RuntimeWarning, stacklevel=2)

    digest = hashlib.sha256(repr(arr.shape).encode() + arr.tobytes()).hexdigest()
    arguments = {
        "source": "arrays",
        "config": jsonable(system.config.model_dump(mode="json")),
        "traj_sha256": digest,
        "n_trajectories": N,
        "n_states": T,
        "val_fraction": vf,
        "test_fraction": tf,
        "seed": seed,
        "chunk_length": chunk_length,
        "contact_fraction": contact_fraction,
        "stride": stride,
        "true_parameters": true_parameters,
        "impact_tol": None if math.isinf(impact_tol) else impact_tol,  # None: off
        "gap_tol": gap_tol,
    }
    if contact is not None or event_times is not None:
        given = [np.asarray(a, dtype=np.float64) for a in (contact, event_times) if a is not None]
        arguments["flags_sha256"] = hashlib.sha256(
            b"".join(repr(a.shape).encode() + np.nan_to_num(a, nan=-1.0).tobytes() for a in given)
        ).hexdigest()
    folder = output_folder(out_dir)
    if prepare_folder(folder, arguments, progress):
        return folder

    seeds = split_seeds(seed)
    splits = {
        name: chunk_split(
            system,
            arr[index[name]],
            contact[index[name]],
            seeds[name],
            chunk_length,
            contact_fraction,
            0.0,
            stride,
            name,
        )
        for name in SPLITS
    }
    source_indices = {name: index[name].tolist() for name in SPLITS}
    write_dataset(
        folder, system, splits, arguments, source_indices=source_indices,
        contact_flags=flag_counts,
    )  # fmt: skip
    return folder


# what flags a state (contact_cues), and where to look when it flags too many
_CUE_WORDS = {
    "gap": (
        "a gap below gap_tol={tol:g}",
        "the config's geometry (radii, walls, limits) and the units of the positions (mm "
        "where the config has m?)",
    ),
    "impact": ("a velocity jump before it", "impact_tol (inf: off)"),
    "given": ("the contact flags given", "the contact flags"),
    "events": ("an event time before it", "the event times"),
}


def _flagged_by(
    cues: dict[str, np.ndarray], r: int, states: slice | np.ndarray, gap_tol: float
) -> tuple[str, str]:
    """Which cues flag trajectory ``r``'s ``states``, with how many of them each (most
    first), and where to look: ``(by, where)``, parts of one-line messages."""
    counts = {name: int(flags[r, states].sum()) for name, flags in cues.items()}
    named = sorted((name for name in counts if counts[name]), key=lambda c: -counts[c])
    by = ", ".join(
        f"{_CUE_WORDS[name][0].format(tol=gap_tol)} at {counts[name]} of them" for name in named
    )
    return by, ", ".join(_CUE_WORDS[name][1] for name in named)


def _listed(rows: np.ndarray) -> str:
    return ", ".join(map(str, rows[:10].tolist())) + (" ..." if rows.size > 10 else "")


def _stuck_message(
    system: System,
    arr: np.ndarray,
    cues: dict[str, np.ndarray],
    rows: np.ndarray,
    S: int,
    gap_tol: float,
) -> str:
    """Why trajectories ``rows`` are flagged at every chunk start ``0..S-1`` (one line).

    Names the cues that flag the first of them, with how many of those states each
    flags (most first), and its first state's smallest gap, below ``gap_tol`` or not.
    """
    N = arr.shape[0]
    r = int(rows[0])
    by, where = _flagged_by(cues, r, slice(0, S), gap_tol)
    with torch.no_grad():
        gaps = system.gaps(torch.from_numpy(arr[r, 0, 0]))
    nearest = ""
    if gaps.numel():
        k = int(gaps.argmin())
        gap = float(gaps[k])
        within = "below" if gap < gap_tol else "not below"
        nearest = (
            f"; its state 0's smallest gap is {gap:.3g}, {within} gap_tol={gap_tol:g} "
            f"(candidate {system.contact_names[k]!r})"
        )
    return (
        f"{rows.size} of {N} trajectories ({_listed(rows)}) are flagged in contact at every "
        f"state that could start a chunk (states 0..{S - 1}), so they cannot be chunked (a "
        f"chunk must start out of contact); trajectory {r}'s states 0..{S - 1} are flagged by "
        f"{by}{nearest}. Drop them, or check {where}"
    )


def _states_text(states: np.ndarray) -> str:
    """``"state 0"``, ``"states 0, 10, 20"``, ``"states 0, 4, 8, 12, ..., 32"``."""
    if states.size == 1:
        return f"state {states[0]}"
    shown = states[:4].tolist() + (["...", states[-1]] if states.size > 5 else states[4:].tolist())
    return "states " + ", ".join(map(str, shown))


def _check_stride_starts(
    cues: dict[str, np.ndarray],
    contact: np.ndarray,
    index: dict[str, np.ndarray],
    stride: int,
    S: int,
    gap_tol: float,
) -> None:
    """Refuse a stride at whose starts ``0, stride, ...`` no chunk of the train or val
    split can start out of contact (the split would be written empty); warn about the
    trajectories that get no chunk there while their split has some. (Every trajectory
    has an unflagged start among ``0..S-1``: checked before.)"""
    starts = np.arange(0, S, min(stride, S))  # (a stride beyond S: start 0 alone)
    chunkless = contact[:, starts].all(1)  # (N,)
    if not chunkless.any():
        return
    at = _states_text(starts)
    for name in ("train", "val"):
        rows = index[name]
        if rows.size and chunkless[rows].all():
            r = int(rows[0])
            by, where = _flagged_by(cues, r, starts, gap_tol)
            n = f"{rows.size} {'trajectory' if rows.size == 1 else 'trajectories'}"
            raise ValueError(
                f"stride={stride} leaves the {name} split without a chunk: its {n} "
                f"({_listed(rows)}) {'is' if rows.size == 1 else 'are'} flagged in contact "
                f"at every state the stride lets a chunk start at ({at}; a chunk must start "
                f"out of contact); trajectory {r}'s are flagged by {by}. Use a smaller "
                f"stride (1: every window; other states are out of contact), or check {where}"
            )
    rows = np.flatnonzero(chunkless)
    warnings.warn(
        f"stride={stride}: {rows.size} of {len(contact)} trajectories ({_listed(rows)}) give "
        f"no chunk: they are flagged in contact at every state the stride lets a chunk start "
        f"at ({at}); a smaller stride takes other starts (1: every window)",
        RuntimeWarning,
        stacklevel=3,
    )


def _velocity_mismatch_message(system: System, arr: np.ndarray) -> str | None:
    """The warning for velocities that do not match the positions' motion, as ``diffcontact
    convert`` measures it (:func:`~diffcontact.learning.data.convert.velocity_mismatch`
    above :data:`~diffcontact.learning.data.convert.VELOCITY_MISMATCH_WARN`); ``None``
    when they do, or for fewer than 3 states."""
    if arr.shape[1] < 3:
        return None
    x, v = torch.from_numpy(arr[:, :, 0]), torch.from_numpy(arr[:, :, 1])
    mismatch = velocity_mismatch(x, v, system.dt)
    if not mismatch > VELOCITY_MISMATCH_WARN:
        return None
    size = (
        "more than the median speed, which is 0 (velocities all zero?)"
        if math.isinf(mismatch)
        else f"{mismatch:.2f} of the median speed"
    )
    return (
        f"the velocities do not match the motion of the positions: they differ from the "
        f"positions' finite differences (at the config's dt={system.dt:g}) by {size}; check "
        "their units, frame and order of points, and that the data are sampled at the "
        "config's dt (docs/own-data.md, 'What to check')"
    )


def read_flag_entries(path: str) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The optional entries ``contact (N, T)`` and ``event_times (N, E)`` of an .npz file.

    ``(None, None)`` for an .npy file or when absent (call
    :func:`read_arrays_file` first: it reports unreadable files).
    """
    try:
        found, members = read_npz(Path(path), ("contact", "event_times"))
        if members == [""]:  # an .npy file
            return None, None
    except (OSError, ValueError) as err:
        raise ValueError(
            f"cannot read {path} as .npz or .npy (truncated or corrupted?): {one_line(err)}"
        ) from None
    for key, kinds in (("contact", "biu"), ("event_times", "fiu")):
        if key in found and found[key].dtype.kind not in kinds:
            raise ValueError(
                f"{path}: entry {key!r} must be {'booleans' if key == 'contact' else 'numbers'}, "
                f"got {found[key].dtype}"
            )
    return found.get("contact"), found.get("event_times")


def read_arrays_file(path: str) -> tuple[np.ndarray, float | None, Any]:
    """``traj`` and, when present, ``dt`` and ``config`` (JSON) of an .npz (or an .npy array).

    The file format of ``diffcontact generate --from-arrays`` (what
    ``diffcontact simulate`` writes).
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"--from-arrays file {path!r} does not exist")
    try:
        entries, keys = read_npz(p, ("traj", "dt", "config"))
        if keys == [""]:  # an .npy file: the trajectories
            return entries[""], None, None
    except (OSError, ValueError) as err:
        raise ValueError(
            f"cannot read {path} as .npz or .npy (truncated or corrupted?): {one_line(err)}"
        ) from None
    if "traj" not in entries:
        from diffcontact.learning.data.convert_cli import SOURCES

        source = next((s for s, names in SOURCES.items() if names[0] in keys), None)
        fix = (
            f"it holds {SOURCES[source][0]!r}, an input of `diffcontact convert {source} "
            f"{path} --config CONFIG --out OUT.npz`, which writes a file for --from-arrays"
            if source is not None
            else "save the trajectories with numpy.savez(FILE, traj=...), or convert "
            "positions, coordinates or MuJoCo data with `diffcontact convert`"
        )
        raise ValueError(
            f"{path} has no array named 'traj' (found: {', '.join(keys) or 'nothing'}); {fix}"
        )
    traj, dt, config = entries["traj"], None, None
    if "dt" in entries:
        if entries["dt"].size != 1 or entries["dt"].dtype.kind not in "fiu":
            raise ValueError(
                f"{path}: entry 'dt' must be one number, got {entries['dt'].dtype} of shape "
                f"{entries['dt'].shape}"
            )
        dt = float(entries["dt"].reshape(()))
    if "config" in entries:
        try:
            config = json.loads(str(entries["config"]))
        except json.JSONDecodeError as err:
            raise ValueError(f"{path}: entry 'config' is not JSON: {err}") from None
        except RecursionError:
            raise ValueError(f"{path}: entry 'config' is nested too deeply to be read") from None
        if not isinstance(config, (dict, str)):
            kind = {list: "an array", bool: "a boolean", type(None): "null"}.get(
                type(config), "a number"
            )
            raise ValueError(
                f"{path}: entry 'config' must be a JSON object (a config, as `diffcontact "
                f"simulate` and `diffcontact convert` write it) or a task name, got {kind}"
            )
    return traj, dt, config
