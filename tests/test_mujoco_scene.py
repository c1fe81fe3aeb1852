"""The MuJoCo scene matched to BP5 and ``benchmarks/run.py simulate --compare mujoco``."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import diffcontact as dc

mujoco = pytest.importorskip("mujoco")

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import mujoco_scene  # noqa: E402
import simulate as simulate_bench  # noqa: E402


@pytest.fixture(scope="module")
def bp5():
    system = dc.load_system("BP5")
    return system, mujoco_scene.build_scene(system.config)


def test_model_matches_config(bp5):
    system, scene = bp5
    cfg, m = system.config, scene.model
    B = len(cfg.masses)
    body = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"body{i}") for i in range(B)]
    geom = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"ball{i}") for i in range(B)]
    np.testing.assert_array_equal(m.body_mass[body], cfg.masses)
    np.testing.assert_array_equal(m.geom_size[geom, 0], cfg.radii)
    assert m.opt.timestep == cfg.dt
    np.testing.assert_array_equal(m.opt.gravity, [0.0, -cfg.gravity, 0.0])
    # two slide joints per body, no rotation: qpos is (x, y) per body
    assert m.nq == m.nv == 2 * B
    assert set(m.jnt_type.tolist()) == {int(mujoco.mjtJoint.mjJNT_SLIDE)}
    # one pair per contact candidate, in our numbering through pair_ids
    assert m.npair == system.n_contacts
    mu = np.array(cfg.per_contact("mu"))
    np.testing.assert_array_equal(m.pair_friction[scene.pair_ids, 0], mu)
    np.testing.assert_array_equal(m.pair_dim[scene.pair_ids], np.where(mu > 0, 3, 1))
    names = [m.pair(int(i)).name for i in scene.pair_ids]
    assert names == [f"contact{k}" for k in range(system.n_contacts)]
    # damping from e_P: none for e_P = 1, more for smaller e_P
    cor = np.array(cfg.per_contact("cor"))
    damping = -m.pair_solref[scene.pair_ids, 1]
    assert damping[cor == 1.0].max() == 0.0
    assert np.all(np.diff(damping[:10]) < 0)  # BP5's pair e_P rises 0.1 ... 1.0
    # the geoms collide only through the explicit pairs
    assert not m.geom_contype.any() and not m.geom_conaffinity.any()


def test_walls_are_the_config_half_planes(bp5):
    system, scene = bp5
    m = scene.model
    for j, (a, b, c) in enumerate(system.config.walls):
        g = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"wall{j}")
        d = mujoco.MjData(m)
        mujoco.mj_forward(m, d)
        normal = d.geom_xmat[g].reshape(3, 3)[:, 2]
        norm = math.hypot(a, b)
        np.testing.assert_allclose(normal, [a / norm, b / norm, 0.0], atol=1e-12)
        # the plane's point lies on the line a x + b y + c = 0
        x, y, _ = d.geom_xpos[g]
        assert abs(a * x + b * y + c) < 1e-12


def test_initial_states_round_trip(bp5):
    system, scene = bp5
    z0 = system.sample_initial_conditions(3, seed=1)
    init = mujoco_scene.initial_states(scene, z0)
    d = mujoco.MjData(scene.model)
    mujoco.mj_setState(scene.model, d, init[2], mujoco.mjtState.mjSTATE_FULLPHYSICS.value)
    np.testing.assert_array_equal(d.qpos, z0[2, 0].reshape(-1).numpy())
    np.testing.assert_array_equal(d.qvel, z0[2, 1].reshape(-1).numpy())
    with pytest.raises(ValueError, match="shape"):
        mujoco_scene.initial_states(scene, z0[:, :, :3])


def test_free_flight_agrees(bp5):
    system, scene = bp5
    # well separated bodies, slow enough that nothing touches within 10 steps
    pos = torch.tensor([[0.15, 0.15], [0.8, 0.15], [0.2, 0.75], [0.75, 0.75], [0.5, 0.45]])
    vel = torch.tensor([[0.3, -0.2], [-0.4, 0.1], [0.2, 0.5], [0.1, 0.05], [0.6, -0.2]])
    z0 = torch.stack([pos, vel])[None].double()
    steps = 10
    traj = system.simulate(z0, steps=steps)
    assert (system.gaps(traj[:, :, 0]) > 0).all()
    init = mujoco_scene.initial_states(scene, z0)
    x_mj = mujoco_scene.positions(scene, init, mujoco_scene.rollout(scene, init, steps))
    assert x_mj.shape == (1, steps + 1, 5, 2)
    torch.testing.assert_close(x_mj, traj[:, :, 0], atol=1e-13, rtol=0)
    # one and two threads give the same states
    init4 = np.repeat(init, 4, axis=0)
    np.testing.assert_array_equal(
        mujoco_scene.rollout(scene, init4, 3), mujoco_scene.rollout(scene, init4, 3, nthread=2)
    )


@pytest.mark.parametrize("e", [0.5, 1.0])
def test_restitution_is_approximated(e):
    # one ball straight into one frictionless wall: MuJoCo's soft contact bounces back
    # with about e_P of the approach speed (approximately: the contact force cannot pull)
    cfg = dc.load_system("BP5").config.model_copy(
        update={"masses": [1.0], "radii": [0.1], "walls": [[1, 0, 0]], "mu": 0.0, "cor": e}
    )
    scene = mujoco_scene.build_scene(cfg)
    init = np.zeros((1, scene.nstate))
    init[0, scene.qpos_slice] = [0.3, 0.5]
    init[0, scene.qvel_slice] = [-1.0, 0.0]
    out = mujoco_scene.rollout(scene, init, 60)
    v_out = out[0, -1, scene.qvel_slice]
    assert v_out[0] > 0 and abs(v_out[0] - e) < 0.1
    assert v_out[1] == 0.0


def test_damping_ratio():
    assert mujoco_scene.damping_ratio(1.0) == 0.0
    assert mujoco_scene.damping_ratio(0.0) == 1.0
    zeta = mujoco_scene.damping_ratio(0.3)
    assert math.isclose(math.exp(-math.pi * zeta / math.sqrt(1 - zeta**2)), 0.3)
    with pytest.raises(ValueError, match="restitution"):
        mujoco_scene.damping_ratio(1.5)


def test_other_system_types_are_rejected():
    with pytest.raises(ValueError, match="bouncing_masses"):
        mujoco_scene.build_scene(dc.load_system("BD5").config)


def test_gravity_is_along_minus_y():
    cfg = dc.load_system("BP5").config.model_copy(update={"gravity": 9.81})
    m = mujoco_scene.build_scene(cfg).model
    np.testing.assert_array_equal(m.opt.gravity, [0.0, -9.81, 0.0])


def test_compare_entry_prints_ratios(capsys):
    status = simulate_bench.main(["--compare", "mujoco", "--n", "4", "--steps", "3"])
    assert status == 0
    out = capsys.readouterr().out
    assert "/ MuJoCo 1 thr" in out
    lines = out.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("---")) + 1
    rows = lines[start : start + 4]
    names = [line.split("|")[0].strip() for line in rows]
    assert names == [
        "diffcontact simulate",
        "diffcontact + gradient",
        "MuJoCo rollout 1 thr",
        "MuJoCo rollout 2 thr",
    ]
    ratios = [float(line.split("|")[-1]) for line in rows]
    assert all(r > 0 and math.isfinite(r) for r in ratios) and ratios[2] == 1.0
    assert "up to the first contact max" in out


def test_compare_sanity_numbers():
    r = simulate_bench.compare_mujoco(6, 4, "cpu", torch.float64)
    s = r["sanity"]
    assert s["free_max"] < 1e-12 and s["free_states"] >= 6
    assert s["threads_agree"]
    assert [row["ratio"] for row in r["rows"]][2] == 1.0


def test_missing_mujoco_is_a_clear_message(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "mujoco", None)
    assert simulate_bench.main(["--compare", "mujoco", "--n", "2", "--steps", "1"]) == 2
    assert "needs the `mujoco` package" in capsys.readouterr().err
    with pytest.raises(ImportError, match="pip install mujoco"):
        mujoco_scene.import_mujoco()
