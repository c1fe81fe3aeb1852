"""The penetration target's metric (config key ``penetration_metric``): resting extended
bodies must not drift by how their points are laid out."""

import math

import pytest
import torch

import diffcontact as dc
from diffcontact.mechanics import disk_points_2d

F64 = torch.float64


def _disks(centres, angles) -> torch.Tensor:
    """Disks at rest: ``(1, 2, 3B, 2)``."""
    c = torch.tensor([centres], dtype=F64)
    a = torch.tensor([angles], dtype=F64)
    B = c.shape[1]
    z = disk_points_2d(c, a, torch.zeros(1, B, 2, dtype=F64), torch.zeros(1, B, dtype=F64))
    return z.transpose(1, 2).reshape(1, 2, 3 * B, 2)


def test_a_disk_resting_on_the_ground_stays_put_at_any_body_angle():
    """BD1-ground (mu = 0.3): a disk at rest on the ground settles into it and stays where
    it is. With appendix G's Euclidean metric it drifted sideways by 2.6 mm in 1 s, in a
    direction set by its body axes (none at 45 degrees)."""
    angles = [0.0, math.pi / 4, math.pi / 2, 2.0]
    z0 = torch.cat([_disks([[0.5, 0.1]], [a]) for a in angles])
    drift = {}
    for metric in ("mass", "euclidean"):
        system = dc.load_system("BD1-ground", penetration_metric=metric)
        traj = system.simulate(z0, progress=False)
        drift[metric] = (traj[:, -1, 0, 0, 0] - 0.5).abs()
        if metric == "mass":
            assert float(system.gaps(traj[:, -1, 0]).min()) > -5e-3  # settled, not sunk
    assert float(drift["mass"].max()) < 1e-12
    assert float(drift["euclidean"][0]) > 1e-3  # the paper's form, kept as an option


def test_a_stack_of_disks_with_friction_stands():
    """Three disks stacked on the ground, mu = 0.5, inelastic: nothing moves sideways
    (the Euclidean metric's tangential targets toppled the stack within 2 s)."""
    config = dict(
        type="bouncing_disks", masses=[1.0, 1.0, 1.0], radii=[0.1, 0.1, 0.1],
        walls=[[0.0, 1.0, 0.0]], gravity=9.81, dt=0.01, horizon=2.0, cor=0.0, mu=0.5,
    )  # fmt: skip
    z0 = _disks([[0.5, 0.1], [0.5, 0.3], [0.5, 0.5]], [0.3, 1.1, 2.0])
    lateral = {}
    for metric in ("mass", "euclidean"):
        system = dc.load_system({**config, "penetration_metric": metric})
        traj = system.simulate(z0, progress=False, check_overlap=False)
        lateral[metric] = float((traj[0, :, 0, ::3, 0] - 0.5).abs().max())
    assert lateral["mass"] < 1e-12
    assert lateral["euclidean"] > 1e-2


def test_point_masses_are_the_same_under_both_metrics():
    """Without equality constraints the two metrics are the same target (bitwise)."""
    z0 = dc.load_system("BP5").sample_initial_conditions(8, seed=0)
    a = dc.load_system("BP5", penetration_metric="mass").simulate(z0, 60, progress=False)
    b = dc.load_system("BP5", penetration_metric="euclidean").simulate(z0, 60, progress=False)
    assert torch.equal(a, b)


def test_an_unknown_metric_is_a_clear_error():
    with pytest.raises(ValueError, match="penetration_metric"):
        dc.load_system("BD5", penetration_metric="inertia")


def test_files_written_before_the_key_keep_the_euclidean_target(tmp_path):
    """A dataset's metadata and a model file store the config as a complete dump; one
    without ``penetration_metric`` predates the key, when every system ran the Euclidean
    target. Read with the new default it would simulate its own data differently."""
    import json

    from diffcontact.learning.data.format import Dataset, load_dataset
    from diffcontact.learning.data.generate import generate_dataset
    from diffcontact.learning.models.registry import create_model
    from diffcontact.learning.models.storage import (
        load_model,
        model_checkpoint,
        model_from_checkpoint,
        save_model,
    )
    from diffcontact.systems.config import stored_config

    dump = dc.load_system("BD1-ground").config.model_dump(mode="json")
    assert dump["penetration_metric"] == "mass"  # dumps of this version carry the key
    old = {k: v for k, v in dump.items() if k != "penetration_metric"}
    assert stored_config(old)["penetration_metric"] == "euclidean"
    assert stored_config(dump) == dump
    data = tmp_path / "data"
    generate_dataset("BD1-ground", data, n_train=2, n_val=1, n_test=1, progress=False)
    dataset = load_dataset(data)
    assert dataset.system.penetration_metric == "mass"
    meta = json.loads((data / "metadata.json").read_text())
    meta["config"].pop("penetration_metric")  # (as written before the key existed)
    earlier = Dataset(dataset.path, meta, dataset.config)
    assert earlier.system.penetration_metric == "euclidean"
    for name in ("CM-CD-CLNN", "MLP-CD-CLNN"):
        model = create_model(name, dump)
        save_model(model, tmp_path / "model.pt")
        assert load_model(tmp_path / "model.pt").system.penetration_metric == "mass"
        stored = model_checkpoint(model)
        stored["config"].pop("penetration_metric")  # (a file of an earlier version)
        assert model_from_checkpoint(stored).system.penetration_metric == "euclidean"
