"""The rollout loss and RolloutModule: loss decrease, skipped steps, learning rates, mu/e_P."""

from __future__ import annotations

import itertools
import json
import logging
import warnings

import lightning.pytorch as pl
import numpy as np
import pytest
import torch

import diffcontact as dc
from diffcontact.contact import ConeQPError
from diffcontact.learning.models.physical import LearnedModel
from diffcontact.learning.training import module as module_mod
from diffcontact.learning.training.module import RolloutModule, rollout_loss
from diffcontact.learning.training.run import ChunkDataModule, read_training_data, train

from .support import SMALL, write_dataset


def test_a_few_steps_reduce_the_loss(bp5_data):
    chunks = read_training_data(bp5_data)[1][:4]
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


def test_nonfinite_and_failed_steps_are_skipped_and_reported(tmp_path, caplog, monkeypatch):
    data = write_dataset(tmp_path / "data", "BP5", n=(6, 2, 2), steps=10, nan_train=(0,))
    calls = {"n": 0}
    real_loss = module_mod.rollout_loss

    def flaky_loss(model, chunk):
        calls["n"] += 1
        if calls["n"] == 2:
            raise ConeQPError("1 of 1 problems did not converge (simulated)")
        loss = real_loss(model, chunk)
        if calls["n"] == 3:  # finite value, non-finite gradient
            s = model.log_mass_rel.sum()
            loss = loss + 0.0 * torch.sqrt(s - s.detach())
        return loss

    monkeypatch.setattr(module_mod, "rollout_loss", flaky_loss)
    with caplog.at_level(logging.WARNING, logger="diffcontact.learning.training.module"):
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


def test_rollout_warnings_are_one_line_per_epoch(tmp_path, caplog, monkeypatch, recwarn):
    """A learned contact model's rollouts tunnel until it has learned to stop the bodies:
    one RuntimeWarning per batch had flooded the log (compare.py's MLP-CD-CLNN runs).
    Tunnelling and constraint drift are counted, one line per epoch; other warnings pass
    on."""
    from diffcontact.systems import ConstraintDriftWarning, RolloutWarning, TunnellingWarning

    data = write_dataset(tmp_path / "data", "BP5", n=(6, 2, 2), steps=10)
    calls = {"n": 0}
    real_loss = module_mod.rollout_loss

    def tunnelling_loss(model, chunk):
        calls["n"] += 1
        if calls["n"] in (2, 7):  # two training batches (of 6), then a validation one
            warnings.warn(f"bodies tunnelled in call {calls['n']} (on_tunnelling='ignore' "
                          "silences this)", TunnellingWarning, stacklevel=2)  # fmt: skip
        if calls["n"] == 5:
            warnings.warn("drifted", ConstraintDriftWarning, stacklevel=2)
        if calls["n"] == 3:
            warnings.warn("another warning", UserWarning, stacklevel=2)
        return real_loss(model, chunk)

    monkeypatch.setattr(module_mod, "rollout_loss", tunnelling_loss)
    with caplog.at_level(logging.WARNING, logger="diffcontact.learning.training.module"):
        train(data, tmp_path / "run", epochs=1, batch_size=1, **SMALL)
    assert calls["n"] == 8  # 6 training and 2 validation batches
    lines = [r.getMessage() for r in caplog.records if "tunnelled" in r.getMessage()]
    assert lines == [
        "epoch 1: the rollouts of 2 training and 1 validation batch(es) warned (tunnelling, "
        "constraint drift); first: bodies tunnelled in call 2"
    ]
    assert not [w for w in recwarn if issubclass(w.category, RolloutWarning)]
    assert [str(w.message) for w in recwarn if w.category is UserWarning] == ["another warning"]


def test_gradient_spikes_are_skipped_and_resume_keeps_the_history(bp5_data, tmp_path, monkeypatch):
    """A batch whose gradient is 1e6 times the usual is skipped, not fed to Adam."""
    calls = {"n": 0}
    real_loss = module_mod.rollout_loss

    def spiky_loss(model, chunk):
        calls["n"] += 1
        loss = real_loss(model, chunk)
        return loss * 1e6 if calls["n"] == 3 else loss  # the third training step

    monkeypatch.setattr(module_mod, "rollout_loss", spiky_loss)
    model = train(bp5_data, tmp_path / "run", epochs=2, batch_size=2, **SMALL)
    learned = json.loads((tmp_path / "run" / "learned.json").read_text())
    assert learned["skipped_steps_total"]["gradient_spike"] == 1
    assert sum(learned["skipped_steps_total"].values()) == 1
    assert learned["global_step"] == 7  # 8 batches, 1 skipped
    assert all(torch.isfinite(p).all() for p in model.parameters())
    ckpt = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", weights_only=False)
    history = ckpt["diffcontact"]["grad_norm_history"]
    # the skipped step's norms are part of the history (the median is every step's)
    assert len(history) == 2 and len(history[0]) == len(history[1]) == 8
    for h in history:
        assert sum(x > module_mod.SPIKE_FACTOR * np.median(h) for x in h) == 1


@pytest.mark.parametrize("every", [2, 4, 8])
def test_a_batch_whose_gradient_stays_large_is_not_skipped_for_good(every):
    """Once the easy batches' gradients have shrunk, a batch whose gradient stays large
    (its contacts; one in ``every`` steps) is skipped as a spike only for its first few
    steps: the skipped norms count, against a high quantile. A median over the accepted
    steps skipped it in every epoch, and a median over all steps still did most of the
    time when such batches were about half of them."""
    m = module_mod.RolloutModule.__new__(module_mod.RolloutModule)
    m.group_names, m.grad_norm_history = ["physical"], [[]]
    for _ in range(module_mod.SPIKE_WINDOW):  # the easy batches have converged
        m._record_norms([1e-6])
    skipped = []
    for step in range(400):
        norm = 1e-2 if step % every == 0 else 1e-6
        skipped.append(m._spike([norm]) is not None)
        m._record_norms([norm])
    assert skipped[0]  # at first a spike ...
    assert sum(skipped) <= 6 and not any(skipped[100:])  # ... then trained on
    # a one-off spike in a steady history stays a spike
    m.grad_norm_history = [[1e-6] * (module_mod.SPIKE_WINDOW - 1) + [1e-2]]
    assert m._spike([1e-2]) is not None


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
    module = RolloutModule(
        model=model,
        lr=0.04,
        weight_decay=0.0,
        dtype="float64",
        physics_lr=None,  # the network's lr, without a schedule
        schedule="constant",
    )
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
    # frozen parameters are left out; physics_lr None means lr
    model.log_mass_rel.requires_grad_(False)
    opt = RolloutModule(
        model=model, lr=2e-3, physics_lr=None, schedule="constant"
    ).configure_optimizers()
    assert all(g["lr"] == 2e-3 for g in opt.param_groups)
    assert not any(p is model.log_mass_rel for g in opt.param_groups for p in g["params"])
    with pytest.raises(ValueError, match="schedule"):
        RolloutModule(model=model, schedule="linear")


def test_a_rollout_that_blew_up_is_a_skipped_step(tmp_path, monkeypatch):
    """System.simulate's NonFiniteRolloutError (its message now also names blown-up finite
    values) is a skipped step, not a crash of the run: it was recognised by the words
    "NaN or infinite" in its message."""
    from diffcontact.systems import NonFiniteRolloutError

    gyro = dc.load_system("Gyro", dt=0.5, horizon=5.0)
    with pytest.raises(NonFiniteRolloutError) as blown:
        gyro.simulate(gyro.sample_initial_conditions(2, seed=0), 3)
    assert "NaN or infinite" not in str(blown.value)  # the wording the check relied on
    data = write_dataset(tmp_path / "data", "BP5", n=(4, 2, 2), steps=10)
    calls = {"n": 0}
    real_loss = module_mod.rollout_loss

    def blowing_up(model, chunk):
        calls["n"] += 1
        if calls["n"] == 2:
            raise blown.value
        return real_loss(model, chunk)

    monkeypatch.setattr(module_mod, "rollout_loss", blowing_up)
    train(data, tmp_path / "run", epochs=1, batch_size=1, **SMALL)
    learned = json.loads((tmp_path / "run" / "learned.json").read_text())
    assert learned["skipped_steps"]["nonfinite_loss"] == 1
