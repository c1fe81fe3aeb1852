"""Simulated datasets: independent splits, reuse with the same arguments, refusals,
interrupted runs finished without simulating their finished splits again."""

from __future__ import annotations

import json

import pytest
import torch

from diffcontact.learning.data.format import MARKER, METADATA, load_dataset
from diffcontact.learning.data.generate import generate_dataset
from diffcontact.systems import System

from .support import BP5, SIZES, copy_dataset, read_only_storage, short_config


def test_val_and_test_are_independent_of_train(bp5_dir):
    ds = load_dataset(bp5_dir)
    z0 = {name: ds.split(name).traj[:, 0] for name in ("train", "val", "test")}
    for a, b in (("train", "val"), ("train", "test"), ("val", "test")):
        dist = (z0[a][:, None] - z0[b][None]).flatten(2).abs().amax(-1)
        assert bool((dist > 1e-6).all()), (a, b)


def test_same_arguments_reuse_files(bp5_dir, tmp_path, monkeypatch, capsys):
    folder = copy_dataset(bp5_dir, tmp_path)
    before = {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in folder.iterdir()}

    def no_simulation(*args, **kwargs):
        raise AssertionError("simulated again")

    monkeypatch.setattr(System, "simulate", no_simulation)
    assert generate_dataset(BP5, folder, **SIZES, seed=0, progress=True) == folder
    assert "reusing" in capsys.readouterr().out
    after = {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in folder.iterdir()}
    assert after == before


def test_a_finished_dataset_on_read_only_storage_is_reused(bp5_dir, tmp_path, monkeypatch, capsys):
    """Reuse wrote (removed a marker that was not there): EROFS on read-only storage."""
    folder = copy_dataset(bp5_dir, tmp_path)
    attempts = read_only_storage(monkeypatch, folder)
    assert generate_dataset(BP5, folder, **SIZES, seed=0, progress=True) == folder
    assert "reusing" in capsys.readouterr().out
    assert attempts == []
    # a marker a run killed after metadata.json left behind: removed where it can be ...
    monkeypatch.undo()
    (folder / MARKER).write_text("{}")
    assert generate_dataset(BP5, folder, **SIZES, seed=0, progress=False) == folder
    assert not (folder / MARKER).exists()
    # ... and kept, harmlessly, where it cannot
    (folder / MARKER).write_text("{}")
    attempts = read_only_storage(monkeypatch, folder)
    assert generate_dataset(BP5, folder, **SIZES, seed=0, progress=False) == folder
    assert (folder / MARKER).exists() and len(attempts) == 1
    # other arguments are still refused, with the usual message
    with pytest.raises(ValueError, match="different arguments"):
        generate_dataset(BP5, folder, n_train=7, n_val=3, n_test=3)


def test_different_arguments_raise_and_keep_files(bp5_dir, tmp_path):
    folder = copy_dataset(bp5_dir, tmp_path)
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    with pytest.raises(ValueError, match="different arguments") as info:
        generate_dataset(BP5, folder, n_train=7, n_val=3, n_test=3, noise_std=0.1)
    msg = str(info.value)
    assert "n_train (6 there, 7 requested)" in msg and "noise_std" in msg and "seed" not in msg
    with pytest.raises(ValueError, match=r"config\.horizon \(0\.2 there, 0\.5 requested\)"):
        generate_dataset(short_config("BP5", 0.5), folder, **SIZES)
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before


def test_foreign_folder_is_refused(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="not empty and holds no dataset"):
        generate_dataset(BP5, tmp_path, **SIZES)
    with pytest.raises(ValueError, match="n_train must be an integer >= 1"):
        generate_dataset(BP5, tmp_path / "x", n_train=0)
    with pytest.raises(ValueError, match="unknown task"):
        generate_dataset("NoSuchTask", tmp_path / "x")
    assert not (tmp_path / "x").exists()


def test_datasets_made_before_a_config_key_existed_are_reused():
    """A dataset recorded without a later config key matches a request with the value that
    stands for the old behaviour, and only that value."""
    from diffcontact.learning.data.write import _differences

    old = {"seed": 0, "config": {"name": "BP5", "dt": 0.01}}
    same = {"seed": 0, "config": {"name": "BP5", "dt": 0.01, "position_projection": 0}}
    assert _differences(old, same) == []
    other = {"seed": 0, "config": {"name": "BP5", "dt": 0.01, "position_projection": 10}}
    assert _differences(old, other) == [
        "config.position_projection (not recorded there, requested 10)"
    ]
    # only inside the config: a top-level argument of that name is not excused
    assert _differences({"seed": 0}, {"seed": 0, "position_projection": 0})


# distinct counts, so a simulation's batch size names its split
SPLIT_OF = {4: "train", 2: "val", 3: "test"}
COUNTS = {"n_train": 4, "n_val": 2, "n_test": 3}


def count_simulations(monkeypatch, fail: str | None = None) -> list[str]:
    """Record the split of every ``System.simulate`` call; interrupt the one of ``fail``."""
    calls: list[str] = []
    simulate = System.simulate

    def counted(self, z0, *args, **kwargs):
        calls.append(SPLIT_OF[z0.shape[0]])
        if calls[-1] == fail:
            raise KeyboardInterrupt  # Ctrl-C while this split is simulated
        return simulate(self, z0, *args, **kwargs)

    monkeypatch.setattr(System, "simulate", counted)
    return calls


def interrupted_run(folder, monkeypatch) -> None:
    """A run of COUNTS stopped while simulating the test split."""
    calls = count_simulations(monkeypatch, fail="test")
    with pytest.raises(KeyboardInterrupt):
        generate_dataset(BP5, folder, **COUNTS, progress=False)
    assert calls == ["train", "val", "test"]
    monkeypatch.undo()
    names = sorted(p.name for p in folder.iterdir())
    assert names == [MARKER, "train.npz", "val.npz"]  # finished splits kept, no metadata


def assert_same_dataset(folder, reference) -> None:
    """Bitwise the same split files and arrays; the same checksums in the metadata."""
    for name in ("train", "val", "test"):
        assert (folder / f"{name}.npz").read_bytes() == (reference / f"{name}.npz").read_bytes()
    ours, theirs = load_dataset(folder), load_dataset(reference)
    assert ours.metadata["files"] == theirs.metadata["files"]
    assert ours.metadata["stats"] == theirs.metadata["stats"]
    for name in ("train", "val", "test"):
        a, b = ours.split(name), theirs.split(name)
        for key in ("traj", "chunks", "chunk_start", "chunk_has_contact", "contact"):
            assert torch.equal(getattr(a, key), getattr(b, key)), (name, key)
    assert not (folder / MARKER).exists()


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    return generate_dataset(BP5, tmp_path_factory.mktemp("ref") / "ds", **COUNTS, progress=False)


def test_an_interrupted_run_keeps_and_reuses_its_finished_splits(
    uninterrupted, tmp_path, monkeypatch, capsys
):
    folder = tmp_path / "ds"
    interrupted_run(folder, monkeypatch)
    kept = {n: (folder / f"{n}.npz").stat().st_ino for n in ("train", "val")}
    calls = count_simulations(monkeypatch)
    assert generate_dataset(BP5, folder, **COUNTS, progress=True) == folder
    assert calls == ["test"]  # train and val were not simulated again
    out = capsys.readouterr().out
    assert f"finishing the interrupted dataset in {folder}" in out
    assert "reusing the train split of the interrupted run (4 trajectories)" in out
    assert "reusing the val split of the interrupted run (2 trajectories)" in out
    # the reused files are not written again (an atomic write would give a new inode)
    assert kept == {n: (folder / f"{n}.npz").stat().st_ino for n in ("train", "val")}
    assert_same_dataset(folder, uninterrupted)


def test_a_leftover_split_that_is_not_complete_is_simulated_again(
    uninterrupted, tmp_path, monkeypatch, capsys
):
    folder = tmp_path / "ds"
    interrupted_run(folder, monkeypatch)
    train = (folder / "train.npz").read_bytes()
    (folder / "train.npz").write_bytes(train[: len(train) // 2])  # truncated
    (folder / "val.npz").write_bytes(train)  # readable, but 4 trajectories, not 2
    calls = count_simulations(monkeypatch)
    assert generate_dataset(BP5, folder, **COUNTS, progress=True) == folder
    assert calls == ["train", "val", "test"]
    out = capsys.readouterr().out
    assert "reusing the" not in out
    assert "train.npz of the interrupted run is not a complete train split" in out
    assert "val.npz of the interrupted run is not a complete val split (traj of shape" in out
    assert "simulating the val split again" in out
    assert_same_dataset(folder, uninterrupted)


def test_a_run_interrupted_before_its_metadata_simulates_nothing_again(
    uninterrupted, tmp_path, monkeypatch
):
    """Only an interrupted run's splits are reused: an interruption after the last split
    (before metadata.json) simulates nothing on the re-run, and writes no split again."""
    folder = tmp_path / "ds"
    folder.mkdir()
    for name in ("train", "val", "test"):
        (folder / f"{name}.npz").write_bytes((uninterrupted / f"{name}.npz").read_bytes())
    arguments = json.loads((uninterrupted / METADATA).read_text())["arguments"]
    (folder / MARKER).write_text(json.dumps({"arguments": arguments}))
    inodes = {p.name: p.stat().st_ino for p in folder.glob("*.npz")}
    calls = count_simulations(monkeypatch)
    assert generate_dataset(BP5, folder, **COUNTS, progress=False) == folder
    assert calls == []
    assert inodes == {p.name: p.stat().st_ino for p in folder.glob("*.npz")}
    assert_same_dataset(folder, uninterrupted)
