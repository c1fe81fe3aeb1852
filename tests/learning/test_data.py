"""Datasets: generation, chunking, noise, reuse, checksums, recorded data and the CLI."""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from diffcontact.io import atomic_path
from diffcontact.learning import data as data_mod
from diffcontact.learning.data import (
    ARRAYS,
    DatasetError,
    dataset_from_arrays,
    generate_dataset,
    load_dataset,
    register_cli,
    select_chunks,
)
from diffcontact.systems import System, load_config

SIZES = {"n_train": 6, "n_val": 3, "n_test": 3}
L = 5


def short_config(task: str, horizon: float) -> dict:
    """A built-in task with a shorter horizon (fewer states: faster tests)."""
    return load_config(task, horizon=horizon).model_dump(mode="json")


BP5 = short_config("BP5", 0.2)  # 20 states
CP3 = short_config("CP3", 0.3)  # 30 states


@pytest.fixture(scope="module")
def bp5_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("data") / "bp5"
    return generate_dataset(BP5, out, **SIZES, seed=0, progress=False)


@pytest.fixture(scope="module")
def cp3_noisy_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("data") / "cp3"
    return generate_dataset(CP3, out, n_train=8, n_val=1, n_test=1, noise_std=0.05, progress=False)


def copy_dataset(src: Path, tmp_path: Path) -> Path:
    dst = tmp_path / src.name
    shutil.copytree(src, dst)
    return dst


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def window_contact(contact: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
    idx = start[:, None] + torch.arange(L)
    return contact.gather(1, idx)


# ------------------------------------------------------------------ chunk choice


def test_select_chunks_hits_the_target_share_and_starts_out_of_contact():
    rng = np.random.default_rng(1)
    N, T = 2000, 30
    contact = rng.random((N, T)) < 0.15
    start, has = select_chunks(contact, L, 0.5, rng=3)
    assert start.dtype == np.int64 and has.dtype == bool
    assert ((start >= 0) & (start <= T - L)).all()
    assert not contact[np.arange(N), start].any()
    windows = np.stack([contact[n, s : s + L] for n, s in enumerate(start)])
    assert (windows.any(1) == has).all()
    assert has.sum() == N // 2
    again = select_chunks(contact, L, 0.5, rng=3)
    assert (again[0] == start).all()  # seeded
    _, has_03 = select_chunks(contact, L, 0.3, rng=3)
    assert has_03.sum() == round(0.3 * N)


def test_select_chunks_forced_kinds_and_unchunkable():
    contact = np.zeros((3, 10), dtype=bool)
    contact[0, 1:] = True  # only chunk: start 0, contains a contact
    contact[2, 4] = True  # both kinds possible
    start, has = select_chunks(contact, L, 0.0, rng=0)
    assert start[0] == 0 and has[0]  # forced even with contact_fraction 0
    assert not has[1] and not has[2]  # trajectory 1 has no contact at all
    _, has = select_chunks(contact, L, 1.0, rng=0)
    assert has.tolist() == [True, False, True]
    contact[1, :6] = True  # every possible start (0..5) in contact
    with pytest.raises(ValueError, match=r"1 of 3 trajectories \(1\).*states 0\.\.5"):
        select_chunks(contact, L, 0.5)
    with pytest.raises(ValueError, match="fewer than chunk_length"):
        select_chunks(np.zeros((2, 4), dtype=bool), L)


# ------------------------------------------------------------------ format


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


def test_contact_share_near_target(bp5_dir):
    ds = load_dataset(bp5_dir)
    for name in ("train", "val", "test"):
        split = ds.split(name)
        N = len(split)
        contact = split.contact.numpy()
        S = contact.shape[1] - L + 1
        windows = np.lib.stride_tricks.sliding_window_view(contact, L, axis=1).any(-1)
        ok = ~contact[:, :S]
        can_c, can_f = (ok & windows).any(1), (ok & ~windows).any(1)
        # the target round(N / 2), as far as the trajectories allow
        target = int(np.clip(round(0.5 * N + 1e-9), (can_c & ~can_f).sum(), can_c.sum()))
        assert int(split.chunk_has_contact.sum()) == target
        assert abs(target - 0.5 * N) <= 1, "BP5 should reach the target"


def test_val_and_test_are_independent_of_train(bp5_dir):
    ds = load_dataset(bp5_dir)
    z0 = {name: ds.split(name).traj[:, 0] for name in ("train", "val", "test")}
    for a, b in (("train", "val"), ("train", "test"), ("val", "test")):
        dist = (z0[a][:, None] - z0[b][None]).flatten(2).abs().amax(-1)
        assert bool((dist > 1e-6).all()), (a, b)


# ------------------------------------------------------------------ reuse and errors


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


# ------------------------------------------------------------------ noise


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
    q_noisy, qd_noisy = data_mod._chain_angles(split.chunks, pivot)
    q_clean, qd_clean = data_mod._chain_angles(clean, pivot)
    dq = torch.remainder(q_noisy - q_clean + torch.pi, 2 * torch.pi) - torch.pi
    for noise in (dq, qd_noisy - qd_clean):
        assert 0.035 < float(noise.std()) < 0.065


# ------------------------------------------------------------------ recorded data


def all_trajectories(folder: Path) -> np.ndarray:
    ds = load_dataset(folder)
    return torch.cat([ds.split(s).traj for s in ("train", "val", "test")]).numpy()


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
        window = window_contact(split.contact, split.chunk_start)
        assert not window[:, 0].any()
        idx = split.chunk_start[:, None] + torch.arange(L)
        assert torch.equal(split.chunks, split.traj[torch.arange(len(split))[:, None], idx])
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


@pytest.fixture(scope="module")
def recorded(bp5_dir) -> np.ndarray:
    return all_trajectories(bp5_dir)


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
    fails(recorded, r"val_fraction \+ test_fraction must be below 1", val_fraction=0.5,
          test_fraction=0.5)  # fmt: skip
    fails(recorded, r"val_fraction must lie in \[0, 1\)", val_fraction=1.0)
    fails(np.array([["a"]]), "numeric array")
    overlapping = recorded.copy()
    overlapping[4, :, 0, 0] = (-0.5, 0.5)  # body 0 beyond the left wall at every state
    fails(
        overlapping,
        r"1 of 12 trajectories \(4\) are in contact .* at every state that could start a "
        r"chunk \(states 0\.\.15\).*body 0 penetrates wall 0",
    )


def test_interrupted_write_leaves_no_partial_file(recorded, tmp_path, monkeypatch):
    out = tmp_path / "rec"
    real = data_mod.atomic_save_npz
    calls = []

    def crash_on_second(path, **arrays):
        calls.append(Path(path).name)
        if len(calls) == 2:
            with atomic_path(path) as tmp:
                tmp.write_bytes(b"half")
                raise RuntimeError("simulated crash")
        return real(path, **arrays)

    monkeypatch.setattr(data_mod, "atomic_save_npz", crash_on_second)
    with pytest.raises(RuntimeError, match="simulated crash"):
        dataset_from_arrays(recorded, BP5, out, progress=False)
    names = sorted(p.name for p in out.iterdir())
    assert names == [".generating.json", "train.npz"]  # no val.npz, no temporary, no metadata
    with pytest.raises(DatasetError, match="interrupted run"):
        load_dataset(out)
    with pytest.raises(ValueError, match=r"unfinished dataset .* seed \(0 there, 1 requested\)"):
        dataset_from_arrays(recorded, BP5, out, seed=1)
    monkeypatch.setattr(data_mod, "atomic_save_npz", real)
    dataset_from_arrays(recorded, BP5, out, progress=False)  # same arguments: finishes
    assert sorted(p.name for p in out.iterdir()) == [
        "metadata.json",
        "test.npz",
        "train.npz",
        "val.npz",
    ]
    load_dataset(out)


# ------------------------------------------------------------------ CLI


def cli(capsys, *argv: str) -> tuple[int, str, str]:
    parser = argparse.ArgumentParser(prog="diffcontact")
    register_cli(parser.add_subparsers(dest="command"))
    args = parser.parse_args(list(argv))
    code = args.func(args)
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code: int, err: str, *needles: str) -> None:
    assert code == 2
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("diffcontact generate: error: "), err
    for needle in needles:
        assert needle in lines[0], lines[0]


def test_cli_bad_input_exits_2(recorded, tmp_path, capsys):
    out = str(tmp_path / "out")
    code, _, err = cli(capsys, "generate", "NoSuchTask", "--out", out)
    assert_one_line_error(code, err, "unknown task 'NoSuchTask'")
    code, _, err = cli(capsys, "generate", "--out", out)
    assert_one_line_error(code, err, "give TASK_OR_CONFIG")
    code, _, err = cli(capsys, "generate", "--from-arrays", str(tmp_path / "no.npz"), "--out", out)
    assert_one_line_error(code, err, "does not exist")
    np.savez(tmp_path / "wrong.npz", x=recorded)
    code, _, err = cli(
        capsys, "generate", "--from-arrays", str(tmp_path / "wrong.npz"), "--config", "BP5",
        "--out", out,
    )  # fmt: skip
    assert_one_line_error(code, err, "no array named 'traj'", "found: x")
    np.savez(tmp_path / "rec.npz", traj=recorded)
    code, _, err = cli(
        capsys, "generate", "--from-arrays", str(tmp_path / "rec.npz"), "--config", "CP3",
        "--out", out,
    )  # fmt: skip
    assert_one_line_error(code, err, "(N, T, 2, 3, 2)", "got (12, 20, 2, 5, 2)")
    code, _, err = cli(
        capsys, "generate", "--from-arrays", str(tmp_path / "rec.npz"), "--config", "BP5",
        "--n-train", "5", "--out", out,
    )  # fmt: skip
    assert_one_line_error(code, err, "--n-train does not apply with --from-arrays")
    code, _, err = cli(capsys, "generate", "BP5", "--dt", "0.01", "--out", out)
    assert_one_line_error(code, err, "--dt applies only with --from-arrays")
    assert not Path(out).exists()


def test_cli_from_arrays_summary_and_reuse(recorded, tmp_path, capsys):
    config = tmp_path / "bp5.yaml"
    config.write_text(json.dumps(BP5))  # JSON is YAML
    np.savez(tmp_path / "rec.npz", traj=recorded, dt=0.01)
    out = tmp_path / "ds"
    argv = ["generate", "--from-arrays", str(tmp_path / "rec.npz"), "--config", str(config)]
    code, stdout, err = cli(capsys, *argv, "--out", str(out))
    assert code == 0, err
    assert "BP5 dataset (arrays) written" in stdout
    assert "train: 10 trajectories x 20 states" in stdout and "% of chunks" in stdout
    assert str(out / "train.npz") in stdout
    code, stdout, _ = cli(capsys, *argv, "--out", str(out))
    assert code == 0 and "reused" in stdout
    code, _, err = cli(capsys, *argv, "--seed", "3", "--out", str(out))
    assert_one_line_error(code, err, "different arguments", "seed (0 there, 3 requested)")


def test_cli_simulates_a_tiny_dataset(tmp_path, capsys):
    config = tmp_path / "tiny.json"
    config.write_text(json.dumps(short_config("BP5", 0.1)))  # 10 states
    out = tmp_path / "ds"
    code, stdout, err = cli(
        capsys, "generate", str(config), "--out", str(out), "--n-train", "2", "--n-val", "1",
        "--n-test", "1", "--seed", "2", "--quiet",
    )  # fmt: skip
    assert code == 0, err
    assert stdout == ""
    ds = load_dataset(out)
    assert ds.counts == {"train": 2, "val": 1, "test": 1}
    assert ds.metadata["seeds"] == {"train": 2000, "val": 2001, "test": 2002}
