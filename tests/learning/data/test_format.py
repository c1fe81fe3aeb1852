"""The dataset format and its reader: files, shapes, contact flags, checksums."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

from diffcontact.learning.data import format as format_mod
from diffcontact.learning.data.format import ARRAYS, DatasetError, load_dataset
from diffcontact.learning.data.generate import generate_dataset
from diffcontact.systems import System

from .support import BP5, SIZES, L, copy_dataset, sha256, window_contact


@pytest.mark.parametrize("which", ["bp5", "cp3"])
def test_format_and_shapes(which, bp5_dir, cp3_noisy_dir):
    folder = bp5_dir if which == "bp5" else cp3_noisy_dir
    assert sorted(p.name for p in folder.iterdir()) == [
        "metadata.json",
        "test.npz",
        "train.npz",
        "val.npz",
    ]
    meta = json.loads((folder / "metadata.json").read_text())
    for key in (
        "format_version", "config", "task", "seed", "seeds", "dt", "n_train", "n_val",
        "n_test", "noise_std", "chunk_length", "diffcontact_version", "created", "files",
        "arguments",
    ):  # fmt: skip
        assert key in meta, key
    assert meta["seeds"] == {"train": 0, "val": 1, "test": 2}
    assert meta["chunk_length"] == L and meta["dt"] == 0.01
    assert set(meta["files"]) == {"train.npz", "val.npz", "test.npz"}
    for name, digest in meta["files"].items():
        assert sha256(folder / name) == digest

    ds = load_dataset(folder)
    system = ds.system
    assert isinstance(system, System) and ds.config.horizon == meta["config"]["horizon"]
    T = round(ds.config.horizon / ds.config.dt)
    assert ds.n_states == T
    P, d = system.n_points, system.dim
    for name in ("train", "val", "test"):
        with np.load(folder / f"{name}.npz") as npz:
            assert list(npz.files) == list(ARRAYS)
            N = meta[f"n_{name}"]
            assert npz["traj"].shape == (N, T, 2, P, d) and npz["traj"].dtype == np.float64
            assert npz["chunks"].shape == (N, L, 2, P, d) and npz["chunks"].dtype == np.float64
            assert npz["chunk_start"].shape == (N,) and npz["chunk_start"].dtype == np.int64
            assert npz["chunk_has_contact"].dtype == bool and npz["contact"].shape == (N, T)
            assert npz["contact"].dtype == bool
        split = ds.split(name)
        assert len(split) == N
        # contact means a negative gap at the state's positions
        gaps = system.gaps(split.traj[..., 0, :, :])
        assert torch.equal(split.contact, (gaps < 0).any(-1))
        assert not split.contact[:, 0].any()  # initial states are sampled out of contact
        window = window_contact(split.contact, split.chunk_start)
        assert not window[:, 0].any()  # chunks start out of contact
        assert torch.equal(split.chunk_has_contact, window.any(1))
        if ds.noise_std == 0:
            idx = split.chunk_start[:, None] + torch.arange(L)
            expected = split.traj[torch.arange(N)[:, None], idx]
            assert torch.equal(split.chunks, expected)
    f32 = ds.split("train", dtype=torch.float32)
    assert f32.chunks.dtype == torch.float32 and f32.chunk_start.dtype == torch.int64
    assert ds.split("train", dtype="float32").chunks.dtype == torch.float32
    # an integer dtype had truncated the chunks, a string other than these a torch TypeError
    for bad in (torch.int64, torch.bfloat16, torch.complex64, "bogus"):
        with pytest.raises(ValueError, match=r"dtype must be torch\.float32 or torch\.float64"):
            ds.split("train", dtype=bad)


def test_checksum_corruption_and_missing_files(bp5_dir, tmp_path):
    folder = copy_dataset(bp5_dir, tmp_path)
    ds = load_dataset(folder)  # valid now
    raw = bytearray((folder / "val.npz").read_bytes())
    raw[-100] ^= 0xFF
    (folder / "val.npz").write_bytes(bytes(raw))
    with pytest.raises(DatasetError, match=r"val\.npz does not match its sha256"):
        load_dataset(folder)
    with pytest.raises(DatasetError, match=r"val\.npz does not match"):
        ds.split("val")  # the bytes read are checked too
    with pytest.raises(DatasetError, match=r"val\.npz does not match"):
        generate_dataset(BP5, folder, **SIZES, progress=False)  # no silent reuse
    (folder / "test.npz").unlink()
    with pytest.raises(DatasetError, match=r"test\.npz is missing"):
        load_dataset(folder)
    (folder / "metadata.json").unlink()
    with pytest.raises(DatasetError, match=r"no metadata\.json"):
        load_dataset(folder)
    with pytest.raises(DatasetError, match="does not exist"):
        load_dataset(tmp_path / "nowhere")
    # a file is not "a folder that does not exist"
    (tmp_path / "rec.npz").write_bytes(b"")
    hint = r"`diffcontact generate --from-arrays .*rec\.npz --out DATASET_DIR`"
    with pytest.raises(DatasetError, match=r"rec\.npz is a file, not a dataset folder: .*" + hint):
        load_dataset(tmp_path / "rec.npz")
    (tmp_path / "notes.txt").write_text("")
    with pytest.raises(DatasetError, match=r"notes\.txt is a file, not a dataset folder"):
        load_dataset(tmp_path / "notes.txt")


def test_a_split_is_hashed_once_unless_its_file_changed(bp5_dir, tmp_path, monkeypatch):
    """load_dataset hashes every file; reading a split of an unchanged file does not again."""
    calls = []
    real = format_mod.hashlib.sha256

    def counting(*args):
        calls.append(args)
        return real(*args)

    monkeypatch.setattr(format_mod.hashlib, "sha256", counting)
    fresh = copy_dataset(bp5_dir, tmp_path / "fresh")
    ds = load_dataset(fresh)
    assert len(calls) == 4  # metadata.json's own checksum and the three files
    ds.split("train")  # just written: within the timestamp granularity, hashed again
    assert len(calls) == 5

    monkeypatch.setattr(format_mod, "_RECENT_NS", -(10**15))  # as if written long ago
    folder = copy_dataset(bp5_dir, tmp_path / "old")
    calls.clear()
    ds = load_dataset(folder)
    ds.split("train")
    ds.split("val")
    assert len(calls) == 4  # verified by load_dataset, unchanged since
    raw = bytearray((folder / "val.npz").read_bytes())
    raw[-100] ^= 0xFF
    (tmp_path / "val.npz").write_bytes(bytes(raw))
    os.replace(tmp_path / "val.npz", folder / "val.npz")  # another file (inode) now
    with pytest.raises(DatasetError, match=r"val\.npz does not match"):
        ds.split("val")


def test_mismatch_sees_other_link_lengths_and_pivots(tmp_path):
    """evaluate and refit scored a CP3 model on data of other link lengths or another
    pivot: the contact gaps agree there, the equality constraints do not."""
    from diffcontact.learning import create_model
    from diffcontact.systems import load_config

    config = load_config("CP3").model_dump(mode="json")
    model = create_model("CM-CD-CLNN", "CP3", hidden=[4])
    changes = {
        "same": {},
        "links": {"link_lengths": [0.3, 0.45, 0.35]},
        "pivot": {"pivot": [0.1, 0.0]},
    }
    for name, change in changes.items():
        folder = generate_dataset({**config, **change}, tmp_path / name, n_train=2, n_val=1,
                                  n_test=1, progress=False)  # fmt: skip
        why = load_dataset(folder).mismatch(model)
        if name == "same":
            assert why is None
        else:
            assert why is not None and "equality constraints differ" in why
