"""The penetration target's pseudo-inverse (S.24) without an SVD: ``impulse._pinv_apply``."""

import torch

from diffcontact.contact.impulse import _pinv_apply, penetration_target

F64 = torch.float64


def _pinv(J, v):
    return (torch.linalg.pinv(J) @ v.unsqueeze(-1)).squeeze(-1)


def test_full_row_rank_and_padded_rows_equal_pinv():
    gen = torch.Generator().manual_seed(0)
    J = torch.randn(64, 8, 10, generator=gen, dtype=F64)
    v = torch.randn(64, 8, generator=gen, dtype=F64)
    J[::2, 5:] = 0  # padded contacts: zero rows, zero target there
    v[::2, 5:] = 0
    torch.testing.assert_close(_pinv_apply(J, v), _pinv(J, v), rtol=1e-11, atol=1e-12)


def test_dependent_rows_match_pinv_on_the_range():
    """A point mass in a corner: four rows on two coordinates; pinv's least-squares lift."""
    gen = torch.Generator().manual_seed(1)
    J = torch.randn(32, 4, 2, generator=gen, dtype=F64) @ torch.randn(
        32, 2, 6, generator=gen, dtype=F64
    )
    v = torch.randn(32, 4, generator=gen, dtype=F64)
    got, want = _pinv_apply(J, v), _pinv(J, v)
    assert torch.isfinite(got).all()
    # the contact-space result J v* (what the solver uses) agrees to sqrt(eps)
    Jg, Jw = (J @ x.unsqueeze(-1) for x in (got, want))
    torch.testing.assert_close(Jg, Jw, rtol=1e-6, atol=1e-6 * float(Jw.abs().max()))


def test_no_contact_gives_zero_and_nan_propagates():
    J = torch.zeros(2, 4, 6, dtype=F64)
    v = torch.zeros(2, 4, dtype=F64)
    assert torch.equal(_pinv_apply(J, v), torch.zeros(2, 6, dtype=F64))
    J[1, 0, 0] = float("nan")
    out = _pinv_apply(J, v)
    assert torch.equal(out[0], torch.zeros(6, dtype=F64)) and not torch.isfinite(out[1]).all()


def test_penetration_target_float32():
    gen = torch.Generator().manual_seed(2)
    J = torch.randn(16, 6, 10, generator=gen)
    depth = torch.rand(16, 3, generator=gen)
    active = torch.ones(16, 3, dtype=torch.bool)
    got = penetration_target(J, depth, active, 0.01, 2)
    want = penetration_target(J.double(), depth.double(), active, 0.01, 2)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got.double(), want, rtol=1e-3, atol=1e-3)


def _corner_batch(n=24, seed=3):
    """Contact rows of ``n`` states, every third with dependent rows (four rows on two
    coordinates: a point mass in a corner), padded contacts in some."""
    gen = torch.Generator().manual_seed(seed)
    J = torch.randn(n, 4, 6, generator=gen, dtype=F64)
    J[::3] = torch.randn(n // 3, 4, 2, generator=gen, dtype=F64) @ torch.randn(
        n // 3, 2, 6, generator=gen, dtype=F64
    )
    depth = torch.rand(n, 2, generator=gen, dtype=F64)
    active = torch.ones(n, 2, dtype=torch.bool)
    active[1::4, 1] = False
    J[1::4, 2:] = 0
    return J, depth, active


def test_without_constraints_the_target_is_the_desired_velocity_where_rows_are_independent():
    """``J pinv(J) v_d = v_d`` for full row rank: exactly ``v_d`` (normal components
    ``fraction depth / dt``, tangential zero), and ``J pinv(J) v_d`` on the range where
    rows are dependent, with the operator as with the tensor."""
    from diffcontact.contact import DenseContact

    J, depth, active = _corner_batch()
    dt, fraction = 0.01, 0.25
    got = penetration_target(J, depth, active, dt, 2, fraction)
    v_d = torch.zeros(J.shape[0], 2, 2, dtype=F64)
    v_d[..., 0] = torch.where(active, fraction * depth / dt, 0)
    v_d = v_d.flatten(-2)
    independent = torch.ones(J.shape[0], dtype=torch.bool)
    independent[::3] = False
    assert torch.equal(got[independent], v_d[independent])
    want = (J @ _pinv(J, v_d).unsqueeze(-1)).squeeze(-1)  # the projection onto the range
    scale = float(want.abs().max())
    torch.testing.assert_close(got[~independent], want[~independent], rtol=0, atol=1e-6 * scale)
    assert not torch.allclose(want[~independent], v_d[~independent])  # a real projection
    via_op = penetration_target(DenseContact(J, None), depth, active, dt, 2, fraction)
    assert torch.equal(via_op, got)


def test_a_states_target_does_not_depend_on_its_batch():
    """Alone and in the batch: the same numbers (independent rows: exactly the desired
    velocity); a NaN stays in its state."""
    J, depth, active = _corner_batch()
    full = penetration_target(J, depth, active, 0.01, 2)
    for i in (0, 1, 2, 3):
        alone = penetration_target(J[i : i + 1], depth[i : i + 1], active[i : i + 1], 0.01, 2)
        torch.testing.assert_close(alone, full[i : i + 1], rtol=0, atol=1e-14)
    nan = J.clone()
    nan[5, 0, 0] = float("nan")
    out = penetration_target(nan, depth, active, 0.01, 2)
    assert not torch.isfinite(out[5]).all() and torch.isfinite(out[torch.arange(24) != 5]).all()


def test_an_active_contact_with_a_zero_row_gets_no_target():
    """A degenerate active contact whose Jacobian rows are zero: ``J pinv(J) v`` is zero
    there (the range of ``J`` does not reach it), the other rows keep their target."""
    J, depth, active = _corner_batch()
    J[2, 2:] = 0.0  # state 2 (independent rows): contact 1, active, has zero rows
    dt, fraction = 0.01, 0.5
    got = penetration_target(J, depth, active, dt, 2, fraction)
    v_d = torch.zeros(J.shape[0], 2, 2, dtype=F64)
    v_d[..., 0] = fraction * depth / dt
    v_d = v_d.flatten(-2)
    want = (J[2] @ _pinv(J[2], v_d[2])).squeeze(-1)
    assert float(v_d[2, 2]) > 0 and float(got[2, 2]) == 0.0
    torch.testing.assert_close(got[2], want, rtol=1e-12, atol=1e-12)


def test_mass_metric_target_is_the_desired_velocity_under_equality_constraints():
    """With the constrained inverse inertia as the metric, the target of independent rows
    is the desired velocity itself (zero tangential parts) whatever the constraints;
    appendix G's Euclidean lift and projection (S.22-S.24) give it tangential parts."""
    from diffcontact.mechanics import Mhat_inv

    gen = torch.Generator().manual_seed(3)
    n, D, E, K, d = 16, 9, 3, 2, 2
    J = torch.randn(n, K * d, D, generator=gen, dtype=F64)
    J_E = torch.randn(n, E, D, generator=gen, dtype=F64)
    R = torch.randn(n, D, D, generator=gen, dtype=F64)
    M_inv = R @ R.transpose(-1, -2) + D * torch.eye(D, dtype=F64)
    Mh = Mhat_inv(M_inv, J_E)
    depth = torch.rand(n, K, generator=gen, dtype=F64)
    active = torch.ones(n, K, dtype=torch.bool)
    mass = penetration_target(J, depth, active, 0.01, d, 0.125, J_E, Mh)
    desired = torch.stack([0.125 * depth / 0.01, torch.zeros_like(depth)], -1).flatten(-2)
    torch.testing.assert_close(mass, desired, rtol=1e-10, atol=1e-12)
    euclid = penetration_target(J, depth, active, 0.01, d, 0.125, J_E)
    assert float(euclid[:, 1::2].abs().min()) > 1e-6
