"""MuJoCo qpos/qvel to diffcontact trajectories, checked against MuJoCo's own kinematics.

Scenes are stepped with MuJoCo; the converted points are compared with an
independent computation from MuJoCo's ``xipos``/``ximat``/``site_xpos`` and
``mj_objectVelocity``, their velocities with finite differences of their
positions, and rigid distances must stay constant.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from diffcontact.cli import main
from diffcontact.learning.data.convert import finite_difference_velocities, trajectory_checks
from diffcontact.systems import load_config

# a free box, a hinge-slide-hinge-ball chain, in 3D
SCENE_3D = """
<mujoco>
  <option timestep="0.001" integrator="RK4" gravity="0 0 -9.81"/>
  <worldbody>
    <body name="box" pos="0.3 -0.2 1.0" euler="10 20 30">
      <freejoint/>
      <geom type="box" size=".1 .2 .05" pos=".02 .01 0" euler="5 0 0"/>
      <geom type="sphere" size=".05" pos="0.1 0 0.1"/>
    </body>
    <body name="l1" pos="0 1 2" euler="0 0 20">
      <joint type="hinge" axis="0 1 0" pos="0 0 0.1" ref="0.2"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.5" size=".03"/>
      <body name="l2" pos="0 0 -0.5" quat="0.9 0.1 0.2 0.1">
        <joint type="slide" axis="1 0 0.3"/>
        <joint type="hinge" axis="0.2 1 0" pos="0.05 0 0"/>
        <geom type="capsule" fromto="0 0 0 0.1 0 -0.4" size=".03"/>
        <body name="l3" pos="0 0 -0.4">
          <joint type="ball" pos="0 0.02 0"/>
          <geom type="box" size=".05 .08 .1" pos="0 0 -0.1"/>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>"""

# planar: two disks (slide x, slide z, hinge y) and a two-link pendulum with tip sites;
# no collisions (smooth motion)
SCENE_2D = """
<mujoco>
  <option timestep="0.001" integrator="RK4" gravity="0 0 -9.81"/>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    <body name="d1" pos="0.3 0 0.5">
      <joint type="slide" axis="1 0 0"/><joint type="slide" axis="0 0 1"/>
      <joint type="hinge" axis="0 1 0"/>
      <geom type="cylinder" size=".1 .02" euler="90 0 0" mass="0.2"/>
    </body>
    <body name="d2" pos="0.7 0 0.5" euler="0 30 0">
      <joint type="slide" axis="1 0 0"/><joint type="slide" axis="0 0 1"/>
      <joint type="hinge" axis="0 1 0"/>
      <geom type="cylinder" size=".12 .02" euler="90 0 0" mass="0.3"/>
    </body>
    <body name="a" pos="2 0 1">
      <joint type="hinge" axis="0 1 0"/>
      <geom type="sphere" size=".05" pos="0 0 -0.4" mass="0.1"/>
      <site name="tip_a" pos="0 0 -0.4"/>
      <body name="b" pos="0 0 -0.4">
        <joint type="hinge" axis="0 1 0"/>
        <geom type="sphere" size=".05" pos="0 0 -0.3" mass="0.1"/>
        <site name="tip_b" pos="0 0 -0.3"/>
      </body>
    </body>
  </worldbody>
</mujoco>"""

DISKS = {
    "type": "bouncing_disks", "name": "two-disks", "masses": [0.2, 0.3], "radii": [0.1, 0.12],
    "walls": [[0, 1, 5]], "dt": 0.005, "horizon": 1.0, "gravity": 9.81,
}  # fmt: skip
CHAIN = {
    "type": "chain_pendulum", "name": "chain-2", "masses": [0.1, 0.1],
    "link_lengths": [0.4, 0.3], "radii": [0.05, 0.05], "walls": [[0, 1, 5]],
    "dt": 0.005, "horizon": 1.0, "gravity": 9.81,
}  # fmt: skip


def _record(mujoco, xml: str, n: int, T: int, every: int, seed: int) -> dict:
    """Step a scene from random states; record qpos, qvel and MuJoCo's own body data."""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(seed)
    out: dict[str, list] = {k: [] for k in ("qpos", "qvel", "xipos", "ximat", "xmat", "site",
                                            "vel")}  # fmt: skip
    for _ in range(n):
        mujoco.mj_resetData(m, d)
        d.qpos[:] = m.qpos0 + 0.4 * rng.standard_normal(m.nq)
        mujoco.mj_normalizeQuat(m, d.qpos)
        d.qvel[:] = 1.5 * rng.standard_normal(m.nv)
        rows: dict[str, list] = {k: [] for k in out}
        for _ in range(T):
            mujoco.mj_forward(m, d)
            rows["qpos"].append(d.qpos.copy())
            rows["qvel"].append(d.qvel.copy())
            rows["xipos"].append(d.xipos.copy())
            rows["ximat"].append(d.ximat.reshape(-1, 3, 3).copy())
            rows["xmat"].append(d.xmat.reshape(-1, 3, 3).copy())
            rows["site"].append(d.site_xpos.copy())
            vel = np.zeros((m.nbody, 6))
            for b in range(m.nbody):  # (angular, linear) at the centre of mass, world frame
                mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_BODY, b, vel[b], 0)
            rows["vel"].append(vel)
            for _ in range(every):
                mujoco.mj_step(m, d)
        for k in out:
            out[k].append(np.array(rows[k]))
    rec = {k: np.array(v) for k, v in out.items()}
    rec["model"] = m
    return rec


# (recorded every 0.005 s, converted with Gyro's dt of 0.02: the velocity check says so)
@pytest.mark.filterwarnings("ignore:the velocities from qvel do not match:RuntimeWarning")
def test_mujoco_3d_bodies_match_mujoco_kinematics():
    mujoco = pytest.importorskip("mujoco")
    from diffcontact.learning.data.mujoco import trajectories_from_mujoco

    rec = _record(mujoco, SCENE_3D, n=2, T=12, every=5, seed=0)
    m = rec["model"]
    for name in ("box", "l1", "l2", "l3"):  # free; hinge; slide + hinge; ball under all
        b = m.body(name).id
        for axes, frame in (("inertial", rec["ximat"]), ("body", rec["xmat"])):
            z = trajectories_from_mujoco(m, rec["qpos"], rec["qvel"], "Gyro", bodies=[name],
                                         axes=axes)  # fmt: skip
            assert z.shape == (2, 12, 2, 4, 3)
            c = rec["xipos"][:, :, b]
            want_x = np.concatenate([c[:, :, None], c[:, :, None] + np.swapaxes(
                frame[:, :, b], -1, -2)], axis=2)  # fmt: skip
            assert np.abs(z[:, :, 0] - want_x).max() < 1e-12, name
            w, v = rec["vel"][:, :, b, :3], rec["vel"][:, :, b, 3:]
            want_v = v[:, :, None] + np.cross(w[:, :, None], want_x - c[:, :, None])
            assert np.abs(z[:, :, 1] - want_v).max() < 1e-12, name
            # rigid: the axis points stay unit length and orthogonal
            e = z[:, :, 0, 1:] - z[:, :, 0, :1]
            gram = np.einsum("ntid,ntjd->ntij", e, e)
            assert np.abs(gram - np.eye(3)).max() < 1e-12


def test_mujoco_planar_disks_and_chain_sites():
    mujoco = pytest.importorskip("mujoco")
    from diffcontact.learning.data.mujoco import trajectories_from_mujoco

    rec = _record(mujoco, SCENE_2D, n=2, T=40, every=5, seed=1)  # samples 0.005 s apart
    m, qpos, qvel = rec["model"], rec["qpos"], rec["qvel"]
    z = trajectories_from_mujoco(m, qpos, qvel, DISKS, bodies=["d1", "d2"], plane="xz")
    assert z.shape == (2, 40, 2, 6, 2)
    for k, name in enumerate(("d1", "d2")):  # centres: MuJoCo's xipos, x and z
        got = z[:, :, 0, 3 * k]
        assert np.abs(got - rec["xipos"][:, :, m.body(name).id][..., [0, 2]]).max() < 1e-12
    checks = trajectory_checks(DISKS, z)  # rigid bodies: unit orthogonal axes, exactly
    assert checks["constraint_residual"] < 1e-12 and checks["velocity_constraint_residual"] < 1e-12
    # positions against velocities: finite differences agree to O(dt^2)
    fd = finite_difference_velocities(z[:, :, 0], 0.005)
    scale = np.abs(z[:, :, 1]).max()
    assert np.abs(fd[:, 1:-1] - z[:, 1:-1, 1]).max() < 1e-3 * scale

    zc = trajectories_from_mujoco(m, qpos, qvel, CHAIN, bodies=["site:tip_a", "site:tip_b"],
                                  plane="xz", origin=[2.0, 0.0, 1.0])  # fmt: skip
    tips = rec["site"][:, :, [m.site("tip_a").id, m.site("tip_b").id]][..., [0, 2]]
    assert np.abs(zc[:, :, 0] - (tips - np.array([2.0, 1.0]))).max() < 1e-12
    checks = trajectory_checks(CHAIN, zc)  # link lengths 0.4 and 0.3 from the pivot
    assert checks["constraint_residual"] < 1e-12 and checks["velocity_constraint_residual"] < 1e-12
    # independently: absolute link angles from the hinge angles (a hinge about +y turns
    # (0, 0, -l) to l (-sin h, -cos h) in the (x, z) plane: diffcontact's angle is -h)
    from diffcontact.learning.data.convert import trajectories_from_coordinates

    a = -qpos[..., 6:8].cumsum(-1)
    a_dot = -qvel[..., 6:8].cumsum(-1)
    want = trajectories_from_coordinates(CHAIN, a, a_dot)
    assert np.abs(zc - want).max() < 1e-12


def test_mujoco_velocities_that_are_not_the_positions_motion_are_warned():
    """qvel in other units (or a recording at another step than the config's dt) showed
    only as a number in convert's checks line, where convert coordinates warns."""
    import warnings

    mujoco = pytest.importorskip("mujoco")
    from diffcontact.learning.data.mujoco import trajectories_from_mujoco

    rec = _record(mujoco, SCENE_2D, n=2, T=40, every=5, seed=1)  # samples 0.005 s apart
    m, qpos, qvel = rec["model"], rec["qpos"], rec["qvel"]
    args = {"bodies": ["d1", "d2"], "plane": "xz"}
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        trajectories_from_mujoco(m, qpos, qvel, DISKS, **args)
    with pytest.warns(RuntimeWarning, match=r"the velocities from qvel do not match the "
                      r"motion of qpos: .* by \d+\.\d\d of the median speed"):  # fmt: skip
        trajectories_from_mujoco(m, qpos, 1000 * qvel, DISKS, **args)


# (a body at rest given a velocity: the velocity check says so)
@pytest.mark.filterwarnings("ignore:the velocities from qvel do not match:RuntimeWarning")
def test_mujoco_errors_and_out_of_plane_warning(tmp_path):
    mujoco = pytest.importorskip("mujoco")
    from diffcontact.learning.data.mujoco import trajectories_from_mujoco

    m = mujoco.MjModel.from_xml_string(SCENE_2D)
    q, v = np.tile(m.qpos0, (1, 9, 1)), np.zeros((1, 9, m.nv))
    with pytest.raises(ValueError, match=r"2 bodies but 4 MuJoCo bodies.*'d1'"):
        trajectories_from_mujoco(m, q, v, DISKS, plane="xz")
    with pytest.raises(ValueError, match="no body 'nope'"):
        trajectories_from_mujoco(m, q, v, DISKS, bodies=["d1", "nope"], plane="xz")
    with pytest.raises(ValueError, match="needs plane"):
        trajectories_from_mujoco(m, q, v, DISKS, bodies=["d1", "d2"])
    with pytest.raises(ValueError, match="a site gives one point"):
        trajectories_from_mujoco(m, q, v, DISKS, bodies=["d1", "site:tip_a"], plane="xz")
    with pytest.raises(ValueError, match="rotate about that normal"):
        trajectories_from_mujoco(m, q, v, DISKS, bodies=["d1", "d2"], plane="xy")
    with pytest.raises(ValueError, match=r"qpos must have shape \(N, T, 8\)"):
        trajectories_from_mujoco(m, q[..., :5], v, DISKS, bodies=["d1", "d2"], plane="xz")
    mocap = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><body name="m" mocap="true"><geom size=".1"/></body>'
        '<body name="f"><freejoint/><geom size=".1"/></body></worldbody></mujoco>'
    )
    qm, vm = np.tile(mocap.qpos0, (1, 9, 1)), np.zeros((1, 9, mocap.nv))
    with pytest.raises(ValueError, match="mocap body"):
        trajectories_from_mujoco(mocap, qm, vm, "Gyro", bodies=["m"])
    vm[..., 0] = 1.0  # the free body moves along x; y projected away
    vm[..., 1] = 0.5
    cfg = {**CHAIN, "masses": [0.1], "link_lengths": [1.0], "radii": [0.1]}
    with pytest.warns(RuntimeWarning, match="out of the plane"):
        trajectories_from_mujoco(mocap, qm, vm, cfg, bodies=["f"], plane="xz")
    with pytest.raises(ValueError, match="does not exist"):
        trajectories_from_mujoco(tmp_path / "missing.xml", qm, vm, "Gyro")


def test_convert_cli_mujoco_then_generate(tmp_path, capsys):
    mujoco = pytest.importorskip("mujoco")
    rec = _record(mujoco, SCENE_2D, n=4, T=30, every=5, seed=2)
    xml = tmp_path / "scene.xml"
    xml.write_text(SCENE_2D)
    raw = tmp_path / "mj.npz"
    np.savez(raw, qpos=rec["qpos"], qvel=rec["qvel"], dt=0.005)
    cfg = tmp_path / "chain.json"
    cfg.write_text(json.dumps(load_config(CHAIN).model_dump(mode="json")))
    out = tmp_path / "chain.npz"
    argv = ["convert", "mujoco", str(raw), "--model", str(xml), "--config", str(cfg),
            "--out", str(out), "--bodies", "site:tip_a", "site:tip_b", "--plane", "xz",
            "--origin", "2", "0", "1"]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    assert "constraint_residual" in capsys.readouterr().out
    # a NaN origin wrote a file full of NaN with exit status 0
    bad = [*argv[:-3], "0", "0", "nan", "--force"]
    assert main(bad) == 2
    assert "--origin: must be a finite number, got nan" in capsys.readouterr().err
    data_dir = tmp_path / "data"
    assert main(["generate", "--from-arrays", str(out), "--out", str(data_dir), "--quiet",
                 "--val-fraction", "0.25", "--test-fraction", "0.25"]) == 0  # fmt: skip


def test_mujoco_recordings_of_no_sample_are_named(tmp_path, capsys):
    """``qpos``/``qvel`` of shape ``(2, 0, nq)`` gave exit 1 "RuntimeError: max(): Expected
    reduction dim ..." (from the out-of-plane check)."""
    mujoco = pytest.importorskip("mujoco")
    from diffcontact.learning.data.mujoco import trajectories_from_mujoco

    m = mujoco.MjModel.from_xml_string(SCENE_2D)
    q, v = np.zeros((2, 0, m.nq)), np.zeros((2, 0, m.nv))
    with pytest.raises(ValueError, match=rf"qpos needs T >= 1 sample per trajectory; got 0 "
                       rf"\(shape \(2, 0, {m.nq}\)\)"):  # fmt: skip
        trajectories_from_mujoco(m, q, v, DISKS, bodies=["d1", "d2"], plane="xz")
    xml = tmp_path / "scene.xml"
    xml.write_text(SCENE_2D)
    np.savez(tmp_path / "mj.npz", qpos=q, qvel=v)
    cfg = tmp_path / "chain.json"
    cfg.write_text(json.dumps(load_config(CHAIN).model_dump(mode="json")))
    out = tmp_path / "o.npz"
    assert main(["convert", "mujoco", str(tmp_path / "mj.npz"), "--model", str(xml), "--config",
                 str(cfg), "--out", str(out), "--bodies", "site:tip_a", "site:tip_b", "--plane",
                 "xz"]) == 2  # fmt: skip
    assert "error: qpos needs T >= 1 sample per trajectory; got 0" in capsys.readouterr().err
    assert not out.exists()


def test_mujoco_body_ids_and_a_body_given_twice(tmp_path, capsys):
    """``--bodies 1 2`` said "the model has no body '1' (its bodys: ...)"; ``--bodies d1 d1``
    mapped one MuJoCo body to two diffcontact bodies."""
    mujoco = pytest.importorskip("mujoco")
    from diffcontact.learning.data.mujoco import trajectories_from_mujoco

    rec = _record(mujoco, SCENE_2D, n=1, T=12, every=5, seed=3)
    m, q, v = rec["model"], rec["qpos"], rec["qvel"]
    by_name = trajectories_from_mujoco(m, q, v, DISKS, bodies=["d1", "d2"], plane="xz")
    for ids in ([1, 2], ["1", "2"], ["d1", "2"], [np.int64(1), "d2"]):
        z = trajectories_from_mujoco(m, q, v, DISKS, bodies=ids, plane="xz")
        assert np.array_equal(z, by_name), ids
    with pytest.raises(ValueError, match=r"no body 'nope' \(its bodies: 'world', 'd1'"):
        trajectories_from_mujoco(m, q, v, DISKS, bodies=["d1", "nope"], plane="xz")
    with pytest.raises(ValueError, match=r"no site 'x' \(its sites: 'tip_a', 'tip_b'\)"):
        trajectories_from_mujoco(m, q, v, CHAIN, bodies=["site:x", "site:tip_b"], plane="xz")
    for twice in (["d1", "d1"], ["d1", 1], ["1", "d1"]):
        with pytest.raises(
            ValueError, match=r"bodies\[0\] and bodies\[1\] are both MuJoCo body 'd1'"
        ):
            trajectories_from_mujoco(m, q, v, DISKS, bodies=twice, plane="xz")
    with pytest.raises(
        ValueError, match=r"bodies\[0\] and bodies\[1\] are both MuJoCo site 'tip_a'"
    ):
        trajectories_from_mujoco(m, q, v, CHAIN, bodies=["site:tip_a"] * 2, plane="xz")
    # a body whose name is digits wins over the id
    named = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><body name="2" pos="0 0 1"><freejoint/><geom size=".1"/></body>'
        '<body name="b" pos="1 2 3"><freejoint/><geom size=".1"/></body></worldbody></mujoco>'
    )
    qn, vn = np.tile(named.qpos0, (1, 3, 1)), np.zeros((1, 3, named.nv))
    point = {**CHAIN, "masses": [0.1], "link_lengths": [1.0], "radii": [0.1]}
    for spec, x in (("2", 0.0), (2, 1.0), ("1", 0.0)):
        z = trajectories_from_mujoco(named, qn, vn, point, bodies=[spec], plane="xz")
        assert z[0, 0, 0, 0, 0] == x, spec
    # the command line
    xml = tmp_path / "scene.xml"
    xml.write_text(SCENE_2D)
    raw = tmp_path / "mj.npz"
    np.savez(raw, qpos=q, qvel=v, dt=0.005)
    cfg = tmp_path / "disks.json"
    cfg.write_text(json.dumps(load_config(DISKS).model_dump(mode="json")))
    out = tmp_path / "disks.npz"
    argv = ["convert", "mujoco", str(raw), "--model", str(xml), "--config", str(cfg),
            "--out", str(out), "--plane", "xz", "--quiet", "--bodies"]  # fmt: skip
    assert main([*argv, "1", "2"]) == 0, capsys.readouterr().err
    assert np.array_equal(np.load(out)["traj"], by_name)
    capsys.readouterr()
    for twice in (["d1", "d1"], ["d1", "1"]):
        assert main([*argv, *twice, "--force"]) == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and "are both MuJoCo body 'd1'" in err[0], err
    assert main([*argv, "1", "7", "--force"]) == 2
    assert "bodies[1] = 7: MuJoCo body ids run from 1 to 4" in capsys.readouterr().err


def test_importing_diffcontact_does_not_import_mujoco():
    code = (
        "import sys, diffcontact, diffcontact.learning.data.mujoco, "
        "diffcontact.learning.data.convert\n"
        "from diffcontact.cli import build_parser; build_parser()\n"
        "assert 'mujoco' not in sys.modules, 'mujoco imported'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
