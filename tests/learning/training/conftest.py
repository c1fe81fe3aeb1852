"""A dataset written once for all training tests."""

from __future__ import annotations

import pytest

from .support import write_dataset


@pytest.fixture(scope="package")
def bp5_data(tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("bp5"), "BP5")
