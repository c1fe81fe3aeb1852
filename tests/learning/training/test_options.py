"""One set of training defaults: train(), RolloutModule and ``diffcontact train`` agree."""

from __future__ import annotations

import argparse
import inspect

from diffcontact.learning.models.physical import LearnedModel
from diffcontact.learning.training import options
from diffcontact.learning.training.cli import register_cli
from diffcontact.learning.training.module import RolloutModule
from diffcontact.learning.training.run import ChunkDataModule, train

DEFAULTS = {
    "model": options.DEFAULT_MODEL,
    "epochs": options.DEFAULT_EPOCHS,
    "batch_size": options.DEFAULT_BATCH_SIZE,
    "lr": options.DEFAULT_LR,
    "weight_decay": options.DEFAULT_WEIGHT_DECAY,
    "physics_lr": options.DEFAULT_PHYSICS_LR,
    "schedule": options.DEFAULT_SCHEDULE,
    "seed": options.DEFAULT_SEED,
    "device": options.DEFAULT_DEVICE,
    "eps": None,  # options of the physical models: None means the model's default
    "hidden": None,
    "dtype": options.DEFAULT_DTYPE,
}


def _defaults(func) -> dict:
    params = inspect.signature(func).parameters.values()
    return {p.name: p.default for p in params if p.default is not inspect.Parameter.empty}


def test_train_module_data_and_cli_share_the_defaults():
    assert {k: v for k, v in _defaults(train).items() if k in DEFAULTS} == DEFAULTS
    module = _defaults(RolloutModule.__init__)
    for name in ("lr", "weight_decay", "physics_lr", "schedule", "dtype"):
        assert module[name] == DEFAULTS[name], name
    data = _defaults(ChunkDataModule.__init__)
    for name in ("batch_size", "seed", "dtype"):
        assert data[name] == DEFAULTS[name], name
    parser = argparse.ArgumentParser()
    register_cli(parser.add_subparsers(dest="command"))
    args = vars(parser.parse_args(["train", "DATA", "--out", "RUN"]))
    assert {k: args[k] for k in DEFAULTS} == DEFAULTS
    # the physical models' own defaults are the documented ones
    physical = _defaults(LearnedModel.__init__)
    assert physical["eps"] == options.DEFAULT_EPS and physical["hidden"] == options.DEFAULT_HIDDEN
