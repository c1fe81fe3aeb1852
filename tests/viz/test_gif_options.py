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


def test_gif_frames_are_written_as_they_are_drawn(tmp_path, monkeypatch):
    """Every RGB frame was kept until the last was drawn (1.2 GB for 1000 frames of four
    BP5 panels; 16 panels take 3 MB a frame): each is now written when drawn."""
    from PIL import GifImagePlugin

    from diffcontact.viz import Circle, Scene
    from diffcontact.viz import animation as anim

    events = []
    update, getdata = anim._Panel2D.update, GifImagePlugin.getdata

    def drawn(self, k):
        events.append("draw")
        return update(self, k)

    def written(*args, **kwargs):
        events.append("write")
        return getdata(*args, **kwargs)

    monkeypatch.setattr(anim._Panel2D, "update", drawn)
    monkeypatch.setattr(GifImagePlugin, "getdata", written)
    t = np.linspace(0.0, 1.0, 30)
    x = np.stack([0.2 + 0.6 * t, 0.5 + 0.2 * np.sin(6 * t)], -1)[:, None]  # (T, 1, 2)
    traj = np.stack([x, np.gradient(x, axis=0)], axis=1)  # (T, 2, 1, 2)
    animate(traj, Scene(dim=2, circles=(Circle(0, 0.05),)), tmp_path / "s.gif", max_frames=30)
    assert events.count("write") == 30
    # the palette is cut from 3 frames, drawn first; then each frame is written before
    # the next is drawn (the one written is one behind: it may be lengthened)
    assert events[:5] == ["draw"] * 5 and events[5:] == ["write", "draw"] * 28 + ["write"] * 2
    with Image.open(tmp_path / "s.gif") as image:
        assert image.n_frames == 30


@pytest.mark.parametrize("encoder", ["per frame", "pillow"])
def test_the_gif_writer_round_trips_and_merges_equal_frames(tmp_path, monkeypatch, encoder):
    """The GIF written one frame at a time reads back as the frames given (changed
    rectangles with transparent pixels after the first), equal frames as one longer; so
    does Pillow's own writer, taken where its per-frame encoder is missing."""
    from PIL import GifImagePlugin

    from diffcontact.viz.animation import _save_gif

    if encoder == "pillow":
        monkeypatch.delattr(GifImagePlugin, "getdata")

    rng = np.random.default_rng(0)
    palette = rng.integers(0, 256, 3 * 20).tolist()
    frames = [rng.integers(0, 20, (40, 50), dtype=np.uint8)]
    for k in range(6):
        nxt = frames[-1].copy()
        if k != 2:  # frame 3 equals frame 2
            nxt[5 + k : 9 + 2 * k, 10 : 12 + 3 * k] = rng.integers(0, 20, (4 + k, 2 + 3 * k))
        frames.append(nxt)
    images = []
    for f in frames:
        im = Image.fromarray(f).convert("P")  # (L -> P keeps the indices)
        im.putpalette(palette)
        images.append(im)
    path = tmp_path / "w.gif"
    _save_gif(palette, iter(images), path, fps=10)
    colors = np.array(palette).reshape(-1, 3)
    expected = [frames[k] for k in range(len(frames)) if k != 3]
    with Image.open(path) as gif:
        assert gif.n_frames == len(expected) and gif.info["loop"] == 0
        durations = []
        for k, want in enumerate(expected):
            gif.seek(k)
            durations.append(gif.info["duration"])
            np.testing.assert_array_equal(np.asarray(gif.convert("RGB")), colors[want])
    assert durations == [100, 100, 200, 100, 100, 100]
    assert not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]
