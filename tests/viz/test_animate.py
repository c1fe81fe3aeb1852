"""GIF animations, energy plots and scenes (diffcontact.viz)."""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest
import torch
from PIL import Image

from diffcontact.viz import (
    Chain,
    Circle,
    Disk3D,
    Scene,
    animate,
    frame_indices,
    plot_energy,
    render_frame,
    scene_from_config,
    scene_from_system,
)

BOX = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (-1.0, 0.0, 1.0), (0.0, -1.0, 1.0))


def _with_velocities(x: np.ndarray) -> np.ndarray:
    """Positions ``(..., T, P, d)`` -> states ``(..., T, 2, P, d)`` (finite-difference v)."""
    v = np.gradient(x, axis=-3)
    return np.stack([x, v], axis=-3)


def bouncing_points(n_traj: int, T: int, n: int = 3, seed: int = 0) -> np.ndarray:
    """Points reflected inside [0.2, 0.8]^2 (a triangle wave): ``(N, T, 2, n, 2)``."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(0.2, 0.8, (n_traj, 1, n, 2))
    v = rng.normal(0.0, 1.0, (n_traj, 1, n, 2))
    t = (np.arange(T) * 0.01)[None, :, None, None]
    x = np.abs(((x0 + v * t - 0.2) % 1.2) - 0.6) + 0.2
    return _with_velocities(x)


def rotating_disks(T: int) -> np.ndarray:
    """Two 3-point rigid disks spinning in place: ``(T, 2, 6, 2)``."""
    c = np.array([[0.3, 0.3], [0.7, 0.6]])
    ang = np.linspace(0.0, 4.0, T)[:, None] * np.array([1.0, -2.0])
    ex = np.stack([np.cos(ang), np.sin(ang)], -1)
    ey = np.stack([-np.sin(ang), np.cos(ang)], -1)
    pts = np.stack([c + 0 * ex, c + ex, c + ey], axis=2).reshape(T, 6, 2)
    return _with_velocities(pts)


def chain(T: int, lengths=(0.35, 0.4, 0.35)) -> np.ndarray:
    """A swinging chain from the origin: ``(T, 2, len, 2)``."""
    q = np.stack([np.sin(np.linspace(0, 4, T) * k) for k in (1.0, 1.5, 2.0)], -1)
    rel = np.stack([np.sin(q), -np.cos(q)], -1) * np.asarray(lengths)[:, None]
    return _with_velocities(rel.cumsum(-2))


def gyroscope(T: int) -> np.ndarray:
    """A precessing, spinning body on the origin: ``(T, 2, 4, 3)``."""
    out = []
    for k in range(T):
        a, b, c = 0.1 * k, 0.5 + 0.1 * math.sin(0.2 * k), 0.6 * k
        rz = lambda t: np.array(  # noqa: E731
            [[math.cos(t), -math.sin(t), 0], [math.sin(t), math.cos(t), 0], [0, 0, 1]]
        )
        rx = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
        R = rz(a) @ rx @ rz(c)
        com = R @ np.array([0.0, 0.0, 0.5])
        out.append(np.stack([com, com + R[:, 0], com + R[:, 1], com + R[:, 2]]))
    return _with_velocities(np.asarray(out))


def n_frames(path) -> int:
    with Image.open(path) as im:
        assert im.format == "GIF"
        return im.n_frames


def no_temp_files(folder) -> bool:
    return not [p for p in folder.iterdir() if ".tmp-" in p.name]


def test_gif_bouncing_points(tmp_path):
    traj = bouncing_points(1, 30)[0]  # (T, 2, P, 2)
    scene = Scene(dim=2, circles=tuple(Circle(i, 0.05 + 0.03 * i) for i in range(3)), walls=BOX)
    out = animate(traj, scene, tmp_path / "bp.gif", dt=0.01, fps=10)
    assert out == tmp_path / "bp.gif"
    assert n_frames(out) == 30
    assert out.stat().st_size > 5_000
    assert no_temp_files(tmp_path)


def test_frames_subsampled_and_grid(tmp_path):
    traj = torch.from_numpy(bouncing_points(6, 250))  # torch input, N > max_trajectories
    scene = Scene(dim=2, circles=tuple(Circle(i, 0.08) for i in range(3)), walls=BOX)
    out = animate(traj, scene, tmp_path / "grid.gif", max_frames=40, dpi=50, panel_size=3.0)
    assert n_frames(out) == 40
    with Image.open(out) as im:  # 4 trajectories shown as a 2 x 2 grid
        w, h = im.size
    assert w == 2 * 3.0 * 50
    assert h > w


def test_frame_indices():
    assert frame_indices(5, 100).tolist() == [0, 1, 2, 3, 4]
    idx = frame_indices(1001, 100)
    assert len(idx) == 100 and idx[0] == 0 and idx[-1] == 1000
    assert np.all(np.diff(idx) > 0)
    with pytest.raises(ValueError, match="max_frames"):
        frame_indices(10, 0)


def test_disks_with_overlay(tmp_path):
    traj = rotating_disks(20)
    circles = (Circle(0, 0.1, oriented=True), Circle(3, 0.15, oriented=True))
    scene = Scene(dim=2, circles=circles, walls=BOX)
    out = animate(
        traj, scene, tmp_path / "bd.gif", overlay=traj + 0.02, labels=("true", "predicted")
    )
    assert n_frames(out) == 20
    with pytest.raises(ValueError, match="overlay"):
        animate(traj, scene, tmp_path / "bad.gif", overlay=traj[:5])
    assert not (tmp_path / "bad.gif").exists()
    assert no_temp_files(tmp_path)


def test_chain_rope_and_frame_png(tmp_path):
    traj = chain(15)
    pendulum = Scene(
        dim=2,
        circles=(Circle(0, 0.05), Circle(1, 0.15), Circle(2, 0.1)),
        chains=(Chain((0, 1, 2), anchor=(0.0, 0.0)),),
        walls=((0.0, 1.0, 1.0),),
        pivots=((0.0, 0.0),),
        title="CP3",
    )
    assert n_frames(animate(traj, pendulum, tmp_path / "cp.gif")) == 15
    rope = Scene(dim=2, chains=(Chain((0, 1, 2), anchor=(0.0, 0.0), style="rope"),))
    assert n_frames(animate(traj, rope, tmp_path / "rope.gif")) == 15
    png = render_frame(traj, pendulum, tmp_path / "cp.png", frame=7, dt=0.01)
    with Image.open(png) as im:
        assert im.format == "PNG"


def test_gyroscope_3d(tmp_path):
    traj = gyroscope(12)
    scene = Scene(
        dim=3,
        disks3d=(Disk3D(0, 0.3, pivot=(0.0, 0.0, 0.0)),),
        planes=((0.0, 1.0, 0.0, 0.33),),
        pivots=((0.0, 0.0, 0.0),),
    )
    out = animate(np.stack([traj, traj[::-1]]), scene, tmp_path / "gyro.gif", dt=0.02)
    assert n_frames(out) == 12
    assert out.stat().st_size > 5_000


def test_scene_checks():
    scene = Scene(dim=2, circles=(Circle(4, 0.1, oriented=True),))
    with pytest.raises(ValueError, match=r"point indices \[4, 5\]"):
        scene.check(n_points=4, dim=2)
    with pytest.raises(ValueError, match="dim=3"):
        scene.check(n_points=6, dim=3)
    with pytest.raises(ValueError, match="2D elements"):
        Scene(dim=3, walls=BOX)
    with pytest.raises(ValueError, match="wall"):
        Scene(dim=2, walls=((0.0, 0.0, 1.0),))
    with pytest.raises(ValueError, match="shape"):
        animate(np.zeros((3, 5, 2)), Scene.points(5, 2), "unused.gif")


def test_plot_energy(tmp_path):
    E = np.cumsum(np.random.default_rng(0).normal(size=(3, 50)), axis=1)
    out = plot_energy(torch.from_numpy(E), 0.01, tmp_path / "energy.png", title="test")
    with Image.open(out) as im:
        assert im.format == "PNG"
    plot_energy(E[0], 0.01, tmp_path / "energy1.png")
    with pytest.raises(ValueError, match="E must have shape"):
        plot_energy(np.zeros((2, 3, 4)), 0.01, tmp_path / "bad.png")
    assert no_temp_files(tmp_path)


CONFIG_SCENES = [
    (
        {"type": "bouncing_masses", "radii": [0.1, 0.2], "walls": [list(w) for w in BOX]},
        2,
        lambda s: [c.point for c in s.circles] == [0, 1] and len(s.walls) == 4,
    ),
    (
        {"type": "bouncing_disks", "radii": [0.1, 0.2], "walls": [list(w) for w in BOX]},
        6,
        lambda s: [c.point for c in s.circles] == [0, 3] and all(c.oriented for c in s.circles),
    ),
    (
        {"type": "chain_pendulum", "link_lengths": [0.3, 0.4], "radii": [0.1, 0.2]},
        2,
        lambda s: s.chains[0].points == (0, 1) and s.chains[0].anchor == (0.0, 0.0),
    ),
    (
        {"type": "rope", "n_points": 5, "anchor": [0.0, 0.5]},
        5,
        lambda s: s.chains[0].style == "rope" and s.chains[0].anchor == (0.0, 0.5),
    ),
    (
        {"type": "gyroscope", "rim_radius": 0.3, "wall": [0, 1, 0, 0.33]},
        4,
        lambda s: s.disks3d[0].radius == 0.3 and s.planes == ((0.0, 1.0, 0.0, 0.33),),
    ),
]


@pytest.mark.parametrize(("cfg", "n_points", "ok"), CONFIG_SCENES)
def test_scene_from_config_dicts(cfg, n_points, ok):
    scene = scene_from_config(cfg)
    assert ok(scene)
    scene.check(n_points, scene.dim)


def test_scene_from_config_unknown_type():
    with pytest.raises(ValueError, match="unknown system type"):
        scene_from_config({"type": "trebuchet"})


def _tasks() -> list[str]:
    try:
        from diffcontact.systems import list_tasks
    except ImportError:
        return []
    return list_tasks()


@pytest.mark.parametrize("task", _tasks() or ["<no systems>"])
def test_scene_from_system_builtin(task):
    systems = pytest.importorskip("diffcontact.systems")
    system = systems.load_system(task)
    scene = scene_from_system(system)
    scene.check(system.n_points, system.dim)  # every index fits the state layout
    cfg = system.config
    if cfg.type in ("bouncing_masses", "bouncing_disks"):
        assert [c.radius for c in scene.circles] == list(cfg.radii)
        assert len(scene.walls) == len(cfg.walls)
        assert all(c.oriented == (cfg.type == "bouncing_disks") for c in scene.circles)
    elif cfg.type == "chain_pendulum":
        assert [c.radius for c in scene.circles] == list(cfg.radii)
        assert scene.walls == tuple(tuple(w) for w in cfg.walls)
        assert scene.chains[0].anchor == tuple(cfg.pivot)
    elif cfg.type == "rope":
        assert scene.chains[0].points == tuple(range(cfg.n_points))
    elif cfg.type == "gyroscope":
        assert scene.disks3d[0].radius == cfg.rim_radius
        assert scene.planes == (tuple(cfg.wall),)


def test_animate_simulated_bp5(tmp_path):
    systems = pytest.importorskip("diffcontact.systems")
    system = systems.load_system("BP5")
    traj = system.simulate(system.sample_initial_conditions(2, seed=0), steps=4)
    out = animate(traj, scene_from_system(system), tmp_path / "sim.gif", dt=system.dt)
    assert n_frames(out) == 5


def test_files_take_the_format_their_name_says(tmp_path):
    """``--energy-plot e.pdf`` had written PNG bytes under the .pdf name; ``animate`` to a
    .png wrote a GIF, ``render_frame`` to a .gif a PNG."""
    E = np.cumsum(np.random.default_rng(0).normal(size=(3, 50)), axis=1)
    assert (plot_energy(E, 0.01, tmp_path / "e.pdf")).read_bytes().startswith(b"%PDF")
    assert b"<svg" in (plot_energy(E, 0.01, tmp_path / "e.svg")).read_bytes()[:400]
    traj = bouncing_points(2, 10)
    scene = Scene(dim=2, circles=tuple(Circle(i, 0.05) for i in range(3)), walls=BOX)
    assert render_frame(traj, scene, tmp_path / "f.pdf").read_bytes().startswith(b"%PDF")
    for call, name in (
        (lambda p: animate(traj, scene, p), "a.png"),
        (lambda p: render_frame(traj, scene, p), "f.gif"),
        (lambda p: plot_energy(E, 0.01, p), "e.jpg"),
    ):
        with pytest.raises(ValueError, match="the file name must end in"):
            call(tmp_path / name)
        assert not (tmp_path / name).exists()
    (tmp_path / "d.gif").mkdir()
    with pytest.raises(ValueError, match="is a directory"):
        animate(traj, scene, tmp_path / "d.gif")


def test_bad_arguments_of_the_plots_are_named(tmp_path):
    traj = bouncing_points(2, 10)
    scene = Scene(dim=2, circles=tuple(Circle(i, 0.05) for i in range(3)), walls=BOX)
    E = np.ones((2, 5))
    cases = [
        (lambda: animate(traj[:0], scene, tmp_path / "a.gif"), "N = 0"),
        (lambda: animate(traj, scene, tmp_path / "a.gif", fps=0), "fps must be"),
        (lambda: animate(traj, scene, tmp_path / "a.gif", dpi=0), "dpi must be"),
        (lambda: animate(traj, scene, tmp_path / "a.gif", overlay=traj, labels=["a"]), "labels"),
        (lambda: render_frame(traj, scene, tmp_path / "f.png", frame=1000), "frame must be"),
        (lambda: plot_energy(E, 0.0, tmp_path / "e.png"), "dt must be"),
        (lambda: plot_energy(E, float("nan"), tmp_path / "e.png"), "dt must be"),
        (lambda: plot_energy(E[:0], 0.01, tmp_path / "e.png"), "N, T >= 1"),
        (lambda: plot_energy(E * np.nan, 0.01, tmp_path / "e.png"), "no finite value"),
        # a blank GIF, and NaN or negative steps in the titles, were accepted
        (lambda: animate(traj * np.nan, scene, tmp_path / "a.gif"), "no finite position"),
        (lambda: animate(traj, scene, tmp_path / "a.gif", dt=float("nan")), "dt must be"),
        (lambda: animate(traj, scene, tmp_path / "a.gif", dt=-1.0), "dt must be"),
        (lambda: animate(traj, scene, tmp_path / "a.gif", trail=-1), "trail must be"),
    ]
    for call, needle in cases:
        with pytest.raises(ValueError, match=needle):
            call()
    assert no_temp_files(tmp_path) and not list(tmp_path.iterdir())
    render_frame(traj, scene, tmp_path / "last.png", frame=-1)  # from the end
    # a missing folder named the hidden temporary file, not the path given
    missing = tmp_path / "nope" / "a.gif"
    with pytest.raises(FileNotFoundError) as err:
        animate(traj, scene, missing)
    assert err.value.filename == str(missing)


def test_a_diverging_overlay_does_not_set_the_axis_limits(tmp_path):
    """One prediction running off to x = 20 zoomed every panel out until the true bodies
    were dots in a corner: the limits come from traj and the scene."""
    from diffcontact.viz.animation import _build_figure

    traj = bouncing_points(2, 10)
    scene = Scene(dim=2, circles=tuple(Circle(i, 0.05) for i in range(3)), walls=BOX)
    far = traj.copy()
    far[:, :, 0, 0, 0] += np.linspace(0, 20, traj.shape[1])
    kw = dict(max_trajectories=4, max_frames=40, labels=None, trail=0, panel_size=3.2)
    plain, _, _ = _build_figure(traj, scene, overlay=None, **kw)
    with_far, _, _ = _build_figure(traj, scene, overlay=far, **kw)
    assert plain.axes[0].get_xlim() == with_far.axes[0].get_xlim()
    assert with_far.axes[0].get_xlim()[1] < 2


def test_non_finite_states_are_warned_about(tmp_path):
    """A body with NaN states vanished from the GIF without a word."""
    traj = bouncing_points(1, 10)
    traj[0, 5:, :, 1] = np.nan
    scene = Scene(dim=2, circles=tuple(Circle(i, 0.05) for i in range(3)), walls=BOX)
    with pytest.warns(RuntimeWarning, match="NaN or infinite positions"):
        animate(traj, scene, tmp_path / "nan.gif")


def test_a_plan_s_target_is_drawn_and_kept_in_view(tmp_path):
    """billiards.gif and throw.gif never showed the target: a cross (a point) and a dotted
    line (an x), inside the axis limits even where the bodies never get there."""
    from diffcontact.viz.animation import _limits_2d

    traj = bouncing_points(1, 10)[0]
    base = Scene(dim=2, circles=tuple(Circle(i, 0.05) for i in range(3)))
    x = traj[:, 0]
    far = Scene(dim=2, targets=((5.0, -3.0),), circles=base.circles)
    (_, x_hi), (y_lo, _) = _limits_2d([x], far)
    assert x_hi >= 5.0 and y_lo <= -3.0
    (x_lo, _), _ = _limits_2d([x], Scene(dim=2, target_x=(-4.0,), circles=base.circles))
    assert x_lo <= -4.0
    plain = render_frame(traj, base, tmp_path / "plain.png")
    marked = render_frame(
        traj, Scene(dim=2, circles=base.circles, targets=((0.5, 0.5),)), tmp_path / "cross.png"
    )
    a = np.asarray(Image.open(plain).convert("L"), dtype=float)
    b = np.asarray(Image.open(marked).convert("L"), dtype=float)
    assert a.shape == b.shape and (np.abs(a - b) > 100).sum() > 20  # a black cross
    with pytest.raises(ValueError, match="two finite numbers"):
        Scene(dim=2, targets=((0.5,),))
    with pytest.raises(ValueError, match="2D elements"):
        Scene(dim=3, target_x=(1.0,))


@pytest.mark.parametrize(
    ("data", "drawn", "shapes"),
    [
        ("BP5", "CP3", ((2, 5, 2), (2, 3, 2))),
        ("CP3", "BP5", ((2, 3, 2), (2, 5, 2))),
        ("BP5", "BD5", ((2, 5, 2), (2, 15, 2))),
        ("Gyro", "BP5", ((2, 4, 3), (2, 5, 2))),
    ],
)
def test_a_trajectory_of_another_system_is_refused(tmp_path, data, drawn, shapes):
    """BP5's five point masses animated with CP3's scene were drawn as a 3-link pendulum
    (its first three masses), without a word; the shapes are named now."""
    systems = pytest.importorskip("diffcontact.systems")
    system = systems.load_system(data)
    traj = system.simulate(system.sample_initial_conditions(2, seed=0), steps=3)
    scene = scene_from_system(systems.load_system(drawn))
    said = re.escape(
        f"trajectory states have shape {shapes[0]}, but the scene ({drawn}) draws a system "
        f"with states {shapes[1]}: the scene of another system"
    )
    with pytest.raises(ValueError, match=said):
        animate(traj, scene, tmp_path / "wrong.gif")
    with pytest.raises(ValueError, match=said):
        render_frame(traj, scene, tmp_path / "wrong.png")
    assert not (tmp_path / "wrong.gif").exists() and not (tmp_path / "wrong.png").exists()
    # the right pair is drawn
    animate(traj, scene_from_system(system), tmp_path / "right.gif", max_frames=2)
    assert n_frames(tmp_path / "right.gif") == 2


def test_a_scene_knows_its_systems_points():
    """``scene_from_config`` records the state points of its system (``Scene.n_points``);
    a hand-made scene without them accepts any trajectory whose points it refers to."""
    for cfg, n_points, _ in CONFIG_SCENES:
        assert scene_from_config(cfg).n_points == n_points
    scene = Scene(dim=2, circles=(Circle(0, 0.1),))
    scene.check(n_points=7, dim=2)
    with pytest.raises(ValueError, match=r"\(2, 7, 2\).*\(2, 1, 2\)"):
        dataclasses.replace(scene, n_points=1).check(n_points=7, dim=2)
    with pytest.raises(ValueError, match="n_points must be a positive integer"):
        Scene(dim=2, n_points=0)


def test_a_name_that_is_only_a_suffix_is_named_so(tmp_path):
    """``render_frame(..., 'v/.png')`` said "the file name must end in .png or .pdf or
    .svg" of a name that does (pathlib reads '.png' as a hidden file without a suffix)."""
    traj = bouncing_points(1, 5)
    scene = Scene(dim=2, circles=tuple(Circle(i, 0.05) for i in range(3)), walls=BOX)
    (tmp_path / "v").mkdir()
    for call, name in (
        (lambda p: render_frame(traj, scene, p), ".png"),
        (lambda p: animate(traj, scene, p), ".gif"),
        (lambda p: plot_energy(np.ones((1, 5)), 0.01, p), ".SVG"),
    ):
        path = tmp_path / "v" / name
        with pytest.raises(ValueError) as err:
            call(path)
        assert str(err.value) == f"{path}: '{name}' has no file name before its suffix"
    assert not list((tmp_path / "v").iterdir())


def test_frame_indices_of_no_state_is_an_error():
    """``frame_indices(0, 5)`` and ``frame_indices(-5, 5)`` returned no frame at all."""
    for n_steps in (0, -5):
        with pytest.raises(ValueError, match=f"n_steps must be >= 1, got {n_steps}"):
            frame_indices(n_steps, 5)
    assert frame_indices(1, 5).tolist() == [0]


def test_a_non_finite_overlay_is_warned_about(tmp_path):
    """A prediction that diverged at once (all NaN) was left out of the GIF without a
    word, its legend entry drawn all the same; NaN in traj was warned about."""
    import warnings

    traj = bouncing_points(2, 10)
    scene = Scene(dim=2, circles=tuple(Circle(i, 0.05) for i in range(3)), walls=BOX)
    with pytest.warns(RuntimeWarning, match="overlay holds no finite position in the traj"):
        animate(traj, scene, tmp_path / "nan.gif", overlay=traj * np.nan)
    partly = traj.copy()
    partly[1, 4:] = np.inf
    with pytest.warns(RuntimeWarning, match="overlay holds NaN or infinite positions"):
        render_frame(traj, scene, tmp_path / "nan.png", overlay=partly)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        animate(traj, scene, tmp_path / "fine.gif", overlay=traj)  # finite: nothing said
        # only the trajectories shown count
        animate(traj, scene, tmp_path / "one.gif", overlay=partly, max_trajectories=1)


def test_frames_of_too_many_pixels_are_refused_before_drawing(tmp_path):
    """``animate(..., dpi=100000)`` or ``panel_size=1000`` raised MemoryError
    (std::bad_alloc) from Agg."""
    from diffcontact.viz.animation import MAX_PIXELS, _build_figure

    traj = bouncing_points(16, 3)
    scene = Scene(dim=2, circles=tuple(Circle(i, 0.05) for i in range(3)), walls=BOX)
    E = np.ones((2, 5))
    cases = [
        (lambda: animate(traj, scene, tmp_path / "a.gif", dpi=100_000), "dpi 100000 and"),
        (lambda: animate(traj, scene, tmp_path / "a.gif", panel_size=10_000), "panel_size 10000"),
        (lambda: render_frame(traj, scene, tmp_path / "f.png", dpi=100_000), "dpi 100000 and"),
        (lambda: render_frame(traj, scene, tmp_path / "f.pdf", panel_size=10_000), "make"),
        (lambda: plot_energy(E, 0.01, tmp_path / "e.png", dpi=100_000), "dpi 100000 makes"),
    ]
    for call, needle in cases:
        with pytest.raises(ValueError, match=f"{needle}.* more than the {MAX_PIXELS} "):
            call()
    assert not list(tmp_path.iterdir())
    # a 4 x 4 grid of the default panels at 300 dpi fits (the figure only: not drawn)
    kw = dict(overlay=None, max_frames=3, labels=None, trail=0, panel_size=3.2)
    fig, _, _ = _build_figure(traj, scene, max_trajectories=16, dpi=300, **kw)
    assert np.prod(fig.get_size_inches() * 300) <= MAX_PIXELS
