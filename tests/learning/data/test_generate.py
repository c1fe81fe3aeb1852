"""Simulated datasets: independent splits, reuse with the same arguments, refusals."""

from __future__ import annotations

import pytest

from diffcontact.learning.data.format import MARKER, load_dataset
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
