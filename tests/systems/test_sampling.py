"""Initial conditions: shapes, dtype, no contact, determinism, and the paper-facts.md layouts."""

import math

import pytest
import torch

import diffcontact as dc
from diffcontact.systems import list_tasks
from diffcontact.systems.initial_conditions import euler_zxz

TASKS = list_tasks()


@pytest.mark.parametrize("task", TASKS)
def test_sampling_shapes_validity_determinism(task):
    system = dc.load_system(task)
    z = system.sample_initial_conditions(16, seed=3)
    assert z.shape == (16, 2, system.n_points, system.dim)
    assert z.dtype == torch.float64 and bool(torch.isfinite(z).all())
    assert bool((system.gaps(z[:, 0]) > 0).all()), "sampled states must not be in contact"
    again = system.sample_initial_conditions(16, seed=3)
    assert torch.equal(z, again)  # same seed, same bytes
    other = system.sample_initial_conditions(16, seed=4)
    assert not torch.equal(z, other)
    # the first samples do not depend on how many are asked for
    assert torch.equal(system.sample_initial_conditions(4, seed=3), z[:4])
    if system.constraints is not None:
        x, v = z[:, 0], z[:, 1]
        assert float(system.constraints.phi(x).abs().max()) < 1e-12
        assert float(system.constraints.phi_dot(x, v).abs().max()) < 1e-12


def test_sample_argument_errors():
    system = dc.load_system("BP5-e")
    for n in (0, -1, 2.5):
        with pytest.raises(ValueError, match="positive integer"):
            system.sample_initial_conditions(n)


def test_impossible_box_is_reported():
    system = dc.load_system(
        "BP5-e", initial_conditions={"position_low": [0.0, 0.0], "position_high": [0.05, 0.05]}
    )
    with pytest.raises(ValueError, match="could only draw 0 of 2 valid initial conditions"):
        system.sample_initial_conditions(2)  # five balls of radius 0.1 in a 0.05 box


def test_a_config_whose_draws_all_touch_names_the_contact():
    """A chain pivot below its ground loads, and sampling only said "widen the box or make
    the bodies smaller": the error names the contact the draws run into."""
    system = dc.load_system("CP3", pivot=[0.0, -2.0])
    with pytest.raises(ValueError, match=r"most often closed in the draws is 'joint 0 pen"):
        system.sample_initial_conditions(2)


def test_bouncing_distributions():
    system = dc.load_system("BP5")
    z = system.sample_initial_conditions(1000, seed=0)
    x, v = z[:, 0], z[:, 1]
    r = torch.tensor(system.config.radii, dtype=torch.float64)[:, None]
    assert bool(((x > r) & (x < 1 - r)).all())  # inside the box (walls rejected)
    assert abs(float(v.std()) - 1.0) < 0.03 and abs(float(v.mean())) < 0.03

    disks = dc.load_system("BD5")
    z = disks.sample_initial_conditions(1000, seed=0)
    pts = z[:, 0].reshape(-1, 5, 3, 2)
    vel = z[:, 1].reshape(-1, 5, 3, 2)
    e_x = pts[:, :, 1] - pts[:, :, 0]
    angle = torch.atan2(e_x[..., 1], e_x[..., 0])
    assert float(angle.min()) < -3.0 and float(angle.max()) > 3.0  # spans [0, 2 pi)
    e_y = pts[:, :, 2] - pts[:, :, 0]
    omega = ((vel[:, :, 1] - vel[:, :, 0]) * e_y).sum(-1)  # v_x-axis point = v + w e_y
    assert abs(float(omega.std()) - 0.5) < 0.03
    assert abs(float(vel[:, :, 0].std()) - 0.5) < 0.03


def test_chain_pendulum_layout():
    system = dc.load_system("CP3")
    z = system.sample_initial_conditions(1000, seed=0)
    x = z[:, 0]
    prev = torch.cat([torch.zeros_like(x[:, :1]), x[:, :-1]], dim=1)
    seg = x - prev
    q = torch.atan2(seg[..., 0], -seg[..., 1])  # from straight down
    assert float(q.min()) >= 0 and float(q.max()) < math.pi
    torch.testing.assert_close(
        seg.norm(dim=-1), torch.tensor([0.35, 0.4, 0.35], dtype=torch.float64).expand(1000, 3)
    )


def test_gyroscope_layout():
    system = dc.load_system("Gyro")
    z = system.sample_initial_conditions(500, seed=0)
    x, v = z[:, 0], z[:, 1]
    com, axes = x[:, 0], x[:, 1:] - x[:, :1]  # rows: R e1, R e2, R e3
    R = axes.transpose(-1, -2)
    torch.testing.assert_close(
        R.transpose(-1, -2) @ R, torch.eye(3, dtype=torch.float64).expand(500, 3, 3)
    )
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(500, dtype=torch.float64))
    torch.testing.assert_close(com, 0.5 * R[:, :, 2])  # pivot at the origin
    # pivot velocity is zero: v_com - 0.5 (v_e3 - v_com) = 0
    torch.testing.assert_close(
        1.5 * v[:, 0] - 0.5 * v[:, 3], torch.zeros(500, 3, dtype=torch.float64)
    )
    # spin about the symmetry axis: |w . e3| = 1.5 (7 + N(0, 1)) cos-free part
    a = torch.tensor([0.3, -0.7, 1.1], dtype=torch.float64)
    Rk, w = euler_zxz(a, torch.tensor([1.0, 0.2, 3.0], dtype=torch.float64))
    ca, sa, cb, sb = math.cos(0.3), math.sin(0.3), math.cos(-0.7), math.sin(-0.7)
    Rz = torch.tensor([[ca, -sa, 0], [sa, ca, 0], [0, 0, 1]], dtype=torch.float64)
    Rx = torch.tensor([[1, 0, 0], [0, cb, -sb], [0, sb, cb]], dtype=torch.float64)
    torch.testing.assert_close(Rk[:, 2], (Rz @ Rx)[:, 2])
    # finite-difference check of the world angular velocity: R' = [w]x R
    h = 1e-6
    Rp, _ = euler_zxz(a + h * torch.tensor([1.0, 0.2, 3.0], dtype=torch.float64), torch.zeros(3))
    Rm, _ = euler_zxz(a - h * torch.tensor([1.0, 0.2, 3.0], dtype=torch.float64), torch.zeros(3))
    W = (Rp - Rm) / (2 * h) @ Rk.T
    torch.testing.assert_close(torch.stack([W[2, 1], W[0, 2], W[1, 0]]), w, atol=1e-8, rtol=0)


def test_rope_layout():
    system = dc.load_system("Rope")
    z = system.sample_initial_conditions(500, seed=0)
    x = z[:, 0]
    prev = torch.cat([torch.zeros_like(x[:, :1]), x[:, :-1]], dim=1)
    seg = x - prev
    torch.testing.assert_close(seg.norm(dim=-1), torch.full((500, 10), 0.05, dtype=torch.float64))
    q0 = torch.atan2(seg[:, 0, 0], -seg[:, 0, 1])
    assert float(q0.min()) >= 0 and float(q0.max()) < math.pi
    gaps = system.gaps(x)
    assert float(gaps[:, :9].min()) > 0 and float(gaps[:, :9].max()) <= 0.2
