"""Frames and extended-body material points."""

import math

import pytest
import torch

from diffcontact.geometry import contact_frame, material_point_weights, tangent_basis
from diffcontact.geometry.frames import safe_normalize

DT = torch.float64


def test_tangent_2d_is_normal_turned_left():
    n = torch.tensor([[1.0, 0.0], [0.6, 0.8]], dtype=DT)
    t = tangent_basis(n)
    assert t.shape == (2, 1, 2)
    torch.testing.assert_close(t[:, 0], torch.tensor([[0.0, 1.0], [-0.8, 0.6]], dtype=DT))


def test_tangent_3d_right_handed_orthonormal():
    g = torch.Generator().manual_seed(0)
    n = torch.randn(500, 3, generator=g, dtype=DT)
    axes = torch.tensor(
        [[0, 0, 1], [0, 0, -1], [0, 1, 0], [1, 0, 0], [0, -1, 0], [0, 0, -0.0]], dtype=DT
    )
    axes[-1] = torch.tensor([0.0, 1e-300, -1.0], dtype=DT)
    n = torch.cat((n, axes)) / torch.cat((n, axes)).norm(dim=-1, keepdim=True)
    frame = contact_frame(n)  # (N, 3, 3) rows n, t1, t2
    assert torch.isfinite(frame).all()
    eye = torch.eye(3, dtype=DT).expand_as(frame)
    torch.testing.assert_close(frame @ frame.transpose(-1, -2), eye)
    t1, t2 = frame[:, 1], frame[:, 2]
    torch.testing.assert_close(torch.linalg.cross(t1, t2), n)
    # deterministic: same input, same output
    torch.testing.assert_close(tangent_basis(n), tangent_basis(n.clone()), rtol=0, atol=0)


def test_tangent_rejects_other_dims():
    with pytest.raises(ValueError, match="2D or 3D"):
        tangent_basis(torch.ones(4, dtype=DT))


def test_material_point_weights_reproduce_point_2d_and_3d():
    g = torch.Generator().manual_seed(1)
    # 2D disk rotated by phi at c; the point p = c + (0.3, -0.2) in world frame
    phi = 0.7
    c = torch.tensor([0.4, -1.0], dtype=DT)
    ex = torch.tensor([math.cos(phi), math.sin(phi)], dtype=DT)
    ey = torch.tensor([-math.sin(phi), math.cos(phi)], dtype=DT)
    body = torch.stack((c, c + ex, c + ey))
    p = c + torch.tensor([0.3, -0.2], dtype=DT)
    w = material_point_weights(body, p)
    r1, r2 = float((p - c) @ ex), float((p - c) @ ey)
    torch.testing.assert_close(w, torch.tensor([1 - r1 - r2, r1, r2], dtype=DT))
    torch.testing.assert_close(w @ body, p)
    # 3D, batched, general (non-orthonormal) axes: still sum_a c_a x_a = p
    body3 = torch.randn(7, 5, 4, 3, generator=g, dtype=DT)
    p3 = torch.randn(7, 5, 3, generator=g, dtype=DT)
    w3 = material_point_weights(body3, p3)
    assert w3.shape == (7, 5, 4)
    torch.testing.assert_close((w3.unsqueeze(-1) * body3).sum(-2), p3)
    torch.testing.assert_close(w3.sum(-1), torch.ones(7, 5, dtype=DT))


def test_material_point_weights_point_mass_is_one():
    body = torch.randn(3, 1, 2, dtype=DT)
    w = material_point_weights(body, torch.randn(3, 2, dtype=DT))
    torch.testing.assert_close(w, torch.ones(3, 1, dtype=DT))


def test_safe_normalize_zero_vector_has_finite_gradient():
    v = torch.zeros(2, 3, dtype=DT, requires_grad=True)
    u, norm = safe_normalize(v)
    (u.sum() + norm.sum()).backward()
    assert torch.isfinite(v.grad).all()
    torch.testing.assert_close(u, torch.tensor([[1.0, 0, 0], [1.0, 0, 0]], dtype=DT))
