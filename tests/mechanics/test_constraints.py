"""Equality constraints: values, analytic Jacobians and second-order terms."""

import pytest
import torch
from torch.func import jacrev, vmap

from diffcontact.mechanics import (
    EqualityConstraints,
    ball_joint,
    chain_constraints,
    concat_constraints,
    dot_constraints,
    rigid_body_constraints,
)

DT = torch.float64


def mixed_2d() -> EqualityConstraints:
    """Chain (pivot off the origin), a disk with a ball joint, an anchor dot constraint."""
    chain = chain_constraints([0.35, 0.4, 0.35], pivot=[0.1, -0.2])
    disk = rigid_body_constraints(3, 2)
    joint = ball_joint(3, [0.2, -0.1], [1.0, 1.0], num_points=6)
    # (x_4 - anchor_0) . (x_1 - x_5) = 0.3, anchor 0 encoded as index num_points + 0
    extra = dot_constraints([[4, 6, 1, 5]], [0.3], dim=2, num_points=6, anchors=[[0.5, 0.7]])
    return concat_constraints(chain, disk, joint, extra)


def gyroscope() -> EqualityConstraints:
    return concat_constraints(
        rigid_body_constraints(0, 3), ball_joint(0, [0.0, 0.0, -0.5], [0.0, 0.0, 0.0])
    )


CASES = [(mixed_2d, 7, 2), (gyroscope, 4, 3)]  # 7 > 6 points: an extra free point


def random_state(P: int, dim: int, batch: int = 4, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(batch, P, dim, generator=gen, dtype=DT)
    v = torch.randn(batch, P, dim, generator=gen, dtype=DT)
    return x, v


def test_sizes_and_gyroscope_joint_weights():
    cons = mixed_2d()
    assert (cons.num_points, cons.num_dot, cons.num_linear) == (6, 7, 1)
    assert cons.num_equations == 9
    gyro = gyroscope()
    assert gyro.num_equations == 9
    torch.testing.assert_close(gyro.lin_weight, torch.tensor([[1.5, 0.0, 0.0, -0.5]], dtype=DT))


def test_phi_values_chain_and_joint():
    x, _ = random_state(7, 2)
    cons = mixed_2d()
    phi = cons.phi(x)
    assert phi.shape == (4, 9)
    pivot = torch.tensor([0.1, -0.2], dtype=DT)
    torch.testing.assert_close(phi[:, 0], ((x[:, 0] - pivot) ** 2).sum(-1) - 0.35**2)
    torch.testing.assert_close(phi[:, 2], ((x[:, 2] - x[:, 1]) ** 2).sum(-1) - 0.35**2)
    torch.testing.assert_close(phi[:, 5], ((x[:, 4] - x[:, 3]) * (x[:, 5] - x[:, 3])).sum(-1))
    anchor = torch.tensor([0.5, 0.7], dtype=DT)
    torch.testing.assert_close(phi[:, 6], ((x[:, 4] - anchor) * (x[:, 1] - x[:, 5])).sum(-1) - 0.3)
    joint = 0.9 * x[:, 3] + 0.2 * x[:, 4] - 0.1 * x[:, 5] - 1.0
    torch.testing.assert_close(phi[:, 7:], joint)


@pytest.mark.parametrize(("build", "P", "dim"), CASES)
def test_jacobian_matches_autograd_and_finite_differences(build, P, dim):
    cons = build()
    x, _ = random_state(P, dim)
    J = cons.jacobian(x)
    assert J.shape == (4, cons.num_equations, P * dim)
    auto = torch.autograd.functional.jacobian(lambda y: cons.phi(y).sum(0), x)
    auto = auto.permute(1, 0, 2, 3).reshape(J.shape)  # rows of element b depend on x_b only
    torch.testing.assert_close(J, auto, rtol=1e-12, atol=1e-12)
    h = 1e-6
    e = torch.zeros(P * dim, dtype=DT)
    e[P * dim // 2] = 1.0
    e = e.reshape(P, dim)
    fd = (cons.phi(x + h * e) - cons.phi(x - h * e)) / (2 * h)
    torch.testing.assert_close(J @ e.reshape(-1), fd, rtol=1e-7, atol=1e-8)


@pytest.mark.parametrize(("build", "P", "dim"), CASES)
def test_second_order_terms_match_autograd(build, P, dim):
    cons = build()
    x, v = random_state(P, dim, seed=1)

    def J_auto(y):
        return jacrev(cons.phi)(y).reshape(cons.num_equations, -1)

    def Jv(y, w):
        return J_auto(y) @ w.reshape(-1)

    def D_Jv(y, w):  # D_x(J_E(x) w) at fixed w, by reverse mode through J_auto
        return jacrev(lambda q: Jv(q, w))(y).reshape(cons.num_equations, -1)

    torch.testing.assert_close(cons.phi_dot(x, v), vmap(Jv)(x, v), rtol=1e-12, atol=1e-12)
    K_auto = vmap(D_Jv)(x, v)
    torch.testing.assert_close(cons.velocity_jacobian(x, v), K_auto)
    jdv_auto = (K_auto @ v.reshape(4, -1, 1))[..., 0]
    torch.testing.assert_close(cons.jacobian_dot_v(x, v), jdv_auto)
    assert jdv_auto.abs().max() > 0.1  # the check is not vacuous


def test_empty_constraints_shapes():
    cons = EqualityConstraints.empty(5, 2)
    x, v = random_state(5, 2)
    assert cons.num_equations == 0
    assert cons.phi(x).shape == (4, 0)
    assert cons.jacobian(x).shape == (4, 0, 10)
    assert cons.jacobian_dot_v(x, v).shape == (4, 0)
    assert cons.velocity_jacobian(x, v).shape == (4, 0, 10)


def test_concat_renumbers_anchors_and_pads_points():
    a = chain_constraints([1.0], pivot=[0.5, 0.0])  # P = 1, anchor index 1
    b = chain_constraints([2.0], first_point=2, pivot=[-1.0, 3.0])  # P = 3, anchor index 3
    both = concat_constraints(a, b, num_points=4)
    assert both.num_points == 4
    assert both.dot_index.tolist() == [[0, 4, 0, 4], [2, 5, 2, 5]]
    x, _ = random_state(4, 2)
    torch.testing.assert_close(both.phi(x), torch.cat([a.phi(x), b.phi(x)], -1))
    torch.testing.assert_close(both.jacobian(x), torch.cat([a.jacobian(x), b.jacobian(x)], -2))


def test_dtype_follows_input_and_broadcasting():
    cons = gyroscope()
    x, v = random_state(4, 3)
    x32 = x.float()
    assert cons.jacobian(x32).dtype == torch.float32
    assert cons.phi(x32).dtype == torch.float32
    # one position, a batch of velocities
    jdv = cons.jacobian_dot_v(x[0], v)
    assert jdv.shape == (4, 9)
    torch.testing.assert_close(jdv[2], cons.jacobian_dot_v(x[0], v[2]))


def test_bad_inputs_raise():
    cons = gyroscope()
    with pytest.raises(ValueError, match="shape"):
        cons.phi(torch.zeros(4, 2, dtype=DT))
    with pytest.raises(ValueError, match="dot_index"):
        dot_constraints([[0, 9, 0, 9]], [1.0], dim=2, num_points=2)
    with pytest.raises(ValueError, match="link_lengths"):
        chain_constraints([0.3, -0.1])
    with pytest.raises(ValueError, match="dim"):
        concat_constraints(rigid_body_constraints(0, 2), rigid_body_constraints(0, 3))


def test_split_gives_one_bodys_constraints_where_bodies_are_independent():
    bodies = concat_constraints(*(rigid_body_constraints(3 * b, 2, 12) for b in range(4)))
    one = bodies.split(3)
    assert one is not None and one.num_points == 3 and one.num_equations == 3
    assert torch.equal(one.dot_index, rigid_body_constraints(0, 2).dot_index)
    torch.testing.assert_close(one.dot_target, rigid_body_constraints(0, 2).dot_target)
    # the batched bodies give the same values and Jacobian blocks as all points at once
    x, _ = random_state(12, 2, batch=3)
    torch.testing.assert_close(one.phi(x.unflatten(-2, (4, 3))).flatten(-2), bodies.phi(x))
    J = bodies.jacobian(x).unflatten(-2, (4, 3)).unflatten(-1, (4, 6))  # (3, 4, 3, 4, 6)
    blocks = one.jacobian(x.unflatten(-2, (4, 3)))  # (3, 4, 3, 6)
    torch.testing.assert_close(J.diagonal(dim1=1, dim2=3).movedim(-1, 1), blocks)


@pytest.mark.parametrize(
    "build, size",
    [
        (mixed_2d, 3),  # anchors and a linear constraint: never split
        (gyroscope, 4),  # one body (nothing to batch) with a ball joint
        (lambda: chain_constraints([0.3, 0.3, 0.3, 0.3]), 2),  # a chain from a pivot
        # a link between the groups of points 0-1 and 2-3
        (lambda: dot_constraints([[1, 0, 1, 0], [2, 1, 2, 1]], [0.1, 0.1], 2, 4), 2),
        # a joint row between bodies 0 and 1
        (
            lambda: concat_constraints(
                rigid_body_constraints(0, 2, 6),
                rigid_body_constraints(3, 2, 6),
                dot_constraints([[1, 4, 1, 4]], [0.5], dim=2, num_points=6),
            ),
            3,
        ),
        # different targets per body
        (lambda: dot_constraints([[1, 0, 1, 0], [3, 2, 3, 2]], [1.0, 2.0], 2, 4), 2),
        # different local indices per body
        (lambda: dot_constraints([[1, 0, 1, 0], [2, 3, 2, 3]], [1.0, 1.0], 2, 4), 2),
        (lambda: rigid_body_constraints(0, 2, 5), 3),  # 5 points are not groups of 3
    ],
)
def test_split_refuses_constraints_that_couple_or_differ(build, size):
    assert build().split(size) is None
