"""All the data: every window of every trajectory as a chunk (``stride``), on simulated and
recorded data; warnings when the contact fraction cannot be met."""

from __future__ import annotations

import argparse
import json
import logging

import numpy as np
import pytest
import torch

from diffcontact.learning.data.arrays import dataset_from_arrays
from diffcontact.learning.data.chunks import window_chunks
from diffcontact.learning.data.cli import register_cli
from diffcontact.learning.data.format import ARRAYS, load_dataset
from diffcontact.learning.data.generate import generate_dataset

from .support import BP5, L, window_contact


def test_window_chunks_lists_every_window_that_starts_out_of_contact():
    rng = np.random.default_rng(0)
    contact = rng.random((4, 17)) < 0.3
    for stride in (1, 2, 5):
        owner, start, has = window_chunks(contact, L, stride)
        want = [
            (n, s, bool(contact[n, s : s + L].any()))
            for n in range(4)
            for s in range(0, 17 - L + 1, stride)
            if not contact[n, s]
        ]
        got = list(zip(owner.tolist(), start.tolist(), has.tolist(), strict=True))
        assert got == want
    with pytest.raises(ValueError, match="stride must be an integer >= 1"):
        window_chunks(contact, L, 0)
    with pytest.raises(ValueError, match="fewer than chunk_length"):
        window_chunks(contact[:, :3], L)


def test_generated_windows(tmp_path):
    out = generate_dataset(BP5, tmp_path / "w", n_train=4, n_val=1, n_test=1, stride=3,
                           progress=False)  # fmt: skip
    ds = load_dataset(out)
    assert ds.stride == 3 and ds.metadata["arguments"]["stride"] == 3
    split = ds.split("train")
    T = ds.n_states
    assert split.chunks.shape[0] == int((~split.contact[:, 0 : T - L + 1 : 3]).sum()) > 4
    assert (split.chunk_start % 3 == 0).all()
    idx = split.chunk_start[:, None] + torch.arange(L)
    assert torch.equal(split.chunks, split.traj[split.chunk_traj[:, None], idx])
    window = window_contact(split.contact, split.chunk_start, split.chunk_traj)
    assert not window[:, 0].any() and torch.equal(split.chunk_has_contact, window.any(1))
    assert ds.metadata["stats"]["train"]["n_chunks"] == len(split.chunks)
    # the same arguments reuse it; another stride is refused
    generate_dataset(BP5, out, n_train=4, n_val=1, n_test=1, stride=3, progress=False)
    with pytest.raises(ValueError, match=r"stride \(3 there, 2 requested\)"):
        generate_dataset(BP5, out, n_train=4, n_val=1, n_test=1, stride=2, progress=False)
    # noise is drawn per chunk (overlapping windows: independent draws)
    folder = generate_dataset(
        BP5, tmp_path / "n", n_train=4, n_val=1, n_test=1, stride=1, noise_std=0.01,
        progress=False,
    )  # fmt: skip
    noisy = load_dataset(folder).split("train")
    clean = noisy.traj[noisy.chunk_traj[:, None], noisy.chunk_start[:, None] + torch.arange(L)]
    diff = noisy.chunks - clean
    assert 0.005 < float(diff.std()) < 0.02


def test_default_generated_datasets_keep_one_chunk_per_trajectory(bp5_dir):
    ds = load_dataset(bp5_dir)
    assert ds.stride is None and "stride" not in ds.metadata["arguments"]
    with np.load(bp5_dir / "train.npz") as npz:
        assert list(npz.files) == list(ARRAYS)  # no chunk_traj: the files of before
    split = ds.split("train")
    assert torch.equal(split.chunk_traj, torch.arange(len(split)))


def test_recorded_data_uses_every_window_by_default(recorded, tmp_path):
    out = dataset_from_arrays(recorded, BP5, tmp_path / "all", seed=2, progress=False)
    ds = load_dataset(out)
    N = recorded.shape[0]
    T = recorded.shape[1]
    total = sum(len(ds.split(s).chunks) for s in ("train", "val", "test"))
    flags = np.concatenate([ds.split(s).contact.numpy() for s in ("train", "val", "test")])
    assert total == int((~flags[:, : T - L + 1]).sum()) > 10 * N
    one = load_dataset(
        dataset_from_arrays(recorded, BP5, tmp_path / "one", seed=2, stride=None, progress=False)
    )
    assert one.stride is None and len(one.split("train").chunks) == one.counts["train"]


def test_a_contact_fraction_that_cannot_be_met_is_warned(recorded, tmp_path, caplog):
    # 6 states per trajectory: two windows each, most with a contact
    short = recorded[:, :6]
    with caplog.at_level(logging.WARNING):
        out = dataset_from_arrays(short, BP5, tmp_path / "a", stride=None, progress=False)
    train = load_dataset(out).split("train")
    n_c = int(train.chunk_has_contact.sum())
    assert n_c > 5  # round(0.5 * 10) asked for
    assert (
        f"train: --contact-fraction 0.5 cannot be met: {n_c} of 10 chunks contain a contact "
        "(5 asked for; the trajectories allow no fewer)"
    ) in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        generate_dataset(BP5, tmp_path / "b", n_train=6, n_val=1, n_test=1, contact_fraction=0.5,
                         seed=3, progress=False)  # fmt: skip
    assert "train: --contact-fraction" not in caplog.text  # met exactly (3 of 6)


def _cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="diffcontact")
    register_cli(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_stride(recorded, tmp_path, capsys):
    path = tmp_path / "rec.npz"
    np.savez(path, traj=recorded, dt=0.01)
    cfg = tmp_path / "bp5.json"
    cfg.write_text(json.dumps(BP5))
    base = ["generate", "--from-arrays", str(path), "--config", str(cfg), "--quiet"]
    assert _cli([*base, "--out", str(tmp_path / "a"), "--stride", "none"]) == 0
    assert load_dataset(tmp_path / "a").stride is None
    assert _cli([*base, "--out", str(tmp_path / "b"), "--stride", "4"]) == 0
    assert load_dataset(tmp_path / "b").stride == 4
    assert _cli(["generate", "BP5", "--out", str(tmp_path / "c"), "--stride", "0",
                 "--n-train", "1", "--n-val", "0", "--n-test", "0", "--quiet"]) == 0  # fmt: skip
    assert load_dataset(tmp_path / "c").stride is None
    with pytest.raises(SystemExit):
        _cli([*base, "--out", str(tmp_path / "d"), "--stride", "x"])
    assert "--stride" in capsys.readouterr().err
