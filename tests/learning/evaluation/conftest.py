"""A dataset written once for all evaluation tests."""

from __future__ import annotations

from pathlib import Path

import pytest

import diffcontact as dc
from diffcontact.learning.data.arrays import dataset_from_arrays

from .support import TINY


@pytest.fixture(scope="package")
def dataset(tmp_path_factory) -> Path:
    """A dataset folder whose test split holds 3 trajectories of 20 states."""
    system = dc.load_system(TINY)
    traj = system.simulate(system.sample_initial_conditions(5, seed=1))
    folder = tmp_path_factory.mktemp("data") / "tiny"
    return dataset_from_arrays(
        traj, TINY, folder, val_fraction=0.2, test_fraction=0.6, progress=False
    )
