"""Datasets generated once for all dataset tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from diffcontact.learning.data.generate import generate_dataset

from .support import BP5, CP3, SIZES, all_trajectories


@pytest.fixture(scope="package")
def bp5_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("data") / "bp5"
    return generate_dataset(BP5, out, **SIZES, seed=0, progress=False)


@pytest.fixture(scope="package")
def cp3_noisy_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("data") / "cp3"
    return generate_dataset(CP3, out, n_train=8, n_val=1, n_test=1, noise_std=0.05, progress=False)


@pytest.fixture(scope="package")
def recorded(bp5_dir) -> np.ndarray:
    return all_trajectories(bp5_dir)
