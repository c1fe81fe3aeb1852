"""A dataset written once for all evaluation tests."""

from __future__ import annotations

from pathlib import Path

import pytest

import diffcontact as dc
from diffcontact.learning.data.arrays import dataset_from_arrays
from diffcontact.learning.data.generate import generate_dataset

from .support import TINY


@pytest.fixture(scope="package")
def dataset(tmp_path_factory) -> Path:
    """A simulated dataset (its config is the truth): 3 test trajectories of 20 states."""
    folder = tmp_path_factory.mktemp("data") / "tiny"
    return generate_dataset(TINY, folder, n_train=1, n_val=1, n_test=3, seed=1, progress=False)


@pytest.fixture(scope="package")
def recorded_dataset(tmp_path_factory) -> Path:
    """The same system as recorded data, true parameters not declared: 3 test trajectories."""
    system = dc.load_system(TINY)
    traj = system.simulate(system.sample_initial_conditions(5, seed=1))
    folder = tmp_path_factory.mktemp("data") / "recorded"
    return dataset_from_arrays(
        traj, TINY, folder, val_fraction=0.2, test_fraction=0.6, progress=False
    )
