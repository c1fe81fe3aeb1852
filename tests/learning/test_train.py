"""Training: run directory, loss decrease, resume, skipped steps, CLI errors, learning mu/e_P."""

import argparse
import csv
import hashlib
import itertools
import json
import logging

import lightning.pytorch as pl
import numpy as np
import pytest
import torch

import diffcontact as dc
from diffcontact.contact import ConeQPError
from diffcontact.learning import train as train_mod
from diffcontact.learning.model import LearnedModel, load_model
from diffcontact.learning.train import (
    ChunkDataModule,
    RolloutModule,
    TrainingInputError,
    register_cli,
    rollout_loss,
    train,
)

SMALL = {"hidden": (16, 16), "progress": False}


def write_dataset(folder, config, n=(8, 4, 4), steps=15, chunk=5, seed=0, nan_train=()):
    """A dataset folder in the format of docs/conventions.md, written with numpy only.

    From each trajectory one chunk whose first state is out of contact; every
    other trajectory takes a chunk with a contact when it has one.
    ``nan_train``: train chunks whose states 2.. are set to NaN.
    """
    folder.mkdir(parents=True, exist_ok=True)
    system = dc.load_system(config)
    files = {}
    for k, (split, count) in enumerate(zip(("train", "val", "test"), n, strict=True)):
        traj = system.simulate(system.sample_initial_conditions(count, seed=seed + k), steps)
        with torch.no_grad():
            contact = (system.gaps(traj[..., 0, :, :]) < 0).any(-1).numpy()
        rng = np.random.default_rng(seed + k)
        starts, has = [], []
        for i in range(count):
            ok = [s for s in range(steps + 2 - chunk) if not contact[i, s]]
            with_contact = [s for s in ok if contact[i, s : s + chunk].any()]
            s = int(rng.choice(with_contact if with_contact and i % 2 == 0 else ok))
            starts.append(s)
            has.append(bool(contact[i, s : s + chunk].any()))
        t = traj.numpy()
        chunks = np.stack([t[i, s : s + chunk] for i, s in enumerate(starts)])
        if split == "train":
            for i in nan_train:
                chunks[i, 2:] = np.nan
        path = folder / f"{split}.npz"
        np.savez(
            path,
            traj=t,
            chunks=chunks,
            chunk_start=np.array(starts, dtype=np.int64),
            chunk_has_contact=np.array(has),
            contact=contact,
        )
        files[path.name] = hashlib.sha256(path.read_bytes()).hexdigest()
    meta = {
        "format_version": 1,
        "config": system.config.model_dump(mode="json"),
        "task": system.name,
        "seed": seed,
        "seeds": {"train": seed, "val": seed + 1, "test": seed + 2},
        "dt": system.dt,
        "n_train": n[0],
        "n_val": n[1],
        "n_test": n[2],
        "n_states": steps + 1,
        "noise_std": 0.0,
        "chunk_length": chunk,
        "diffcontact_version": dc.__version__,
        "created": "test",
        "files": files,
        "arguments": {},
    }
    (folder / "metadata.json").write_text(json.dumps(meta))
    return folder


@pytest.fixture(scope="module")
def bp5_data(tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("bp5"), "BP5")


def _state(run_dir):
    return torch.load(run_dir / "model.pt", weights_only=True)["state_dict"]


def test_train_writes_the_run_directory(bp5_data, tmp_path):
    out = tmp_path / "run"
    # max_time: stop after the first epoch that ends after 1e-9 minutes, i.e. after epoch 0
    model = train(bp5_data, out, epochs=3, batch_size=4, max_time=1e-9, **SMALL)
    run = json.loads((out / "run.json").read_text())
    assert run["model"] == "CM-CD-CLNN" and run["data_dir"] == str(bp5_data.resolve())
    assert run["dtype"] == "float64" and run["heterogeneous"] is True
    assert (out / "checkpoints" / "last.ckpt").is_file()
    assert (out / "checkpoints" / "epoch0000.ckpt").is_file()
    learned = json.loads((out / "learned.json").read_text())
    assert learned["finished"] and learned["epoch"] == 0
    assert not (out / "checkpoints" / "epoch0001.ckpt").exists()
    assert learned["learned"] == model.learned_parameters()
    with open(out / "logs" / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    columns = set(rows[0])
    assert {"train/loss_epoch", "val/loss", "param/mass_ratio_4", "param/mu_29"} <= columns
    assert {"param/cor_0", "train/loss_step", "train/skipped"} <= columns
    val = [float(r["val/loss"]) for r in rows if r["val/loss"]]
    assert len(val) == 1 and np.isfinite(val[0])
    back = load_model(out)
    assert back.learned_parameters() == model.learned_parameters()
    from_ckpt = load_model(out / "checkpoints" / "last.ckpt")
    assert from_ckpt.learned_parameters() == model.learned_parameters()


def test_a_few_steps_reduce_the_loss(bp5_data):
    chunks = train_mod.read_training_data(bp5_data)[1][:4]
    torch.manual_seed(0)
    model = LearnedModel("BP5", hidden=(16, 16)).double()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2, weight_decay=1e-4)
    losses = []
    for _ in range(6):
        opt.zero_grad()
        loss = rollout_loss(model, chunks)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert all(b < a for a, b in itertools.pairwise(losses)), losses
    assert losses[-1] < 0.97 * losses[0], losses


class _CrashAt(pl.Callback):
    """Raise in the middle of an epoch (an interruption)."""

    def __init__(self, epoch, batch):
        self.epoch, self.batch = epoch, batch

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.current_epoch == self.epoch and batch_idx == self.batch:
            raise RuntimeError("simulated crash")


def test_resume_gives_the_uninterrupted_result(bp5_data, tmp_path):
    opts = dict(batch_size=4, seed=3, **SMALL)
    train(bp5_data, tmp_path / "a", epochs=2, keep_checkpoints=1, **opts)
    kept = sorted(p.name for p in (tmp_path / "a" / "checkpoints").iterdir())
    assert kept == ["epoch0001.ckpt", "last.ckpt"]
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(bp5_data, tmp_path / "b", epochs=2, callbacks=[_CrashAt(1, 1)], **opts)
    assert not (tmp_path / "b" / "model.pt").exists()
    assert (tmp_path / "b" / "checkpoints" / "epoch0000.ckpt").is_file()
    train(bp5_data, tmp_path / "b", epochs=2, resume=True, **opts)
    a, b = _state(tmp_path / "a"), _state(tmp_path / "b")
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(b[k], a[k]), k
    with open(tmp_path / "b" / "logs" / "metrics.csv") as fh:
        epochs = [r["epoch"] for r in csv.DictReader(fh) if r["train/loss_epoch"]]
    assert epochs == ["0", "1"]  # continuous log, the interrupted epoch once


def test_nonfinite_and_failed_steps_are_skipped_and_reported(tmp_path, caplog, monkeypatch):
    data = write_dataset(tmp_path / "data", "BP5", n=(6, 2, 2), steps=10, nan_train=(0,))
    calls = {"n": 0}
    real_loss = train_mod.rollout_loss

    def flaky_loss(model, chunk):
        calls["n"] += 1
        if calls["n"] == 2:
            raise ConeQPError("1 of 1 problems did not converge (simulated)")
        loss = real_loss(model, chunk)
        if calls["n"] == 3:  # finite value, non-finite gradient
            s = model.log_mass_rel.sum()
            loss = loss + 0.0 * torch.sqrt(s - s.detach())
        return loss

    monkeypatch.setattr(train_mod, "rollout_loss", flaky_loss)
    with caplog.at_level(logging.WARNING, logger="diffcontact.learning.train"):
        model = train(data, tmp_path / "run", epochs=1, batch_size=1, **SMALL)
    learned = json.loads((tmp_path / "run" / "learned.json").read_text())
    assert learned["skipped_steps"] == {
        "nonfinite_loss": 1,
        "nonfinite_grad": 1,
        "solver_failure": 1,
        "gradient_spike": 0,
    }
    assert learned["global_step"] == 3  # 6 batches, 3 skipped
    assert all(torch.isfinite(p).all() for p in model.parameters())
    messages = [r.getMessage() for r in caplog.records if "skipped" in r.getMessage()]
    assert len(messages) == 1 and "skipped 3 step(s)" in messages[0]


def test_gradient_spikes_are_skipped_and_resume_keeps_the_history(bp5_data, tmp_path, monkeypatch):
    """A batch whose gradient is 1e6 times the usual is skipped, not fed to Adam."""
    calls = {"n": 0}
    real_loss = train_mod.rollout_loss

    def spiky_loss(model, chunk):
        calls["n"] += 1
        loss = real_loss(model, chunk)
        return loss * 1e6 if calls["n"] == 3 else loss  # the third training step

    monkeypatch.setattr(train_mod, "rollout_loss", spiky_loss)
    model = train(bp5_data, tmp_path / "run", epochs=2, batch_size=2, **SMALL)
    learned = json.loads((tmp_path / "run" / "learned.json").read_text())
    assert learned["skipped_steps_total"]["gradient_spike"] == 1
    assert sum(learned["skipped_steps_total"].values()) == 1
    assert learned["global_step"] == 7  # 8 batches, 1 skipped
    assert all(torch.isfinite(p).all() for p in model.parameters())
    ckpt = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", weights_only=False)
    history = ckpt["diffcontact"]["grad_norm_history"]
    assert len(history) == 2 and len(history[0]) == len(history[1]) == 7
    # the spike's norm was not recorded: every kept norm is within the factor of the median
    for h in history:
        assert max(h) <= train_mod.SPIKE_FACTOR * np.median(h)


def _run_cli(argv, capsys):
    parser = argparse.ArgumentParser(prog="diffcontact")
    register_cli(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    code = args.func(args)
    return code, capsys.readouterr().err


def test_cli_bad_input_gives_one_line_and_exit_2(bp5_data, tmp_path, capsys):
    out = str(tmp_path / "run")
    cases = [
        (["train", str(tmp_path / "missing"), "--out", out], "does not exist"),
        (["train", str(bp5_data), "--model", "XX-CD-CLNN", "--out", out], "unknown model"),
        (["train", str(bp5_data), "--resume", "--out", out], "cannot resume"),
        (["train", str(bp5_data), "--dtype", "float16", "--out", out], "dtype"),
    ]
    if not torch.cuda.is_available():
        cases.append((["train", str(bp5_data), "--device", "cuda", "--out", out], "CUDA"))
    for argv, text in cases:
        code, err = _run_cli(argv, capsys)
        assert code == 2, argv
        assert text in err and err.count("\n") == 1, err
    # an out dir holding a different run
    run = tmp_path / "other"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.ckpt").write_bytes(b"")
    (run / "run.json").write_text(json.dumps({"model": "CM-CD-CLNN", "lr": 0.5}))
    code, err = _run_cli(["train", str(bp5_data), "--resume", "--out", str(run)], capsys)
    assert code == 2 and "different run" in err and err.count("\n") == 1
    code, err = _run_cli(["train", str(bp5_data), "--out", str(run)], capsys)
    assert code == 2 and "already holds a run" in err
    with pytest.raises(TrainingInputError, match="epochs"):
        train(bp5_data, tmp_path / "x", epochs=0)
    with pytest.raises(TrainingInputError, match="strategy"):
        train(bp5_data, tmp_path / "x", epochs=1, strategy="nonsense", progress=False)
    assert not (tmp_path / "x").exists()  # nothing written before the checks pass


BALL = {
    "type": "bouncing_masses",
    "name": "ball",
    "masses": [1.0],
    "radii": [0.1],
    "walls": [[1, 0, 0], [0, 1, 0], [-1, 0, 1], [0, -1, 1]],
    "mu": 0.3,
    "cor": 0.6,
    "dt": 0.01,
    "horizon": 0.5,
    "initial_conditions": {"velocity_std": 2.0},
}


def _contact_chunks(system, n, length=5, seed=0):
    traj = system.simulate(system.sample_initial_conditions(n, seed=seed), 40)
    with torch.no_grad():
        contact = (system.gaps(traj[..., 0, :, :]) < 0).any(-1)
    out = []
    for i in range(n):
        for s in range(traj.shape[1] - length):
            if not contact[i, s] and contact[i, s + 1 : s + length].any():
                out.append(traj[i, s : s + length])
                break
    return torch.stack(out)


@pytest.mark.filterwarnings("ignore:.*LeafSpec")
def test_learning_recovers_mu_and_cor_of_a_bouncing_ball():
    """mu and e_P of a point mass bouncing in a box, from wall-contact chunks.

    The mass drops out of a single body's impulses and there is no potential,
    so only mu and e_P are learned (from 0.5 each). Tolerance 0.03 on both.
    """
    system = dc.load_system(BALL)
    train_chunks = _contact_chunks(system, 48, seed=0)
    val_chunks = _contact_chunks(system, 8, seed=1)
    pl.seed_everything(0, verbose=False)
    model = LearnedModel(BALL, hidden=(4,))
    model.potential = None
    model.log_mass_scale.requires_grad_(False)
    model.log_mass_rel.requires_grad_(False)
    module = RolloutModule(model=model, lr=0.04, weight_decay=0.0, dtype="float64")
    data = ChunkDataModule(train_chunks, val_chunks, batch_size=len(train_chunks), dtype="float64")
    trainer = pl.Trainer(
        max_epochs=40,
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        inference_mode=False,
        num_sanity_val_steps=0,
        check_val_every_n_epoch=40,
    )
    trainer.fit(module, datamodule=data)
    p = model.learned_parameters()
    assert p["mu"][0] == pytest.approx(0.3, abs=0.03), p
    assert p["cor"][0] == pytest.approx(0.6, abs=0.03), p
    assert module.last_epoch_summary["val_loss"] < 5e-3


def test_physical_parameters_get_their_own_learning_rate_and_no_weight_decay():
    model = LearnedModel("BD5", model="CMr-CD-CLNN", eps="learnable", hidden=(8,))
    physical = model.physical_parameters()
    names = {n for n, p in model.named_parameters() if any(p is q for q in physical)}
    assert names == {
        "log_mass_scale", "log_mass_rel", "log_second_moments", "raw_mu", "raw_cor", "log_eps"
    }  # fmt: skip
    assert len(model.network_parameters()) + len(physical) == len(list(model.parameters()))
    module = RolloutModule(model=model, lr=1e-3, weight_decay=1e-4, physics_lr=0.05)
    opt = module.configure_optimizers()
    opt = opt["optimizer"] if isinstance(opt, dict) else opt
    net, phys = opt.param_groups
    assert (net["lr"], net["weight_decay"]) == (1e-3, 1e-4)
    assert (phys["lr"], phys["weight_decay"]) == (0.05, 0.0)
    assert {id(p) for p in phys["params"]} == {id(p) for p in physical}
    # frozen parameters are left out; physics_lr defaults to lr
    model.log_mass_rel.requires_grad_(False)
    opt = RolloutModule(model=model, lr=2e-3).configure_optimizers()
    assert all(g["lr"] == 2e-3 for g in opt.param_groups)
    assert not any(p is model.log_mass_rel for g in opt.param_groups for p in g["params"])
    with pytest.raises(ValueError, match="schedule"):
        RolloutModule(model=model, schedule="linear")


def test_cosine_schedule_runs_from_lr_to_the_floor(bp5_data, tmp_path):
    """Learning rates per step, logged by a callback, follow the documented cosine."""
    seen = []

    class Record(pl.Callback):
        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
            seen.append([g["lr"] for g in trainer.optimizers[0].param_groups])

    train(bp5_data, tmp_path / "run", epochs=3, batch_size=4, lr=1e-3, physics_lr=0.02,
          callbacks=[Record()], **SMALL)  # fmt: skip
    steps = len(seen)
    assert steps == 6  # 8 chunks, batch 4, 3 epochs
    floor = train_mod.COSINE_FLOOR
    for k, (lr_net, lr_phys) in enumerate(seen):
        # after step k (0-based) the scheduler has advanced k + 1 times
        x = min((k + 1) / (steps - 1), 1.0)
        factor = floor + (1 - floor) * 0.5 * (1 + np.cos(np.pi * x))
        assert lr_net == pytest.approx(1e-3 * factor, rel=1e-12)
        assert lr_phys == pytest.approx(0.02 * factor, rel=1e-12)
    assert seen[-1][1] == pytest.approx(0.02 * floor)
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert (run["schedule"], run["physics_lr"]) == ("cosine", 0.02)
    # a different schedule or physics_lr is a different run: resume refuses it
    with pytest.raises(TrainingInputError, match="physics_lr"):
        train(bp5_data, tmp_path / "run", epochs=4, batch_size=4, lr=1e-3, physics_lr=0.03,
              resume=True, **SMALL)  # fmt: skip
    # so is a run of an older model format (different parameters)
    old = {**run, "model_format": 2}
    (tmp_path / "run" / "run.json").write_text(json.dumps(old))
    with pytest.raises(TrainingInputError, match="model_format: 2 -> 3"):
        train(bp5_data, tmp_path / "run", epochs=4, batch_size=4, lr=1e-3, physics_lr=0.02,
              resume=True, **SMALL)  # fmt: skip
    with pytest.raises(TrainingInputError, match="schedule must be"):
        train(bp5_data, tmp_path / "other", schedule="step", **SMALL)
    with pytest.raises(TrainingInputError, match="physics_lr must be > 0"):
        train(bp5_data, tmp_path / "other", physics_lr=-1.0, **SMALL)
