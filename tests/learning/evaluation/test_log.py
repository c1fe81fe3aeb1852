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


def test_the_training_plot_names_e_p_and_marks_the_refit(tmp_path):
    """``training.png`` ended at Adam's values after a refit (evaluate printed the refit's)
    and its legend said ``cor``."""
    from diffcontact.learning.evaluation.plots import _training_series, plot_training

    epochs = np.arange(5.0)
    log = {"epoch": epochs, "train/loss_epoch": np.exp(-epochs), "param/mass_ratio_1": 1 + epochs,
           "param/mu": 0.5 - 0.01 * epochs, "param/cor": 0.4 - 0.02 * epochs}  # fmt: skip
    final = {"mass_ratios": [1.0, 2.5], "mu": [0.44, 0.44], "cor": [0.03, 0.03], "eps": None}
    panels = _training_series(log, None, 2, final)
    assert [label for label, *_ in panels["cor"]] == ["e_P"]
    assert panels["cor"][0][3] == 0.03 and panels["mu"][0][3] == 0.44
    assert panels["mass_ratios"][0][3] == 2.5  # m2/m1: body 1's ratio
    assert all(after is None for *_, after in _training_series(log, None, 2)["cor"])
    path = plot_training(log, None, 2, tmp_path / "training.png", "t", refit=final)
    assert path is not None and path.stat().st_size > 5000
