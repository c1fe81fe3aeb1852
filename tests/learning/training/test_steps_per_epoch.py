"""Epochs defined by optimiser steps; windows drawn weighted by the contact fraction."""

from __future__ import annotations

import json
import math

import lightning.pytorch as pl
import pytest
import torch

import diffcontact as dc
from diffcontact.learning.data.arrays import dataset_from_arrays
from diffcontact.learning.training.options import TrainingInputError
from diffcontact.learning.training.run import (
    ChunkDataModule,
    EpochShuffleSampler,
    contact_weights,
    train,
)

from .support import SMALL


class _Steps(pl.Callback):
    """Records the optimiser steps taken and the batches seen per epoch."""

    def __init__(self) -> None:
        self.batches: dict[int, int] = {}
        self.global_step = 0

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
        epoch = trainer.current_epoch
        self.batches[epoch] = self.batches.get(epoch, 0) + 1

    def on_train_end(self, trainer, module) -> None:
        self.global_step = trainer.global_step


def test_the_default_sampler_is_one_permutation_per_epoch():
    for epoch in (0, 3):
        s = EpochShuffleSampler(13, 5)
        s.set_epoch(epoch)
        gen = torch.Generator().manual_seed(5 * 100_003 + epoch)
        assert list(s) == torch.randperm(13, generator=gen).tolist() and len(s) == 13
    more = EpochShuffleSampler(5, 2, draws=12)
    order = list(more)
    assert len(order) == len(more) == 12
    assert sorted(order[:5]) == sorted(order[5:10]) == list(range(5))  # whole passes first
    assert order[:5] == list(EpochShuffleSampler(5, 2))


def test_weighted_draws_hit_the_contact_fraction():
    has = torch.tensor([True] * 10 + [False] * 90)
    for f in (0.5, 0.2):
        w = contact_weights(has, f)
        assert w is not None and float(w.sum()) == pytest.approx(1.0)
        s = EpochShuffleSampler(100, 0, draws=20_000, weights=w)
        drawn = torch.tensor(list(s))
        assert float(has[drawn].double().mean()) == pytest.approx(f, abs=0.015)
    assert contact_weights(torch.zeros(4, dtype=torch.bool), 0.5) is None
    assert contact_weights(torch.ones(4, dtype=torch.bool), 0.5) is None
    with pytest.raises(ValueError, match="non-negative"):
        EpochShuffleSampler(3, 0, weights=torch.tensor([1.0, -1.0, 0.0]))


def test_datamodule_steps():
    chunks = torch.zeros(50, 5, 2, 1, 2)
    plain = ChunkDataModule(chunks, chunks, batch_size=8)
    assert plain.draws() is None and len(plain.train_dataloader()) == 7  # one pass
    fixed = ChunkDataModule(chunks, chunks, batch_size=8, steps_per_epoch=3)
    assert fixed.draws() == 24 and len(fixed.train_dataloader()) == 3
    w = torch.ones(50, dtype=torch.float64)
    weighted = ChunkDataModule(chunks, chunks, batch_size=8, weights=w, n_reference=12)
    assert weighted.draws() == 16 and len(weighted.train_dataloader()) == 2  # ceil(12 / 8)
    assert weighted.draws(world=2) == 16  # ceil(ceil(12 / 2) / 8) = 1 step on each rank


@pytest.fixture(scope="module")
def windows_data(tmp_path_factory):
    """Recorded BP5 data: 10 training trajectories of 16 states, every window a chunk."""
    system = dc.load_system("BP5")
    traj = system.simulate(system.sample_initial_conditions(12, seed=4), 15)
    folder = tmp_path_factory.mktemp("win") / "data"
    return dataset_from_arrays(traj, "BP5", folder, progress=False)


def test_training_on_windows_takes_the_steps_of_one_chunk_per_trajectory(windows_data, tmp_path):
    from diffcontact.learning.data.format import load_dataset

    ds = load_dataset(windows_data)
    M, n_train = len(ds.split("train").chunks), ds.counts["train"]
    assert M > 5 * n_train  # every window
    steps = _Steps()
    train(windows_data, tmp_path / "a", epochs=2, batch_size=4, callbacks=[steps], **SMALL)
    per_epoch = math.ceil(n_train / 4)
    assert steps.batches == {0: per_epoch, 1: per_epoch}
    run = json.loads((tmp_path / "a" / "run.json").read_text())
    assert run["sampling"] == "windows weighted by contact_fraction"
    assert "steps_per_epoch" not in run
    # explicit steps per epoch: the schedule follows them, not the data size
    steps = _Steps()
    train(windows_data, tmp_path / "b", epochs=2, batch_size=4, steps_per_epoch=3,
          callbacks=[steps], **SMALL)  # fmt: skip
    assert steps.batches == {0: 3, 1: 3} and steps.global_step == 6
    assert json.loads((tmp_path / "b" / "run.json").read_text())["steps_per_epoch"] == 3
    # resuming with other steps per epoch is another run
    with pytest.raises(TrainingInputError, match="steps_per_epoch: 3 -> 2"):
        train(windows_data, tmp_path / "b", epochs=3, batch_size=4, steps_per_epoch=2,
              resume=True, **SMALL)  # fmt: skip
    with pytest.raises(TrainingInputError, match="steps_per_epoch must be a positive integer"):
        train(windows_data, tmp_path / "c", steps_per_epoch=0, **SMALL)


def test_one_chunk_per_trajectory_keeps_its_epochs(bp5_data, tmp_path):
    steps = _Steps()
    train(bp5_data, tmp_path / "a", epochs=1, batch_size=3, callbacks=[steps], **SMALL)
    assert steps.batches == {0: 3}  # ceil(8 / 3): one pass over the 8 chunks
    run = json.loads((tmp_path / "a" / "run.json").read_text())
    assert "sampling" not in run and "steps_per_epoch" not in run
