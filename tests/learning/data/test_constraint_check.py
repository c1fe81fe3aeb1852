"""Recorded data against the config's equality constraints, and the recording's dt.

A MuJoCo pendulum converted with the wrong origin (its links 0.49 m off on 0.4 m) and rigid
disks whose axis points lay at the rim were turned into datasets and trained on without a
word; ``generate --from-arrays FILE --config OTHER`` dropped the file's own config silently.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
import torch

import diffcontact as dc
from diffcontact.learning.data.arrays import dataset_from_arrays
from diffcontact.learning.data.checks import CONSTRAINT_TOL, constraint_violation
from diffcontact.learning.data.cli import register_cli
from diffcontact.mechanics import dot_constraints

from .support import short_config


def _recorded(task: str, n: int = 6, steps: int = 12) -> tuple[dc.System, np.ndarray]:
    system = dc.load_system(short_config(task, 0.5))
    z0 = system.sample_initial_conditions(n, seed=0)
    return system, system.simulate(z0, steps).numpy()


@pytest.mark.parametrize("task", ["BD5", "CP3", "CP3-e", "Gyro", "Gyro-e", "BD1-ground"])
def test_simulated_data_drift_far_below_the_tolerance(task):
    """A simulation over the task's whole horizon keeps its constraints within a quarter of
    CONSTRAINT_TOL (CP3's chain drifts the most)."""
    system = dc.load_system(task)
    traj = system.simulate(system.sample_initial_conditions(8, seed=0), system.default_steps)
    rel = system.constraints.relative_residual(traj[:, :, 0])
    assert float(rel.max()) < CONSTRAINT_TOL / 4, task
    assert constraint_violation(system, traj[:, :, 0].numpy()) is None


def test_the_data_check_refuses_what_simulate_warns_about():
    """One tolerance for recorded data off their constraints and simulated rollouts that
    drift off them (two constants: the data checks import no torch)."""
    from diffcontact.systems.system import CONSTRAINT_DRIFT_TOL

    assert CONSTRAINT_TOL == CONSTRAINT_DRIFT_TOL


def test_relative_residual_of_a_link_an_axis_and_a_pivot():
    """``|u . w - c| / max(|u| |w|, |c|)`` for dot rows, ``|x_p - anchor|`` over the state's
    extent for linear ones."""
    cons = dot_constraints([[0, 1, 0, 1]], [0.25], dim=2, num_points=2)  # |x0 - x1|^2 = 0.5^2
    x = torch.tensor([[0.0, 0.0], [0.6, 0.0]], dtype=torch.float64)
    assert float(cons.relative_residual(x)[0]) == pytest.approx((0.36 - 0.25) / 0.36)
    pendulum = dc.load_system("CP3")  # point 0 hangs from the pivot: a dot row with an anchor
    x = pendulum.sample_initial_conditions(1, seed=0)[0, 0]
    assert float(pendulum.constraints.relative_residual(x).max()) < 1e-12
    shifted = pendulum.constraints.relative_residual(x + 0.3)  # the whole chain off its pivot
    assert float(shifted.max()) > 0.5 and float(shifted.min()) < 1e-12  # links kept


def test_dataset_from_arrays_refuses_data_off_the_constraints(tmp_path):
    system, traj = _recorded("CP3")
    dataset_from_arrays(traj, system.config, tmp_path / "ok", progress=False)  # as simulated
    moved = traj.copy()
    moved[:, :, 0] += np.array([0.0, 0.6])  # the recording's origin is not the config's
    with pytest.raises(ValueError, match=r"break the config's equality constraints .* relative"):
        dataset_from_arrays(moved, system.config, tmp_path / "moved", progress=False)
    disks, dtraj = _recorded("BD5")
    rim = dtraj.copy()  # a disk's axis points at 0.1 of the centre, not at unit distance
    for b in range(5):
        c = rim[:, :, 0, 3 * b : 3 * b + 1]
        rim[:, :, 0, 3 * b + 1 : 3 * b + 3] = c + 0.1 * (rim[:, :, 0, 3 * b + 1 : 3 * b + 3] - c)
    every = r"by up to 0.99 relative \(trajectory \d+, state \d+; 78 of 78 states above 0.25\)"
    with pytest.raises(ValueError, match=every):
        dataset_from_arrays(rim, disks.config, tmp_path / "rim", progress=False)
    assert not (tmp_path / "moved").exists() and not (tmp_path / "rim").exists()


def test_dt_must_be_a_positive_number_and_a_mismatch_shows_the_digits(tmp_path):
    _, traj = _recorded("BP5", n=3, steps=8)
    with pytest.raises(ValueError, match="dt must be a number, not a string"):
        dataset_from_arrays(traj, "BP5", tmp_path / "a", dt="0.01", progress=False)
    with pytest.raises(ValueError, match=r"dt must be a finite number > 0, got 0"):
        dataset_from_arrays(traj, "BP5", tmp_path / "a", dt=0, progress=False)
    with pytest.raises(ValueError, match=r"dt=0.01000002 of the data differs .* dt=0.01;"):
        dataset_from_arrays(traj, "BP5", tmp_path / "a", dt=0.01000002, progress=False)


def _generate(capsys, *argv: str) -> tuple[int, str]:
    parser = argparse.ArgumentParser(prog="diffcontact")
    register_cli(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["generate", *argv])
    code = args.func(args)
    return code, capsys.readouterr().err


def test_generate_warns_when_config_differs_from_the_files(tmp_path, capsys):
    system, traj = _recorded("BP5", n=6, steps=12)
    stored = system.config.model_dump(mode="json")
    np.savez(tmp_path / "rec.npz", traj=traj, dt=system.dt, config=json.dumps(stored))
    bigger = {**stored, "walls": [[1, 0, 0], [0, 1, 0], [-1, 0, 2], [0, -1, 2]]}
    (tmp_path / "big.json").write_text(json.dumps(bigger))
    argv = ["--from-arrays", str(tmp_path / "rec.npz"), "--quiet", "--impact-tol", "inf"]
    code, err = _generate(capsys, *argv, "--config", str(tmp_path / "big.json"),
                          "--out", str(tmp_path / "d1"))  # fmt: skip
    assert code == 0
    assert "diffcontact generate: warning: --config differs from the config stored in" in err
    assert "the contact geometry differs" in err and "the dataset uses --config" in err
    same = {**stored, "mu": 0.9}  # what is learned may differ: no warning
    (tmp_path / "same.json").write_text(json.dumps(same))
    code, err = _generate(capsys, *argv, "--config", str(tmp_path / "same.json"),
                          "--out", str(tmp_path / "d2"))  # fmt: skip
    assert code == 0 and "differs" not in err
