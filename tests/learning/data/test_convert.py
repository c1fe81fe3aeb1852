"""Converters: positions only (finite differences, velocity jumps), generalised coordinates.

Each converter is checked on data made by the other side: trajectories simulated
by diffcontact, taken apart by hand (positions only; angles and angular
velocities), converted back and compared; and an exact event-driven bouncing
ball whose impacts fall between samples.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from diffcontact.cli import main
from diffcontact.learning.data.convert import (
    finite_difference_velocities,
    trajectories_from_coordinates,
    trajectories_from_positions,
    trajectory_checks,
    velocity_jumps,
)
from diffcontact.learning.data.format import load_dataset
from diffcontact.mechanics import quaternion_to_matrix
from diffcontact.systems import load_config, load_system

F64 = torch.float64


def _simulate(task: str, n: int, steps: int, seed: int = 0, **overrides) -> tuple:
    system = load_system(task, **overrides)
    z0 = system.sample_initial_conditions(n, seed=seed)
    return system, system.simulate(z0, steps, progress=False).numpy()


def _cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


# ------------------------------------------------------------------- finite differences
def test_finite_differences_exact_on_quadratics_and_differentiable():
    t = torch.arange(7, dtype=F64) * 0.1
    a = torch.tensor([1.0, -2.0], dtype=F64, requires_grad=True)
    b, c = torch.tensor([0.5, 3.0], dtype=F64), torch.tensor([-4.9, 1.0], dtype=F64)
    x = (a + b * t[:, None] + c * t[:, None] ** 2)[None, :, None]  # (1, 7, 1, 2)
    v = finite_difference_velocities(x, 0.1)
    assert isinstance(v, torch.Tensor) and v.dtype == F64
    want = (b + 2 * c * t[:, None])[None, :, None]
    assert torch.allclose(v, want, atol=1e-12)  # second order: exact for quadratics, ends too
    v.sum().backward()  # differentiable (the constant a drops out)
    assert torch.allclose(a.grad, torch.zeros(2, dtype=F64), atol=1e-9)
    vn = finite_difference_velocities(x.detach().numpy(), 0.1)
    assert isinstance(vn, np.ndarray) and np.allclose(vn, want.numpy(), atol=1e-12)


def test_positions_only_second_order_on_smooth_motion():
    """FD velocities of a simulated chain pendulum (ground out of reach) converge as dt^2."""
    errors = []
    for dt, steps in ((0.01, 20), (0.005, 40)):  # 0.2 s
        system, traj = _simulate("CP3", 3, steps, seed=2, dt=dt, walls=[[0.0, 1.0, 10.0]])
        z = trajectories_from_positions(traj[:, :, 0], config=system, on_jump="ignore")
        assert np.array_equal(z[:, :, 0], traj[:, :, 0])
        errors.append(
            (
                np.abs(z[:, 1:-1, 1] - traj[:, 1:-1, 1]).max(),  # central
                np.abs(z[:, [0, -1], 1] - traj[:, [0, -1], 1]).max(),  # one-sided ends
            )
        )
    (inner1, end1), (inner2, end2) = errors
    assert 3.5 < inner1 / inner2 < 4.5 and 3.5 < end1 / end2 < 4.5, errors
    assert inner1 < 0.01


def _bouncing_ball(T: int, dt: float, v0: float, x0: float, e: float) -> tuple:
    """Exact 1D ball between walls at 0 and 1 (coefficient e), sampled every dt; 2D with y
    moving uniformly. Returns positions (T, 1, 2), velocities, and the impact times."""
    xs, vs, impacts = [], [], []
    x, v, t = x0, v0, 0.0
    for k in range(T):
        target = k * dt
        while True:  # advance to the next impact or the sample
            wall = 1.0 if v > 0 else 0.0
            t_hit = t + (wall - x) / v if v != 0 else math.inf
            if t_hit > target:
                break
            x, t, v = wall, t_hit, -e * v
            impacts.append(t_hit)
        x, t = x + v * (target - t), target
        xs.append([x, 0.3 + 0.2 * target])
        vs.append([v, 0.2])
    return np.array(xs)[:, None], np.array(vs)[:, None], impacts


def test_velocity_jumps_find_impacts_between_samples():
    """Exact event-driven data: every impact falls between samples and is flagged."""
    dt, T = 0.01, 150
    cases = [_bouncing_ball(T, dt, v0, x0, 0.8) for v0, x0 in ((3.3, 0.5), (-4.1, 0.61))]
    x = np.stack([c[0] for c in cases])  # (2, T, 1, 2)
    v = np.stack([c[1] for c in cases])
    jumps = velocity_jumps(x, dt)
    for n, (_, _, impacts) in enumerate(cases):
        assert len(impacts) >= 3
        samples = {k for t in impacts for k in (math.floor(t / dt), math.ceil(t / dt))}
        flagged = set(np.flatnonzero(jumps.jump[n]).tolist())
        assert flagged <= samples  # no false flag
        for t in impacts:  # each impact flagged at a sample next to it
            if t / dt < T - 2:
                assert {math.floor(t / dt), math.ceil(t / dt)} & flagged
    with pytest.warns(RuntimeWarning, match="velocity jumps"):
        z = trajectories_from_positions(x, dt)
    ok = ~jumps.unreliable
    ok[:, -2:] = False  # the positions cannot show an impact in the last intervals
    assert np.abs(z[:, :, 1] - v)[ok].max() < 1e-9  # uniform motion: exact away from impacts
    assert np.abs(z[:, :, 1] - v)[jumps.unreliable].max() > 0.5  # blended across impacts
    with pytest.raises(ValueError, match="velocity jumps"):
        trajectories_from_positions(x, dt, on_jump="raise")


def test_velocity_jumps_on_simulated_impacts():
    """diffcontact's own BP5-e data: the impact states are all inside `unreliable`."""
    system, traj = _simulate("BP5-e", 4, 59, seed=1)
    x = torch.from_numpy(traj[:, :, 0])
    with torch.no_grad():
        contact = (system.gaps(x) < 0).any(-1).numpy()
    jumps = velocity_jumps(x, system.dt)
    assert isinstance(jumps.unreliable, torch.Tensor)
    unreliable = jumps.unreliable.numpy()
    inner = contact.copy()
    inner[:, -1] = False
    assert inner.sum() > 5 and (unreliable | ~inner).all()
    v = finite_difference_velocities(traj[:, :, 0], system.dt)
    ok = ~unreliable
    ok[:, -1] = False
    assert np.abs(v - traj[:, :, 1])[ok].max() < 1e-10


def test_positions_errors():
    with pytest.raises(ValueError, match=r"\(N, T, 5, 2\).*single trajectory"):
        trajectories_from_positions(np.zeros((10, 5, 2)), config="BP5")
    with pytest.raises(ValueError, match="differs from the config's dt"):
        trajectories_from_positions(np.zeros((1, 10, 5, 2)), 0.02, config="BP5")
    x = np.zeros((2, 10, 5, 2))
    x[1, 3, 0, 0] = np.nan
    with pytest.raises(ValueError, match="trajectory 1 sample 3"):
        trajectories_from_positions(x, config="BP5")
    with pytest.raises(ValueError, match="T >= 3"):
        trajectories_from_positions(np.zeros((1, 2, 5, 2)), config="BP5")
    with pytest.raises(ValueError, match="give dt"):
        trajectories_from_positions(np.zeros((1, 9, 5, 2)))


# ------------------------------------------------------------- generalised coordinates
def test_disks_round_trip():
    system, traj = _simulate("BD5", 3, 30)
    pts = traj.reshape(3, 31, 2, 5, 3, 2)
    c, ex = pts[:, :, 0, :, 0], pts[:, :, 0, :, 1] - pts[:, :, 0, :, 0]
    vc, vex = pts[:, :, 1, :, 0], pts[:, :, 1, :, 1] - pts[:, :, 1, :, 0]
    angle = np.arctan2(ex[..., 1], ex[..., 0])
    omega = _cross2(ex, vex)  # e_x' = w e_y, so w = e_x x e_x'
    q = np.concatenate([c, angle[..., None]], -1)
    qdot = np.concatenate([vc, omega[..., None]], -1)
    z = trajectories_from_coordinates("BD5", q, qdot)
    tol = 10 * trajectory_checks(system, traj)["constraint_residual"] + 1e-12
    assert np.abs(z - traj).max() < tol
    assert trajectory_checks(system, z)["constraint_residual"] < 1e-14


def test_chain_round_trip_and_finite_differences():
    system, traj = _simulate("CP3", 3, 40, seed=3, walls=[[0.0, 1.0, 10.0]])
    x, v = traj[:, :, 0], traj[:, :, 1]
    prev = np.concatenate([np.zeros_like(x[:, :, :1]), x[:, :, :-1]], 2)
    vprev = np.concatenate([np.zeros_like(v[:, :, :1]), v[:, :, :-1]], 2)
    link, dlink = x - prev, v - vprev
    q = np.arctan2(link[..., 0], -link[..., 1])  # x_i - x_{i-1} = l (sin q, -cos q)
    qdot = _cross2(link, dlink) / (link**2).sum(-1)
    z = trajectories_from_coordinates("CP3", torch.from_numpy(q), torch.from_numpy(qdot))
    assert isinstance(z, torch.Tensor)
    checks = trajectory_checks(system, traj)  # the simulation drifts off the constraints
    tol = 10 * (checks["constraint_residual"] + checks["velocity_constraint_residual"])
    assert np.abs(z.numpy() - traj).max() < tol
    # qdot omitted: finite differences of the unwrapped angles (wrap them on purpose)
    wrapped = np.remainder(q + np.pi, 2 * np.pi) - np.pi
    zf = trajectories_from_coordinates(system, wrapped, on_jump="ignore")
    assert np.abs(zf[:, :, 0] - z.numpy()[:, :, 0]).max() < 1e-12
    assert np.abs(zf[:, :, 1] - traj[:, :, 1]).max() < 0.1


def _quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) of rotation matrices (..., 3, 3), by hand."""
    w = np.sqrt(np.maximum(0.0, 1 + np.trace(R, axis1=-2, axis2=-1))) / 2
    x = np.sqrt(np.maximum(0.0, 1 + R[..., 0, 0] - R[..., 1, 1] - R[..., 2, 2])) / 2
    y = np.sqrt(np.maximum(0.0, 1 - R[..., 0, 0] + R[..., 1, 1] - R[..., 2, 2])) / 2
    z = np.sqrt(np.maximum(0.0, 1 - R[..., 0, 0] - R[..., 1, 1] + R[..., 2, 2])) / 2
    x = np.copysign(x, R[..., 2, 1] - R[..., 1, 2])
    y = np.copysign(y, R[..., 0, 2] - R[..., 2, 0])
    z = np.copysign(z, R[..., 1, 0] - R[..., 0, 1])
    return np.stack([w, x, y, z], -1)


def test_gyroscope_round_trip_matrix_quaternion_body_frame():
    system, traj = _simulate("Gyro", 2, 30, seed=1, wall=[0.0, 1.0, 0.0, 5.0])  # no contact
    x, v = traj[:, :, 0], traj[:, :, 1]
    axes = x[:, :, 1:] - x[:, :, :1]  # (N, T, 3, 3) rows: body axes
    U, _, Vt = np.linalg.svd(np.swapaxes(axes, -1, -2))
    R = U @ Vt  # nearest rotation (the simulated axes drift from orthonormal ~1e-4)
    dax = v[:, :, 1:] - v[:, :, :1]
    omega = 0.5 * np.cross(axes, dax).sum(2)  # sum_k e_k x (w x e_k) = 2 w
    tol = 10 * trajectory_checks(system, traj)["constraint_residual"] + 1e-12
    for q in (R, _quaternion(R)):
        z = trajectories_from_coordinates("Gyro", q, omega)
        assert np.abs(z - traj).max() < tol
    body = np.einsum("ntji,ntj->nti", R, omega)  # R^T w
    zb = trajectories_from_coordinates("Gyro", R, body, omega_frame="body")
    assert np.abs(zb - traj).max() < tol
    zf = trajectories_from_coordinates("Gyro", _quaternion(R), on_jump="ignore")
    smooth = np.abs(zf[:, 1:-1, 1] - traj[:, 1:-1, 1]).max()
    assert smooth < 0.2  # omega from dR/dt R^T (dt = 0.02, spin ~10 rad/s)


def test_rates_in_the_wrong_frame_are_warned():
    """A spinning gyroscope's body-frame rates read as world-frame ones (and an orientation
    whose motion is not the rates', as the own-data page once had): the point velocities
    do not move the points, which the constraint residual cannot see."""
    system, traj = _simulate("Gyro", 2, 30, seed=1, wall=[0.0, 1.0, 0.0, 5.0])
    x, v = traj[:, :, 0], traj[:, :, 1]
    axes = x[:, :, 1:] - x[:, :, :1]
    U, _, Vt = np.linalg.svd(np.swapaxes(axes, -1, -2))
    R = U @ Vt
    omega = 0.5 * np.cross(axes, v[:, :, 1:] - v[:, :, :1]).sum(2)
    body = np.einsum("ntji,ntj->nti", R, omega)
    good = trajectories_from_coordinates("Gyro", R, body, omega_frame="body")  # no warning
    assert trajectory_checks(system, good)["velocity_mismatch"] < 0.05
    with pytest.warns(RuntimeWarning, match=r"do not match the motion of q.*omega_frame"):
        bad = trajectories_from_coordinates("Gyro", R, body)  # body rates read as world
    checks = trajectory_checks(system, bad)
    assert checks["velocity_mismatch"] > 0.25 and checks["velocity_constraint_residual"] < 1e-9


def test_quaternion_to_matrix_matches_axis_angle():
    gen = torch.Generator().manual_seed(0)
    axis = torch.nn.functional.normalize(torch.randn(5, 3, generator=gen, dtype=F64), dim=-1)
    angle = torch.rand(5, generator=gen, dtype=F64) * 6
    q = torch.cat([torch.cos(angle / 2)[:, None], torch.sin(angle / 2)[:, None] * axis], -1)
    K = torch.zeros(5, 3, 3, dtype=F64)
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    K = K - K.transpose(1, 2)
    s, c = torch.sin(angle)[:, None, None], torch.cos(angle)[:, None, None]
    want = torch.eye(3, dtype=F64) + s * K + (1 - c) * K @ K
    assert torch.allclose(quaternion_to_matrix(q), want, atol=1e-14)
    assert torch.allclose(quaternion_to_matrix(-3 * q), want, atol=1e-14)


def test_coordinates_errors():
    with pytest.raises(ValueError, match=r"q must have shape \(N, T, 5, 3\)"):
        trajectories_from_coordinates("BD5", np.zeros((1, 4, 5, 2)), np.zeros((1, 4, 5, 3)))
    with pytest.raises(ValueError, match="same trajectories"):
        trajectories_from_coordinates("CP3", np.zeros((1, 4, 3)), np.zeros((1, 5, 3)))
    with pytest.raises(ValueError, match="unit norm"):
        trajectories_from_coordinates("Gyro", np.ones((1, 4, 4)), np.zeros((1, 4, 3)))
    with pytest.raises(ValueError, match="rotation matrices"):
        trajectories_from_coordinates("Gyro", 2 * np.ones((1, 4, 3, 3)), np.zeros((1, 4, 3)))
    with pytest.raises(ValueError, match="omega_frame"):
        trajectories_from_coordinates("Gyro", np.ones((1, 4, 4)), omega_frame="local")
    # a chain pendulum has no angular velocity to be in a body frame (it was ignored)
    with pytest.raises(ValueError, match="omega_frame='body' applies to a gyroscope's"):
        trajectories_from_coordinates("CP3", np.zeros((1, 4, 3)), np.zeros((1, 4, 3)),
                                      omega_frame="body")  # fmt: skip


def test_trajectory_checks_see_wrong_geometry():
    system, traj = _simulate("CP3", 2, 20, seed=0)
    good = trajectory_checks(system, traj)
    assert good["constraint_residual"] < 1e-3 and good["min_gap"] > -0.1
    cfg = load_config("CP3").model_dump(mode="json")
    cfg["link_lengths"] = [0.3, 0.4, 0.35]  # the data's first link is 0.35 long
    bad = trajectory_checks(cfg, traj)
    assert bad["constraint_residual"] > 0.01


# ----------------------------------------------------------------------------- CLI
def test_convert_cli_positions_then_generate(tmp_path, capsys):
    system, traj = _simulate("BP5", 6, 29, seed=0, horizon=0.3)
    raw = tmp_path / "positions.npz"
    np.savez(raw, x=traj[:, :, 0], dt=0.01)
    out = tmp_path / "converted.npz"
    cfg = tmp_path / "bp5.json"
    import json

    cfg.write_text(json.dumps(system.config.model_dump(mode="json")))
    assert main(["convert", "positions", str(raw), "--config", str(cfg), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "velocity_unreliable" in text and "checks:" in text and "next:" in text
    with np.load(out) as data:
        assert data["traj"].shape == (6, 30, 2, 5, 2)
        assert data["velocity_unreliable"].shape == (6, 30)
        unreliable = data["velocity_unreliable"]
        ok = ~unreliable
        ok[:, -1] = False
        assert np.abs(data["traj"][:, :, 1] - traj[:, :, 1])[ok].max() < 1e-10
    assert main(["convert", "positions", str(raw), "--config", str(cfg), "--out", str(out)]) == 2
    assert "exists" in capsys.readouterr().err
    # --quiet: no summary, and a warning as one line on stderr (it was Python's, with a
    # source line)
    quiet = tmp_path / "quiet.npz"
    argv = ["convert", "positions", str(raw), "--config", str(cfg), "--out", str(quiet)]
    assert main([*argv, "--quiet"]) == 0
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert captured.out == "" and len(lines) == 1, captured
    assert lines[0].startswith("diffcontact convert: warning: velocities by finite differences")
    # positions in millimetres: every state "in contact", which the checks show: warned
    mm = tmp_path / "mm.npz"
    np.savez(mm, x=traj[:, :, 0] * 1000, dt=0.01)
    argv = ["convert", "positions", str(mm), "--config", str(cfg), "--out", str(tmp_path / "m.npz")]
    assert main(argv) == 0
    assert "warning: 100% of the states are in contact" in capsys.readouterr().out
    # an --out in a missing folder: named up front (exit 1 and a temporary file's name before)
    missing = tmp_path / "nowhere" / "c.npz"
    assert (
        main(["convert", "positions", str(raw), "--config", str(cfg), "--out", str(missing)]) == 2
    )
    err = capsys.readouterr().err
    assert f"folder {missing.parent} does not exist" in err and ".tmp-" not in err
    data_dir = tmp_path / "data"
    assert main(["generate", "--from-arrays", str(out), "--out", str(data_dir), "--quiet"]) == 0
    assert load_dataset(data_dir).counts["train"] == 4


def test_convert_cli_errors(tmp_path, capsys):
    raw = tmp_path / "q.npz"
    np.savez(raw, qdot=np.zeros((1, 5, 3)))
    out = str(tmp_path / "o.npz")
    assert main(["convert", "coordinates", str(raw), "--config", "CP3", "--out", out]) == 2
    assert "no array named 'q'" in capsys.readouterr().err
    assert main(["convert", "mujoco", str(raw), "--config", "CP3", "--out", out]) == 2
    assert "--model" in capsys.readouterr().err
    assert main(["convert", "positions", str(raw), "--config", "CP3", "--out", out,
                 "--plane", "xz"]) == 2  # fmt: skip
    assert "only to SOURCE mujoco" in capsys.readouterr().err
    # options that did nothing for the source or the file were ignored silently
    both = tmp_path / "qq.npz"
    np.savez(both, q=np.zeros((1, 5, 3)), qdot=np.zeros((1, 5, 3)))
    for source, path, extra, said in (
        ("positions", raw, ["--omega-frame", "body"], "--omega-frame applies only to SOURCE "
         "coordinates"),
        ("positions", raw, ["--omega-frame", "world"], "--omega-frame applies only to SOURCE "
         "coordinates"),  # the default value, given: accepted and ignored before
        ("positions", raw, ["--axes", "body"], "--axes applies only to SOURCE mujoco"),
        ("coordinates", raw, ["--axes", "inertial"], "--axes applies only to SOURCE mujoco"),
        ("mujoco", raw, ["--model", "m.xml", "--threshold", "5"], "--threshold applies only"),
        ("coordinates", both, ["--threshold", "5"], "--threshold is not used: "),
    ):  # fmt: skip
        argv = ["convert", source, str(path), "--config", "CP3", "--out", out, *extra]
        assert main(argv) == 2
        assert said in capsys.readouterr().err
    (tmp_path / "bad.npz").write_bytes(b"PK\x03\x04 truncated")
    assert main(["convert", "positions", str(tmp_path / "bad.npz"), "--config", "CP3",
                 "--out", out]) == 2  # fmt: skip
    assert "cannot read" in capsys.readouterr().err


def test_recordings_of_no_sample_are_named_and_nothing_is_written(tmp_path, capsys):
    """``q``, ``qdot`` of shape ``(N, 0, ...)`` gave exit 1 "RuntimeError: max(): Expected
    reduction dim ..." (from the checks after the conversion), and the output was written."""
    with pytest.raises(ValueError, match=r"q needs T >= 1 sample per trajectory; got 0 \(shape "
                       r"\(2, 0, 5, 2\)\)"):  # fmt: skip
        trajectories_from_coordinates("BP5", np.zeros((2, 0, 5, 2)), np.zeros((2, 0, 5, 2)))
    with pytest.raises(ValueError, match=r"q needs T >= 1 sample per trajectory; got 0"):
        trajectories_from_coordinates("Gyro", np.zeros((2, 0, 4)), np.zeros((2, 0, 3)))
    with pytest.raises(ValueError, match=r"q holds no trajectory \(shape \(0, 5, 4\)\)"):
        trajectories_from_coordinates("Gyro", np.zeros((0, 5, 4)), np.zeros((0, 5, 3)))
    with pytest.raises(ValueError, match=r"finite differences \(qdot=None\) need T >= 3 samples "
                       r"per trajectory; got 2"):  # fmt: skip
        trajectories_from_coordinates("CP3", np.zeros((1, 2, 3)))
    with pytest.raises(ValueError, match=r"trajectories hold no state \(shape \(2, 0, 2, 5, 2\)\)"):
        trajectory_checks("BP5", np.zeros((2, 0, 2, 5, 2)))
    out = tmp_path / "o.npz"
    for config, q, qdot in (
        ("BP5", np.zeros((2, 0, 5, 2)), np.zeros((2, 0, 5, 2))),
        ("Gyro", np.zeros((2, 0, 4)), np.zeros((2, 0, 3))),
    ):
        np.savez(tmp_path / "q.npz", q=q, qdot=qdot)
        argv = ["convert", "coordinates", str(tmp_path / "q.npz"), "--config", config]
        assert main([*argv, "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert "error: q needs T >= 1 sample per trajectory; got 0" in err, err
        assert not out.exists()


def test_convert_says_what_to_fix_when_generate_would_refuse_the_file(tmp_path, capsys):
    """After warning that ``generate --from-arrays`` refuses the data (positions off the
    config's constraints), ``convert`` advised "next: diffcontact generate ..."."""
    _, traj = _simulate("CP3", 2, 19, seed=0, horizon=0.2)
    np.savez(tmp_path / "x.npz", x=traj[:, :, 0] + np.array([0.0, 0.6]), dt=0.01)
    out = tmp_path / "o.npz"
    assert main(["convert", "positions", str(tmp_path / "x.npz"), "--config", "CP3", "--out",
                 str(out)]) == 0  # fmt: skip
    text = capsys.readouterr().out
    assert "break the config's equality constraints" in text and "refuses such data" in text
    assert "next: diffcontact generate" not in text
    assert "next: fix the config (link lengths, pivot, axis points) or the data's origin or " in (
        text
    )
    assert main(["generate", "--from-arrays", str(out), "--out", str(tmp_path / "d")]) == 2
    assert "break the config's equality constraints" in capsys.readouterr().err
