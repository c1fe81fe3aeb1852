"""The training log: Lightning's metrics.csv per epoch."""

from __future__ import annotations

import numpy as np

from diffcontact.learning.evaluation.log import find_training_log, read_training_log

from .support import write_log


def test_read_training_log_groups_rows_by_epoch(tmp_path):
    path = write_log(tmp_path, epochs=5)
    assert find_training_log(tmp_path) == path
    log = read_training_log(path)
    np.testing.assert_array_equal(log["epoch"], np.arange(5.0))
    assert set(log) >= {"train_loss_epoch", "val_loss", "mass_ratio_1", "mu", "cor"}
    assert "step" not in log
    np.testing.assert_allclose(log["val_loss"], 1.1 * np.exp(-np.arange(5) / 3))
    assert find_training_log(tmp_path / "nothing") is None
