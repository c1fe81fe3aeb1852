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


def test_the_training_plot_of_one_epoch_has_dots_and_integer_epochs(tmp_path, monkeypatch):
    """A one-epoch run drew lines through one point (nothing visible) over epoch ticks
    -0.045, -0.030, ... (MaxNLocator(integer=True) found no integer in +-0.05)."""
    import diffcontact.learning.evaluation.plots as plots

    figures = []
    monkeypatch.setattr(plots, "_save", lambda fig, path, dpi=110: figures.append(fig) or path)
    log = {"epoch": np.array([0.0]), "train/loss_epoch": np.array([0.02]),
           "val/loss": np.array([0.03]), "param/mass_ratio_1": np.array([1.06]),
           "param/mu": np.array([0.5])}  # fmt: skip
    assert plots.plot_training(log, None, 2, tmp_path / "training.png", "t") is not None
    (fig,) = figures
    fig.canvas.draw()
    for ax in fig.axes:
        lines = [line for line in ax.get_lines() if len(line.get_xdata()) == 1]
        assert lines and all(line.get_marker() not in (None, "", "None") for line in lines)
        lo, hi = ax.get_xlim()
        ticks = [t for t in ax.get_xticks() if lo <= t <= hi]
        assert ticks == [0.0], ticks
    # many epochs: lines without dots, as before
    figures.clear()
    many = {k: np.linspace(1, 2, 40) for k in log}
    many["epoch"] = np.arange(40.0)
    plots.plot_training(many, None, 2, tmp_path / "training.png", "t")
    assert all(line.get_marker() in (None, "", "None") for line in figures[0].axes[0].get_lines())
