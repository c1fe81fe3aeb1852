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
