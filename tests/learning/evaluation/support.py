"""Constants and helpers shared by the evaluation tests."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import diffcontact as dc
from diffcontact.learning.evaluation.cli import register_cli

BOX = [[1, 0, 0], [0, 1, 0], [-1, 0, 1], [0, -1, 1]]
# two point masses in the unit box: heterogeneous restitution, 1 pair + 8 wall contacts
TINY = {
    "type": "bouncing_masses",
    "name": "BP2",
    "masses": [0.1, 0.3],
    "radii": [0.1, 0.15],
    "walls": BOX,
    "mu": 0.2,
    "cor": [0.9, 0.8, 0.8, 0.8, 0.8, 0.7, 0.7, 0.7, 0.7],
    "dt": 0.01,
    "horizon": 0.2,  # 20 states: shorter than the 100-state evaluation rollout
}


def write_log(run: Path, epochs: int = 12) -> Path:
    """A Lightning-style metrics.csv: step rows and epoch rows with empty cells."""
    folder = run / "logs" / "lightning_logs" / "version_0"
    folder.mkdir(parents=True)
    rows = ["epoch,step,train_loss_step,train_loss_epoch,val_loss,mass_ratio_0,mass_ratio_1,mu,cor"]
    for e in range(epochs):
        a = math.exp(-e / 3)
        rows.append(f"{e},{3 * e},{1.2 * a},,,,,,")
        rows.append(f"{e},{3 * e + 2},,{a},,1.0,{3 - 2 * a},{0.2 + 0.3 * a},{0.8 - 0.3 * a}")
        rows.append(f"{e},{3 * e + 2},,,{1.1 * a},,,,")
    path = folder / "metrics.csv"
    path.write_text("\n".join(rows) + "\n")
    return path


class FailingTruth:
    """The model contract backed by TINY's ground truth, except that the rollouts from the
    initial states of the test trajectories ``states`` (taken from the first call, the
    test set's) fail with ``error(failed_rows)``: a diverged or a failed-solve model."""

    def __init__(self, states, error):
        self.system = dc.load_system(TINY)
        self.states, self.error, self.bad = list(states), error, None

    def simulate(self, z0, steps):
        if self.bad is None:
            self.bad = z0[self.states].clone()
        hit = ((z0[:, None] - self.bad[None]).flatten(2).abs().amax(-1) == 0).any(-1)
        if bool(hit.any()):
            raise self.error(hit.nonzero().flatten().tolist())
        return self.system.simulate(z0, steps)


class SystemModel:
    """The model contract, backed by a ground-truth System (optionally with other masses)."""

    def __init__(self, config, **overrides):
        self.system = dc.load_system(config, **overrides)
        self.config = self.system.config
        self.model_name = "truth" if not overrides else "perturbed"

    def simulate(self, z0, steps):
        return self.system.simulate(z0, steps)

    def learned_parameters(self):
        m, K = self.system.mass, self.system.n_contacts
        return {
            "mass_ratios": (m / m[0]).tolist(),  # includes the first body, like LearnedModel
            "mu": self.system.mu.expand(K).tolist(),
            "cor": self.system.cor.expand(K).tolist(),
            "eps": None,
        }


def run_dir(root: Path, data: Path, log: bool = True) -> Path:
    run = root / "run"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"data_dir": str(data), "model": "CM-CD-CLNN"}))
    if log:
        write_log(run)
    return run


def cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="diffcontact")
    sub = parser.add_subparsers(dest="command")
    register_cli(sub)
    args = parser.parse_args(argv)
    return args.func(args)
