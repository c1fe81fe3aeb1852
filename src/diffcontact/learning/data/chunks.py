"""Contact states and the choice of one training chunk per trajectory."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from diffcontact.learning.data.checks import float_arg, int_arg
from diffcontact.learning.data.format import STREAM_CHUNKS, STREAM_NOISE
from diffcontact.learning.data.noise import add_chunk_noise
from diffcontact.systems import System

__all__ = ["chunk_split", "contact_states", "select_chunks"]


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


def chunk_split(
    system: System,
    traj: np.ndarray,
    contact: np.ndarray,
    split_seed: int,
    chunk_length: int,
    contact_fraction: float,
    noise_std: float,
) -> dict[str, np.ndarray]:
    """The arrays of one split file from its clean trajectories ``(N, T, 2, P, d)``."""
    rng = np.random.default_rng([split_seed, STREAM_CHUNKS])
    start, has = select_chunks(contact, chunk_length, contact_fraction, rng)
    idx = start[:, None] + np.arange(chunk_length)  # (N, L)
    chunks = np.take_along_axis(traj, idx[:, :, None, None, None], axis=1)
    if noise_std > 0:
        noise_rng = np.random.default_rng([split_seed, STREAM_NOISE])
        chunks = add_chunk_noise(system, chunks, noise_std, noise_rng)
    return {
        "traj": np.ascontiguousarray(traj, dtype=np.float64),
        "chunks": np.ascontiguousarray(chunks, dtype=np.float64),
        "chunk_start": start.astype(np.int64),
        "chunk_has_contact": has.astype(bool),
        "contact": contact.astype(bool),
    }
