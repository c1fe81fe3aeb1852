"""The seams are real: a contact model and a learned model defined here, outside the
package, registered, and run through ``simulate``, ``generate``, ``train`` and
``evaluate`` on the command line (docs/architecture.md has the same example)."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
import torch
from torch import nn

import diffcontact as dc
from diffcontact.cli import main
from diffcontact.contact import PoissonTwoPhase
from diffcontact.registry import Registry

BALL = {
    "name": "ball",
    "type": "bouncing_masses",
    "masses": [1.0],
    "radii": [0.1],
    "walls": [[0, 1, 0], [1, 0, 0], [-1, 0, 1]],
    "gravity": 9.81,
    "mu": 0.5,
    "cor": 0.8,
    "dt": 0.01,
    "horizon": 0.5,
    "initial_conditions": {"position_low": [0.2, 0.2], "position_high": [0.8, 0.6]},
}


class Frictionless:
    """A contact model: CM with mu = 0."""

    def resolve(self, J_C, Mhat_inv, v, params, active, d, **kwargs):
        params = params.replace(mu=torch.zeros_like(params.mu))
        return PoissonTwoPhase().resolve(J_C, Mhat_inv, v, params, active, d, **kwargs)


class LearnedRestitution(nn.Module):
    """A learned model: the true structure, gravity and mass, e_P learned, our contact model."""

    def __init__(self, config, init=0.5):
        super().__init__()
        self.system, self.model_name = dc.load_system(config), "LearnedRestitution"
        self.config, self.init = self.system.config, float(init)
        self.raw_cor = nn.Parameter(torch.tensor(self.init))
        self.dt, self.state_shape = self.system.dt, self.system.state_shape
        self.default_steps = self.system.default_steps

    def simulate(self, z0, steps=None, **kwargs):
        p = self.system.parameters().replace(cor=self.raw_cor.clamp(0, 1).to(z0))
        return self.system.simulate(z0, steps, params=p, contact_model="Frictionless", **kwargs)

    def options(self):
        return {"init": self.init}

    def param_groups(self, s):
        return [{"name": "physical", "params": [self.raw_cor], "lr": s.physics_lr}]

    def metrics(self):
        return {"param/cor": float(self.raw_cor.detach().clamp(0, 1))}


@pytest.fixture
def plugins():
    dc.contact.register_contact_model("Frictionless", Frictionless)
    dc.learning.register_model("LearnedRestitution", LearnedRestitution)
    yield
    dc.contact.unregister_contact_model("Frictionless")
    dc.learning.unregister_model("LearnedRestitution")


def test_outside_contact_model_and_model_through_the_cli(plugins, tmp_path, capsys):
    config = tmp_path / "ball.json"
    config.write_text(json.dumps(BALL))
    sim = tmp_path / "sim.npz"
    args = ["simulate", str(config), "--n", "2", "--steps", "30", "--out", str(sim)]
    assert main([*args, "--contact-model", "Frictionless", "--quiet"]) == 0
    with np.load(sim) as f:
        assert str(f["contact_model"]) == "Frictionless"
    assert main(["simulate", str(config), "--contact-model", "Nope", "--out", str(sim)]) == 2
    assert "invalid choice: 'Nope'" in capsys.readouterr().err

    data, run, ev = tmp_path / "data", tmp_path / "run", tmp_path / "eval"
    code = main(
        ["generate", str(config), "--out", str(data), "--n-train", "16", "--n-val", "4",
         "--n-test", "2", "--contact-model", "Frictionless", "--quiet"]
    )  # fmt: skip
    assert code == 0
    meta = json.loads((data / "metadata.json").read_text())
    assert meta["contact_model"] == "Frictionless"
    code = main(
        ["train", str(data), "--out", str(run), "--model", "LearnedRestitution", "--epochs",
         "15", "--batch-size", "8", "--physics-lr", "0.05", "--model-option", "init=0.3",
         "--quiet"]
    )  # fmt: skip
    assert code == 0
    run_info = json.loads((run / "run.json").read_text())
    assert run_info["model"] == "LearnedRestitution" and run_info["options"] == {"init": 0.3}
    model = dc.learning.load_model(run)
    assert isinstance(model, LearnedRestitution)
    assert float(model.raw_cor.detach()) == pytest.approx(0.8, abs=0.05)  # learned from data

    capsys.readouterr()
    assert main(["evaluate", str(run), "--out", str(ev), "--steps", "20", "--n-gif", "0"]) == 0
    metrics = json.loads((ev / "metrics.json").read_text())
    assert metrics["model"] == "LearnedRestitution"
    assert math.isfinite(metrics["rel_err_mean"]) and metrics["rel_err_mean"] < 0.05
    # the built-in models' options do not apply to a registered model
    code = main(["train", str(data), "--out", str(tmp_path / "r2"), "--model",
                 "LearnedRestitution", "--hidden", "8", "--quiet"])  # fmt: skip
    assert code == 2 and "hidden: option(s) of the built-in models only" in capsys.readouterr().err


def test_unknown_model_lists_the_registered_ones(plugins, tmp_path):
    with pytest.raises(ValueError, match=r"unknown model 'MLP'; .*LearnedRestitution"):
        dc.learning.create_model("MLP", BALL)


def test_building_the_parser_imports_no_torch_or_lightning():
    import subprocess
    import sys

    code = (
        "import sys, diffcontact.cli as c; c.build_parser(); "
        "bad = [m for m in ('torch', 'lightning', 'matplotlib') if m in sys.modules]; "
        "print(bad); sys.exit(1 if bad else 0)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


def test_a_plugin_that_breaks_the_protocol_is_named(tmp_path):
    """A factory raising ZeroDivisionError escaped as a traceback; a model without
    state_shape or model_name failed with AttributeError deep inside training; one without
    trainable parameters with torch's 'optimizer got an empty parameter list'."""

    def raising(config):
        return 1 / 0

    class NoShape(LearnedRestitution):
        def __init__(self, config):
            super().__init__(config)
            del self.state_shape

    class Frozen(LearnedRestitution):
        def __init__(self, config):
            super().__init__(config)
            self.raw_cor.requires_grad_(False)

    with pytest.raises(ValueError, match=r"factory of model 'Raising' raised ZeroDivisionError"):
        dc.learning.register_model("Raising", raising)
        try:
            dc.learning.create_model("Raising", BALL)
        finally:
            dc.learning.unregister_model("Raising")
    dc.learning.register_model("NoShape", NoShape)
    try:
        with pytest.raises(ValueError, match=r"returned NoShape, which has no state_shape"):
            dc.learning.create_model("NoShape", BALL)
    finally:
        dc.learning.unregister_model("NoShape")
    config = tmp_path / "ball.json"
    config.write_text(json.dumps(BALL))
    data = tmp_path / "data"
    assert main(["generate", str(config), "--out", str(data), "--n-train", "4", "--n-val", "2",
                 "--n-test", "1", "--quiet"]) == 0  # fmt: skip
    from diffcontact.learning.training.run import train

    dc.learning.register_model("Frozen", Frozen)
    try:
        with pytest.raises(ValueError, match="model 'Frozen' has no trainable parameters"):
            train(data, tmp_path / "run", model="Frozen", epochs=1, progress=False)
        assert not (tmp_path / "run").exists()
    finally:
        dc.learning.unregister_model("Frozen")


@pytest.mark.parametrize("name", ["--out", " ", "", "a b", "runs/x", "../x", "-m", ".hidden", "é"])
def test_a_model_name_that_cannot_be_given_on_the_command_line_is_refused(name):
    """``register_model`` took '--out', ' ', 'a b' and names with '/': names that cannot be
    given as ``diffcontact train DATA --model NAME`` or that break run-folder names."""
    with pytest.raises(ValueError, match=r"model name .* (is not allowed|non-empty)"):
        dc.learning.register_model(name, LearnedRestitution)
    assert name not in dc.learning.model_names()


def test_model_names_follow_one_rule_built_ins_and_entry_points(monkeypatch):
    """The built-in names fit the rule that registered ones must; an entry point with a name
    that breaks it is left out with a warning (it went into the --model choices)."""
    import importlib.metadata

    from diffcontact.learning.models import registry

    for name in ["CM-CD-CLNN", "MLP-CD-CLNN", "IN-SP-CP", "My_Net.v2", "3body"]:
        assert re.fullmatch(registry.NAME_PATTERN, name), name
    for name in registry.model_names():
        assert re.fullmatch(registry.NAME_PATTERN, name), name
    dc.learning.register_model("My_Net.v2", LearnedRestitution)
    dc.learning.unregister_model("My_Net.v2")

    eps = [
        importlib.metadata.EntryPoint("Good-Net", "tests.test_plugins:LearnedRestitution", "g"),
        importlib.metadata.EntryPoint("--bad", "tests.test_plugins:LearnedRestitution", "g"),
    ]
    monkeypatch.setattr(importlib.metadata, "entry_points", lambda group: eps)
    fresh = Registry("model", {}, "g", name_pattern=registry.NAME_PATTERN, name_rule="rule")
    with pytest.warns(RuntimeWarning, match=r"ignored entry point .* model name '--bad'"):
        assert fresh.names() == ["Good-Net"]
