"""Noise on the chunks only, with the right std; on a chain pendulum's angles."""

from __future__ import annotations

import torch

from diffcontact.learning.data import noise as noise_mod
from diffcontact.learning.data.format import load_dataset
from diffcontact.learning.data.generate import generate_dataset
from diffcontact.systems import System

from .support import BP5, L


def test_noise_only_on_chunks_with_the_right_std(bp5_dir, tmp_path, monkeypatch):
    clean = load_dataset(bp5_dir).train

    def replay(self, z0, steps=None, **kwargs):  # the clean simulation, without re-running it
        assert torch.equal(z0, clean.traj[:, 0]) and steps == clean.traj.shape[1] - 1
        return clean.traj.clone()

    monkeypatch.setattr(System, "simulate", replay)
    noisy = generate_dataset(
        BP5, tmp_path / "noisy", n_train=6, n_val=0, n_test=0, noise_std=0.01, progress=False
    )
    split = load_dataset(noisy).train
    assert torch.equal(split.traj, clean.traj)  # same seed, clean trajectories
    assert torch.equal(split.chunk_start, clean.chunk_start)
    assert torch.equal(split.contact, clean.contact)
    diff = split.chunks - clean.chunks
    assert abs(float(diff.mean())) < 0.003
    assert 0.008 < float(diff.std()) < 0.012
    assert len(load_dataset(noisy).val) == 0


def test_pendulum_noise_on_angles_keeps_link_lengths(cp3_noisy_dir):
    ds = load_dataset(cp3_noisy_dir)
    split = ds.train
    lengths = torch.tensor(ds.config.link_lengths, dtype=torch.float64)
    pivot = torch.tensor(ds.config.pivot, dtype=torch.float64)

    def link_lengths(z):
        x = z[..., 0, :, :]
        prev = torch.cat([pivot.expand_as(x[..., :1, :]), x[..., :-1, :]], dim=-2)
        return (x - prev).norm(dim=-1)

    assert torch.allclose(link_lengths(split.chunks), lengths.expand(8, L, 3), atol=1e-12)
    # velocities stay tangent to the links: d/dt |link|^2 = 0
    x, v = split.chunks[..., 0, :, :], split.chunks[..., 1, :, :]
    seg = x - torch.cat([pivot.expand_as(x[..., :1, :]), x[..., :-1, :]], dim=-2)
    dv = v - torch.cat([torch.zeros_like(v[..., :1, :]), v[..., :-1, :]], dim=-2)
    assert float((seg * dv).sum(-1).abs().max()) < 1e-12

    idx = split.chunk_start[:, None] + torch.arange(L)
    clean = split.traj[torch.arange(8)[:, None], idx]
    q_noisy, qd_noisy = noise_mod.chain_angles(split.chunks, pivot)
    q_clean, qd_clean = noise_mod.chain_angles(clean, pivot)
    dq = torch.remainder(q_noisy - q_clean + torch.pi, 2 * torch.pi) - torch.pi
    for noise in (dq, qd_noisy - qd_clean):
        assert 0.035 < float(noise.std()) < 0.065
