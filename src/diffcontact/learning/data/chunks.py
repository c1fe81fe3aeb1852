"""Contact flags of states and the choice of training chunks (one per trajectory, or windows)."""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

from diffcontact.learning.data.checks import float_arg, int_arg
from diffcontact.learning.data.format import STREAM_CHUNKS, STREAM_NOISE
from diffcontact.learning.data.noise import add_chunk_noise
from diffcontact.systems import System

__all__ = [
    "DEFAULT_IMPACT_TOL",
    "chunk_split",
    "contact_cues",
    "contact_flags",
    "contact_states",
    "event_states",
    "impact_intervals",
    "merge_cues",
    "select_chunks",
    "window_chunks",
]

log = logging.getLogger(__name__)

# a velocity change this far (relative to the trajectory's RMS speed) from what the
# neighbouring steps show is an impact; measured in docs/data.md ("Contact flags")
DEFAULT_IMPACT_TOL = 0.2
# neighbouring intervals whose velocity change estimates the smooth dynamics' a * dt
_NEIGHBOURS = (1, 2)


def contact_states(system: System, traj: Tensor | np.ndarray, gap_tol: float = 0.0) -> np.ndarray:
    """States in contact: ``(N, T)`` bool, any candidate gap < ``gap_tol`` at the state's positions.

    For simulated data (``gap_tol = 0``) these are the states at which a
    contact was resolved.

    Args:
        system: the system whose geometry (radii, walls, limits) decides.
        traj: ``(N, T, 2, P, d)`` trajectories.
        gap_tol: a gap (in the config's length unit) below which a state counts
            as in contact (0: penetration only).
    """
    z = torch.as_tensor(traj)
    if not z.is_floating_point():
        z = z.to(torch.float64)
    with torch.no_grad():
        gaps = system.gaps(z[..., 0, :, :])  # (N, T, K)
    return (gaps < gap_tol).any(-1).cpu().numpy()


def impact_intervals(traj: Tensor | np.ndarray, tol: float = DEFAULT_IMPACT_TOL) -> np.ndarray:
    """Intervals between samples across which the velocities jump: ``(N, T - 1)`` bool.

    With ``dv_t = v_{t+1} - v_t`` per point (``(P, d)``), smooth dynamics
    change the velocity by about ``a dt``, which the neighbouring intervals
    show: ``r_t = min_j ||dv_t - dv_j||`` over ``j = t +- 1, t +- 2`` (those
    that exist; the neighbour estimates ``a dt``, the difference is
    ``O(dt^2 * jerk)`` for smooth motion). Interval ``t`` is an impact when
    ``max over points of r_t > tol * s``, with ``s`` the trajectory's RMS point
    speed. An impact between two samples, invisible in the positions (no
    penetration at any sample), shows as such a jump. Trajectories of fewer
    than three states have no neighbouring interval: nothing is flagged.

    Args:
        traj: ``(N, T, 2, P, d)`` trajectories.
        tol: the threshold relative to the RMS speed (``inf``: flag nothing).

    Returns:
        ``(N, T - 1)`` bool: interval ``t`` lies between states ``t`` and ``t + 1``.
    """
    z = np.asarray(traj.detach().cpu() if isinstance(traj, Tensor) else traj, dtype=np.float64)
    if z.ndim != 5 or z.shape[2] != 2:
        raise ValueError(f"trajectories must have shape (N, T, 2, P, d), got {z.shape}")
    v = z[:, :, 1]  # (N, T, P, d)
    N, T = v.shape[:2]
    flags = np.zeros((N, max(T - 1, 0)), dtype=bool)
    if T < 3 or math.isinf(tol):
        return flags
    # the test is homogeneous in v: each trajectory is scaled exactly, by the power of two
    # of its largest |v|, so that squared speeds do not overflow (velocities of 1e300 made
    # the RMS speed inf, and nothing was flagged)
    _, exponent = np.frexp(np.abs(v).max(axis=(1, 2, 3), keepdims=True))
    v = np.ldexp(v, -exponent)
    dv = np.diff(v, axis=1)  # (N, T - 1, P, d)
    r = np.full(dv.shape[:3], np.inf)  # (N, T - 1, P)
    for k in _NEIGHBOURS:  # two fixed offsets, vectorised over trajectories and time
        if k >= T - 1:
            break
        d = np.linalg.norm(dv[:, k:] - dv[:, :-k], axis=-1)  # interval t + k vs t
        r[:, k:] = np.minimum(r[:, k:], d)
        r[:, :-k] = np.minimum(r[:, :-k], d)
    speed = np.sqrt(np.mean(np.sum(v * v, axis=-1), axis=(1, 2)))  # (N,)
    return r.max(-1) > tol * speed[:, None]


def event_states(event_times: Any, n_trajectories: int, n_states: int, dt: float) -> np.ndarray:
    """States flagged by impact times: ``(N, T)`` bool.

    An event at time ``tau`` (seconds after the trajectory's first state)
    flags state ``ceil(tau / dt)``, the first state after it (the state itself
    when the event falls on a sample, within 1e-6 dt), so every chunk that
    spans the event contains a flagged state and no chunk starts just
    after it.

    Args:
        event_times: ``(N, E)`` floats, NaN where a trajectory has fewer than
            ``E`` events.
        n_trajectories, n_states, dt: ``N``, ``T`` and the time step.

    Raises:
        ValueError: not numbers, rows of different lengths, wrong shape, or a
            time outside ``[0, (T - 1) dt]`` (by more than ``1e-6 dt``, at either end).
    """
    if isinstance(event_times, Tensor):
        event_times = event_times.detach().cpu().numpy()
    try:
        ev = np.asarray(event_times)
    except (TypeError, ValueError):  # numpy's "inhomogeneous shape"
        raise ValueError(
            "event_times must be an (N, E) array of times in seconds: rows of one length "
            "(pad trajectories with fewer events with NaN)"
        ) from None
    try:  # numbers (None in a list of lists pads, as NaN), not strings or booleans
        if ev.dtype.kind not in "fiuO":
            raise TypeError
        ev = ev.astype(np.float64)
    except (TypeError, ValueError):
        what = "strings" if ev.dtype.kind in "US" else str(ev.dtype)
        raise ValueError(
            f"event_times must be numbers (times in seconds, NaN-padded), got {what}"
        ) from None
    if ev.ndim != 2 or ev.shape[0] != n_trajectories:
        raise ValueError(
            f"event_times must have shape (N, E) = ({n_trajectories}, E) (NaN-padded times in "
            f"seconds), got {ev.shape}"
        )
    flags = np.zeros((n_trajectories, n_states), dtype=bool)
    if np.isinf(ev).any():  # NaN pads; an infinite time is no time in the recording
        n, e = np.argwhere(np.isinf(ev))[0]
        raise ValueError(
            f"event_times: trajectory {n} has an infinite event time ({ev[n, e]}); pad "
            "trajectories with fewer events with NaN"
        )
    n, e = np.nonzero(np.isfinite(ev))
    tau = ev[n, e]
    end = (n_states - 1) * dt
    tol = 1e-6 * dt  # the same at both ends: an event this close to a sample is on it
    outside = (tau < -tol) | (tau > end + tol)
    if outside.any():
        i = int(np.flatnonzero(outside)[0])
        raise ValueError(
            f"event_times: trajectory {n[i]} has an event at t = {tau[i]:g} s, outside its "
            f"recording [0, {end:g}] s; {int(outside.sum())} event(s) out of range"
        )
    k = np.clip(np.ceil(tau / dt - 1e-6), 0, n_states - 1).astype(np.int64)
    flags[n, k] = True
    return flags


def contact_flags(
    system: System,
    traj: np.ndarray,
    *,
    gap_tol: float = 0.0,
    impact_tol: float = DEFAULT_IMPACT_TOL,
    contact: Any = None,
    event_times: Any = None,
) -> tuple[np.ndarray, dict[str, int]]:
    """Contact flags of recorded states: ``(N, T)`` bool, and how many states each cue flagged.

    A state is flagged when (any of)

    - ``gap``: some candidate gap is below ``gap_tol`` (:func:`contact_states`);
    - ``impact``: the velocities jumped in the interval before it
      (:func:`impact_intervals` with ``impact_tol``): state ``t + 1`` for an
      impact in ``(t, t + 1)``, so chunks that span the impact contain a
      flagged state and no chunk starts right after it;
    - ``given``: the user's flags ``contact (N, T)`` are set;
    - ``events``: an impact time of ``event_times (N, E)`` falls in the
      interval before it (:func:`event_states`).

    Returns:
        ``(flags, counts)``: counts of states flagged by each cue (``gap``,
        ``impact``, ``given``, ``events``) and in all (``total``).
    """
    cues = contact_cues(
        system, traj, gap_tol=gap_tol, impact_tol=impact_tol, contact=contact,
        event_times=event_times,
    )  # fmt: skip
    return merge_cues(cues)


def contact_cues(
    system: System,
    traj: np.ndarray,
    *,
    gap_tol: float = 0.0,
    impact_tol: float = DEFAULT_IMPACT_TOL,
    contact: Any = None,
    event_times: Any = None,
) -> dict[str, np.ndarray]:
    """The ``(N, T)`` bool flags of each cue of :func:`contact_flags`, by name.

    ``{"gap": ..., "impact": ..., "given": ..., "events": ...}``; their union is
    :func:`contact_flags`'s flags (:func:`merge_cues`).
    """
    traj = np.asarray(traj, dtype=np.float64)
    N, T = traj.shape[:2]
    gap = contact_states(system, traj, gap_tol)
    impact = np.zeros((N, T), dtype=bool)
    impact[:, 1:] = impact_intervals(traj, impact_tol)
    given = np.zeros((N, T), dtype=bool)
    if contact is not None:
        try:
            c = np.asarray(contact)
        except (TypeError, ValueError):  # numpy's "inhomogeneous shape"
            raise ValueError(
                f"contact flags must be a boolean array of shape (N, T) = ({N}, {T}), got "
                "rows of different lengths"
            ) from None
        if c.shape != (N, T) or c.dtype.kind not in "biu":
            raise ValueError(
                f"contact flags must be a boolean array of shape (N, T) = ({N}, {T}), got "
                f"{c.dtype} of shape {c.shape}"
            )
        if c.dtype.kind in "iu" and not np.isin(c, (0, 1)).all():
            raise ValueError(
                f"contact flags must be booleans (or 0 and 1), got values "
                f"{np.unique(c[~np.isin(c, (0, 1))])[:5].tolist()}"
            )
        given = c.astype(bool)
    events = np.zeros((N, T), dtype=bool)
    if event_times is not None:
        events = event_states(event_times, N, T, system.dt)
    return {"gap": gap, "impact": impact, "given": given, "events": events}


def merge_cues(cues: dict[str, np.ndarray]) -> tuple[np.ndarray, dict[str, int]]:
    """The union of :func:`contact_cues`' flags and the count of each cue and in all."""
    flags = np.logical_or.reduce(list(cues.values()))
    counts = {name: int(c.sum()) for name, c in cues.items()}
    counts["total"] = int(flags.sum())
    return flags, counts


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
    L = int_arg("chunk_length", chunk_length, 1)
    frac = float_arg("contact_fraction", contact_fraction, 0.0, 1.0)
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
            f"{rows.size} of {N} trajectories ({listed}) are flagged in contact at every "
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


def window_chunks(
    contact: np.ndarray, chunk_length: int = 5, stride: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every window of every trajectory as a chunk: starts ``0, stride, 2 stride, ...``.

    Windows that would start in contact are left out (as in
    :func:`select_chunks`); the others are listed trajectory by trajectory,
    in time order. Vectorised.

    Args:
        contact: ``(N, T)`` bool flags of the states.
        chunk_length: ``L``.
        stride: states between the starts of consecutive windows (1: all).

    Returns:
        ``trajectory (M,)`` and ``start (M,)`` int64, ``has_contact (M,)`` bool.
    """
    contact = np.asarray(contact, dtype=bool)
    L = int_arg("chunk_length", chunk_length, 1)
    stride = int_arg("stride", stride, 1)
    T = contact.shape[1]
    if T < L:
        raise ValueError(f"trajectories hold {T} states, fewer than chunk_length={L}")
    # a stride beyond the last start takes start 0 only (and beyond int64, broke arange)
    starts = np.arange(0, T - L + 1, min(stride, T - L + 1))
    windows = np.lib.stride_tricks.sliding_window_view(contact, L, axis=1)[:, starts]
    has = windows.any(-1)  # (N, S')
    n, k = np.nonzero(~contact[:, starts])
    return n.astype(np.int64), starts[k].astype(np.int64), has[n, k]


def _warn_fraction(split: str, has: np.ndarray, frac: float, windows: bool) -> None:
    """Warn when the chunks cannot give the requested share of contact chunks."""
    M, c = len(has), int(has.sum())
    if M == 0:
        return
    if windows:
        # a sampling weight: met unless a kind that must be drawn is missing
        missing = (frac > 0 and c == 0) or (frac < 1 and c == M)
        if missing:
            kind = "contains a contact" if c == 0 else "is free of contact"
            log.warning(
                "%s: --contact-fraction %g cannot be met: none of the %d chunks %s; the chunks "
                "are drawn uniformly", split, frac, M, kind,
            )  # fmt: skip
        return
    target = math.floor(frac * M + 0.5)
    if c != target:
        log.warning(
            "%s: --contact-fraction %g cannot be met: %d of %d chunks contain a contact "
            "(%d asked for; the trajectories allow no %s)",
            split, frac, c, M, target, "more" if c < target else "fewer",
        )  # fmt: skip


def chunk_split(
    system: System,
    traj: np.ndarray,
    contact: np.ndarray,
    split_seed: int,
    chunk_length: int,
    contact_fraction: float,
    noise_std: float,
    stride: int | None = None,
    name: str = "split",
) -> dict[str, np.ndarray]:
    """The arrays of one split file from its clean trajectories ``(N, T, 2, P, d)``.

    ``stride=None``: one chunk per trajectory (:func:`select_chunks`); an
    integer: the windows of :func:`window_chunks`, with their trajectory in
    ``chunk_traj``. Noise (``noise_std > 0``) is drawn for every chunk
    (overlapping windows get independent noise).
    """
    rng = np.random.default_rng([split_seed, STREAM_CHUNKS])
    if len(traj) == 0 and stride is not None:
        owner = start = np.zeros(0, dtype=np.int64)
        has = np.zeros(0, dtype=bool)
    elif stride is None:
        start, has = select_chunks(contact, chunk_length, contact_fraction, rng)
        owner = np.arange(len(traj))
    else:
        owner, start, has = window_chunks(contact, chunk_length, stride)
    _warn_fraction(name, has, contact_fraction, stride is not None)
    idx = start[:, None] + np.arange(chunk_length)  # (M, L)
    chunks = traj[owner[:, None], idx]  # (M, L, 2, P, d)
    if noise_std > 0:
        noise_rng = np.random.default_rng([split_seed, STREAM_NOISE])
        chunks = add_chunk_noise(system, chunks, noise_std, noise_rng)
    out = {
        "traj": np.ascontiguousarray(traj, dtype=np.float64),
        "chunks": np.ascontiguousarray(chunks, dtype=np.float64),
        "chunk_start": start.astype(np.int64),
        "chunk_has_contact": has.astype(bool),
        "contact": contact.astype(bool),
    }
    if stride is not None:
        out["chunk_traj"] = owner.astype(np.int64)
    return out
