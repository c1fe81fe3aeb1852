"""Measurement noise on training chunks (for a chain pendulum: on its angles)."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from diffcontact.mechanics.bodies import chain_points_2d
from diffcontact.systems import System

__all__ = ["add_chunk_noise", "chain_angles"]


def chain_angles(z: Tensor, pivot: Tensor) -> tuple[Tensor, Tensor]:
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
    q, qdot = chain_angles(z, pivot)
    q = q + noise_std * torch.from_numpy(gen.standard_normal(tuple(q.shape)))
    qdot = qdot + noise_std * torch.from_numpy(gen.standard_normal(tuple(qdot.shape)))
    lengths = torch.tensor(cfg.link_lengths, dtype=z.dtype)
    return chain_points_2d(q, qdot, lengths, pivot).numpy()
