"""The rollout GIF: a colour per body (truth filled, prediction dashed in the same colour)
and a small file."""

from __future__ import annotations

import numpy as np
from matplotlib.colors import to_rgb
from PIL import Image

import diffcontact as dc
from diffcontact.viz import animate, scene_from_system
from diffcontact.viz.animation import _PALETTE, _build_figure


def _rollouts(task: str, n: int = 4, steps: int = 99):
    """Truth and a deliberately wrong prediction (more gravity) from the same states."""
    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(n, seed=0)
    true = system.simulate(z0, steps, progress=False).numpy()
    wrong = dc.load_system(task, gravity=system.config.gravity * 1.1 + 0.3)
    return system, true, wrong.simulate(z0, steps, progress=False).numpy()


def test_each_body_has_its_colour_for_truth_and_prediction(tmp_path):
    system, true, pred = _rollouts("BP5", n=1, steps=9)
    scene = scene_from_system(system)
    _, panels, _ = _build_figure(
        true, scene, max_trajectories=1, overlay=pred, max_frames=10, labels=None, trail=0,
        panel_size=3.2,
    )  # fmt: skip
    panel = panels[0]
    fills = [to_rgb(body[0].get_facecolor()) for body in panel.bodies]
    outlines = [to_rgb(body[0].get_edgecolor()) for body in panel.over_bodies]
    assert len(set(fills)) == system.n_bodies == 5  # every body its own colour
    assert fills == outlines  # the prediction in its body's colour
    assert all(body[0].get_linestyle() == "--" and not body[0].get_fill()
               for body in panel.over_bodies)  # fmt: skip
    # and in the pixels of the GIF: every body's exact colour is drawn (outlines)
    path = animate(true, scene, tmp_path / "one.gif", overlay=pred, dt=system.dt, trail=0)
    with Image.open(path) as gif:
        rgb = np.array(gif.convert("RGB")).reshape(-1, 3)
    present = {tuple(c) for c in np.unique(rgb, axis=0).tolist()}
    for color in _PALETTE[:5]:
        assert tuple(int(color[i : i + 2], 16) for i in (1, 3, 5)) in present, color


def test_four_trajectories_stay_under_300_kb(tmp_path):
    system, true, pred = _rollouts("BP5")  # 5 bodies x 4 panels x (truth + prediction)
    path = animate(
        true, scene_from_system(system, title="BP5: truth (filled) vs model (dashed)"),
        tmp_path / "rollout.gif", overlay=pred, dt=system.dt, labels=("truth", "model"),
    )  # fmt: skip
    size = path.stat().st_size
    assert 50_000 < size < 300_000, size
    with Image.open(path) as gif:
        assert gif.n_frames == 40  # the default max_frames of 100 states


def test_title_and_legend_fit_over_one_panel():
    """evaluate's GIF of one trajectory (``--n-gif 1``): its title and legend are wider
    than one panel and were cut at the figure's edges."""
    system, true, pred = _rollouts("BP5", n=1, steps=9)
    scene = scene_from_system(system, title="BP5: truth (filled) vs MLP-CD-CLNN (dashed)")
    fig, _, _ = _build_figure(
        true, scene, max_trajectories=1, overlay=pred, max_frames=10,
        labels=("ground truth", "MLP-CD-CLNN"), trail=0, panel_size=3.2,
    )  # fmt: skip
    title = fig.suptitle(f"{scene.title}   t = 0.090 s", fontsize=9)  # as animate sets it
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    width = fig.bbox.width
    for artist in (title, *fig.legends):
        box = artist.get_window_extent(renderer)
        assert 0 <= box.x0 and box.x1 <= width, (artist, box.x0, box.x1, width)
