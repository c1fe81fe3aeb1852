"""Recorded data: dataset_from_arrays round trip, validation messages, interrupted writes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from diffcontact.io import atomic_path
from diffcontact.learning.data import write as write_mod
from diffcontact.learning.data.arrays import dataset_from_arrays
from diffcontact.learning.data.format import DatasetError, load_dataset

from .support import BP5, L, all_trajectories, window_contact


def test_arrays_round_trip(bp5_dir, tmp_path, capsys):
    traj = all_trajectories(bp5_dir)  # (12, 20, 2, 5, 2)
    out = dataset_from_arrays(traj, BP5, tmp_path / "rec", dt=0.01, seed=4, progress=False)
    ds = load_dataset(out)
    meta = ds.metadata
    assert meta["source"] == "arrays" and ds.counts == {"train": 10, "val": 1, "test": 1}
    seen = []
    for name in ("train", "val", "test"):
        split = ds.split(name)
        index = meta["source_indices"][name]
        seen += index
        assert np.array_equal(split.traj.numpy(), traj[index])
        window = window_contact(split.contact, split.chunk_start, split.chunk_traj)
        assert not window[:, 0].any()
        assert torch.equal(split.chunk_has_contact, window.any(1))
        idx = split.chunk_start[:, None] + torch.arange(L)
        assert torch.equal(split.chunks, split.traj[split.chunk_traj[:, None], idx])
        # every window (stride 1) that starts out of contact is a chunk
        assert len(split.chunks) == int((~split.contact[:, : 20 - L + 1]).sum())
    assert sorted(seen) == list(range(12))
    # same arrays and arguments: reused; another seed: refused
    dataset_from_arrays(torch.from_numpy(traj), BP5, out, dt=0.01, seed=4)
    assert "reusing" in capsys.readouterr().out
    with pytest.raises(ValueError, match="seed"):
        dataset_from_arrays(traj, BP5, out, seed=5)
    changed = traj.copy()
    changed[0, 3, 1] += 0.1
    with pytest.raises(ValueError, match="traj_sha256"):
        dataset_from_arrays(changed, BP5, out, seed=4)


def test_arrays_validation_messages(recorded, tmp_path):
    out = tmp_path / "rec"

    def fails(traj, match, **kw):
        with pytest.raises(ValueError, match=match):
            dataset_from_arrays(traj, kw.pop("config", BP5), out, **kw)
        assert not out.exists()  # nothing written before validation passes

    bad = recorded.copy()
    bad[2, 5, 0, 1, 0] = np.nan
    bad[3, 7, 1, 0, 1] = np.inf
    fails(bad, r"NaN or infinite values at trajectory 2 state 5 \(t = 0\.05 s\), trajectory 3")
    fails(recorded[..., :1], r"shape \(N, T, 2, 5, 2\) for BP5.*got \(12, 20, 2, 5, 1\)")
    fails(recorded[:, :, :, :3], r"got \(12, 20, 2, 3, 2\)")
    fails(recorded[0], r"got \(20, 2, 5, 2\) \(a single trajectory\? add a leading axis")
    fails(recorded, r"shape \(N, T, 2, 3, 2\) for CP3", config="CP3")
    fails(recorded, r"dt=0\.02 of the data differs from the config's dt=0\.01", dt=0.02)
    fails(recorded[:, :4], r"hold 4 states, fewer than chunk_length=5")
    fails(recorded[:2], r"2 trajectories are too few")
    # a list of trajectories of different lengths (numpy's "inhomogeneous shape" before)
    ragged = [*recorded[:5], recorded[5, :15], *recorded[6:]]
    fails(ragged, r"share one shape \(T, 2, P, d\): trajectory 0 has \(20, 2, 5, 2\), "
          r"trajectory 5 \(15, 2, 5, 2\); cut them to a common length")  # fmt: skip
    fails(recorded, r"val_fraction \+ test_fraction must be below 1", val_fraction=0.5,
          test_fraction=0.5)  # fmt: skip
    fails(recorded, r"val_fraction must be a finite number in \[0, 1\)", val_fraction=1.0)
    fails(np.array([["a"]]), "numeric array")
    overlapping = recorded.copy()
    overlapping[4, :, 0, 0] = (-0.5, 0.5)  # body 0 beyond the left wall at every state
    fails(
        overlapping,
        r"1 of 12 trajectories \(4\) are flagged in contact at every state that could start "
        r"a chunk \(states 0\.\.15\).* flagged by a gap below gap_tol=0 at 16.*smallest gap "
        r"is -0\.\d+, below gap_tol=0 \(candidate 'body 0 penetrates wall 0'\)\. Drop them, "
        r"or check the config's geometry",
    )


def test_an_out_dir_that_is_not_a_path_is_named(recorded):
    """An int out_dir gave pathlib's TypeError (dataset_from_arrays and generate_dataset)."""
    from diffcontact.learning.data.generate import generate_dataset

    for bad in (5, None, ""):
        with pytest.raises(ValueError, match="out_dir must be a path"):
            dataset_from_arrays(recorded, BP5, bad)
        with pytest.raises(ValueError, match="out_dir must be a path"):
            generate_dataset("BP5", bad, n_train=2, n_val=1, n_test=1, progress=False)


def test_flags_given_at_every_chunk_start_are_named_as_the_cause(recorded, tmp_path):
    """Flags given at every state were reported as "body 0 penetrates wall 2 (gap 0.00944)"."""
    out = tmp_path / "rec"
    flags = np.zeros(recorded.shape[:2], dtype=bool)
    flags[7] = True
    with pytest.raises(ValueError) as info:
        dataset_from_arrays(recorded, BP5, out, contact=flags)
    msg = str(info.value)
    assert "1 of 12 trajectories (7) are flagged in contact at every state" in msg, msg
    assert "are flagged by the contact flags given at 16" in msg, msg
    assert "not below gap_tol=0 (candidate '" in msg and "check the contact flags" in msg, msg
    assert "\n" not in msg
    assert not out.exists()


def test_interrupted_write_leaves_no_partial_file(recorded, tmp_path, monkeypatch):
    out = tmp_path / "rec"
    real = write_mod.atomic_save_npz
    calls = []

    def crash_on_second(path, **arrays):
        calls.append(Path(path).name)
        if len(calls) == 2:
            with atomic_path(path) as tmp:
                tmp.write_bytes(b"half")
                raise RuntimeError("simulated crash")
        return real(path, **arrays)

    monkeypatch.setattr(write_mod, "atomic_save_npz", crash_on_second)
    with pytest.raises(RuntimeError, match="simulated crash"):
        dataset_from_arrays(recorded, BP5, out, progress=False)
    names = sorted(p.name for p in out.iterdir())
    assert names == [".generating.json", "train.npz"]  # no val.npz, no temporary, no metadata
    with pytest.raises(DatasetError, match="interrupted run"):
        load_dataset(out)
    with pytest.raises(ValueError, match=r"unfinished dataset .* seed \(0 there, 1 requested\)"):
        dataset_from_arrays(recorded, BP5, out, seed=1)
    monkeypatch.setattr(write_mod, "atomic_save_npz", real)
    dataset_from_arrays(recorded, BP5, out, progress=False)  # same arguments: finishes
    assert sorted(p.name for p in out.iterdir()) == [
        "metadata.json",
        "test.npz",
        "train.npz",
        "val.npz",
    ]
    load_dataset(out)
