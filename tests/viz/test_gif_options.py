"""GIF options of the CLIs and the library: the frame count, the panel cap, body colours."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from diffcontact.testing import assert_usage_error, run_cli
from diffcontact.viz import animate, scene_from_system
from diffcontact.viz.animation import _CONTACT, _PALETTE, MAX_PANELS, _hex_rgb


def test_no_body_has_the_contact_colour():
    """A body in contact gets a red outline; body 3 was tab10's red (#d62728, 57 apart in
    RGB from the outline), so its contacts did not show (the nearest now: orange, 131)."""
    contact = np.array(_hex_rgb(_CONTACT), dtype=float)
    for color in _PALETTE:
        assert np.linalg.norm(np.array(_hex_rgb(color), dtype=float) - contact) > 100, color


def test_simulate_gif_frames(tmp_path, capsys):
    gif = tmp_path / "s.gif"
    argv = ["simulate", "BP5", "--n", "1", "--steps", "30", "--out", str(tmp_path / "s.npz")]
    code, _, err = run_cli(capsys, *argv, "--gif", str(gif), "--gif-frames", "7", "--quiet")
    assert code == 0, err
    with Image.open(gif) as image:
        assert image.n_frames == 7
    code, _, err = run_cli(capsys, *argv, "--gif", str(gif), "--gif-frames", "0")
    assert_usage_error(code, err, "--gif-frames")


def test_the_panel_cap(tmp_path):
    import diffcontact as dc

    system = dc.load_system("BP5")
    traj = system.simulate(system.sample_initial_conditions(MAX_PANELS + 1, seed=0), 2)
    scene = scene_from_system(system)
    with pytest.raises(ValueError, match=f"at most {MAX_PANELS}"):
        animate(traj, scene, tmp_path / "a.gif", max_trajectories=MAX_PANELS + 1)
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="max_trajectories must be a positive integer"):
            animate(traj, scene, tmp_path / "a.gif", max_trajectories=bad)
    with pytest.raises(ValueError, match="max_frames must be a positive integer"):
        animate(traj, scene, tmp_path / "a.gif", max_frames=0)
    assert not (tmp_path / "a.gif").exists()


def test_evaluate_refuses_more_panels_than_the_cap(tmp_path):
    from diffcontact.learning.evaluation.evaluate import EvaluationInputError, evaluate

    cap = rf"n_gif must be an integer in \[0, {MAX_PANELS}\]"
    with pytest.raises(EvaluationInputError, match=cap):
        evaluate(tmp_path / "run", n_gif=MAX_PANELS + 1)
    with pytest.raises(EvaluationInputError, match="gif_frames must be a positive integer"):
        evaluate(tmp_path / "run", gif_frames=0)
