"""Fast paths of solve_cone_qp: the closed form of one contact and warm starts.

A problem that takes a fast path reports 0 interior-point iterations; its answer must be
the minimiser (agreement with the Clarabel reference, optimality), its gradients must
match finite differences, and a guess that is not a minimiser must change nothing.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import diffcontact as dc
from diffcontact.contact import SolverSettings, solve_cone_qp
from diffcontact.contact.closed_form import single_contact_minimiser
from diffcontact.testing import assert_gradients_close

F64 = torch.float64
TORCH = SolverSettings(backend="torch")


def single_contact_batch(n: int, d: int, K_pad: int, seed: int):
    """n problems, each with ONE active contact at a random slot among K_pad: random PD
    2x2 (or 1x1) blocks, generic b, mu in [0, 1.2] with some exact zeros, lower bounds
    on half of them. Inactive slots carry random data that must not matter."""
    gen = torch.Generator().manual_seed(seed)
    C = K_pad * d
    M = torch.randn(n, C, C, generator=gen, dtype=F64)
    A = M @ M.transpose(-1, -2) / C + 0.05 * torch.eye(C, dtype=F64)
    b = torch.randn(n, C, generator=gen, dtype=F64)
    mu = torch.rand(n, K_pad, generator=gen, dtype=F64) * 1.2
    mu[torch.rand(n, K_pad, generator=gen) < 0.15] = 0.0
    lower = torch.rand(n, K_pad, generator=gen, dtype=F64)
    lower[torch.rand(n, K_pad, generator=gen) < 0.5] = 0.0
    slot = torch.randint(K_pad, (n,), generator=gen)
    active = torch.nn.functional.one_hot(slot, K_pad).bool()
    return A, b, mu, lower, active


@pytest.mark.parametrize("d", [1, 2])
def test_single_contact_takes_the_closed_form_and_matches_the_reference(d):
    pytest.importorskip("cvxpy")
    pytest.importorskip("clarabel")
    from .reference import ConeQP, solve_reference

    A, b, mu, lower, active = single_contact_batch(40, d, 3, seed=d)
    f, status = solve_cone_qp(A, b, mu, d, lower, active, return_status=True)
    assert status.converged.all() and (status.iterations == 0).all()
    assert (f.reshape(40, 3, d)[~active] == 0).all()
    for i in range(40):
        p = ConeQP(A[i].numpy(), b[i].numpy(), mu[i].numpy(), d, lower[i].numpy(),
                   active[i].numpy())  # fmt: skip
        ref = solve_reference(p)
        assert ref.polished, ref.reason
        np.testing.assert_allclose(
            f[i].numpy(), ref.f, rtol=0, atol=1e-9 * max(1, abs(ref.f).max())
        )


def test_closed_form_candidates_cover_every_region():
    """The minimiser lies in each region (inside, on a ray, on the lower-bound segment,
    at the corner) for some problem; all of them agree with the general solver."""
    A, b, mu, lower, active = single_contact_batch(400, 2, 1, seed=7)
    f, claimed = single_contact_minimiser(A, b, mu, lower, active, 2)
    assert claimed.all()
    fn, ft = f[:, 0], f[:, 1]
    on_ray = (ft.abs() - mu * fn).abs() < 1e-12
    on_bound = (fn - lower).abs() < 1e-12
    inside = ~on_ray & ~on_bound
    for region in (inside, on_ray & ~on_bound, on_bound & ~on_ray, on_ray & on_bound):
        assert region.any()
    # the general solver, on the same problems embedded among a decoupled second contact
    # (two active contacts: no closed form)
    A2 = torch.zeros(400, 4, 4, dtype=F64)
    A2[:, :2, :2], A2[:, 2:, 2:] = A, torch.eye(2, dtype=F64)
    b2 = torch.cat([b, torch.tensor([1.0, 0.0], dtype=F64).expand(400, 2)], -1)
    mu2 = torch.cat([mu, torch.full_like(mu, 0.5)], -1)
    lower2 = torch.cat([lower, torch.zeros_like(lower)], -1)
    f2 = solve_cone_qp(A2, b2, mu2, 2, lower2)
    torch.testing.assert_close(f2[:, :2], f, rtol=0, atol=1e-10)


@pytest.mark.parametrize("d", [1, 2])
def test_closed_form_gradients_match_finite_differences(d):
    A, b, mu, lower, active = single_contact_batch(6, d, 2, seed=20 + d)
    mu = mu.clamp_min(0.2)  # away from the one-sided points mu = 0 and lower = 0
    lower = lower.clamp_min(0.05)

    def fn(A_, b_, mu_, lower_):
        return solve_cone_qp(0.5 * (A_ + A_.transpose(-1, -2)), b_, mu_, d, lower_, active)

    assert_gradients_close(fn, (A, b, mu, lower))


def test_singular_single_contact_is_left_to_the_interior_point():
    """A rank-1 block: no closed form is claimed; the solver (the interior point of the
    reference, Newton steps from zero on the Warp backend) finds the minimiser."""
    v = torch.tensor([[1.0, 0.5]], dtype=F64)
    A = (v.T @ v).unsqueeze(0)
    b = torch.tensor([[-1.0, 0.2]], dtype=F64)
    mu = torch.tensor([[0.5]], dtype=F64)
    active = torch.ones(1, 1, dtype=torch.bool)
    _, claimed = single_contact_minimiser(A, b, mu, torch.zeros(1, 1, dtype=F64), active, 2)
    assert not claimed.any()
    f, status = solve_cone_qp(A, b, mu, 2, return_status=True)
    f_ref, ref = solve_cone_qp(A, b, mu, 2, return_status=True, settings=TORCH)
    assert status.converged.all() and ref.converged.all() and ref.iterations[0] > 0
    torch.testing.assert_close(f, f_ref, rtol=1e-10, atol=1e-12)


def random_batch(n, K, d, seed):
    gen = torch.Generator().manual_seed(seed)
    C = K * d
    M = torch.randn(n, C, C, generator=gen, dtype=F64)
    A = M @ M.transpose(-1, -2) / C + 0.05 * torch.eye(C, dtype=F64)
    b = torch.randn(n, C, generator=gen, dtype=F64)
    mu = torch.rand(n, K, generator=gen, dtype=F64)
    lower = torch.rand(n, K, generator=gen, dtype=F64) * (torch.rand(n, K, generator=gen) < 0.5)
    return A, b, mu, lower


@pytest.mark.parametrize("d", [2, 3])
def test_warm_start_at_the_solution_skips_the_interior_point(d):
    A, b, mu, lower = random_batch(16, 4, d, seed=40 + d)
    f, status = solve_cone_qp(A, b, mu, d, lower, return_status=True, settings=TORCH)
    assert (status.iterations > 0).all()  # cold, the reference runs the interior point
    f_w, status_w = solve_cone_qp(A, b, mu, d, lower, warm_start=f, return_status=True)
    assert status_w.converged.all() and (status_w.iterations == 0).all()
    torch.testing.assert_close(f_w, f, rtol=0, atol=1e-11)


@pytest.mark.parametrize("d", [2, 3])
def test_a_bad_warm_start_changes_nothing(d):
    """A guess far from the minimiser falls back to the interior point; same answer and
    the same gradients as without it."""
    A, b, mu, lower = random_batch(16, 4, d, seed=50 + d)
    f = solve_cone_qp(A, b, mu, d, lower)
    junk = 100 * torch.randn(16, 4 * d, dtype=F64, generator=torch.Generator().manual_seed(1))
    f_w = solve_cone_qp(A, b, mu, d, lower, warm_start=junk)
    torch.testing.assert_close(f_w, f, rtol=0, atol=1e-10)
    A1, b1, mu1, l1 = (x[:3] for x in (A, b, mu, lower))
    assert_gradients_close(
        lambda b_, mu_: solve_cone_qp(A1, b_, mu_, d, l1, warm_start=junk[:3]), (b1, mu1)
    )


def test_warm_start_is_checked():
    A, b, mu, _ = random_batch(2, 2, 2, seed=0)
    with pytest.raises(ValueError, match="warm_start must have shape"):
        solve_cone_qp(A, b, mu, 2, warm_start=torch.zeros(2, 3, dtype=F64))
    with pytest.raises(ValueError, match="warm_start contains NaN"):
        solve_cone_qp(A, b, mu, 2, warm_start=torch.full((2, 4), float("nan"), dtype=F64))


def test_restitution_phase_of_ball_collisions_needs_no_interior_point(monkeypatch):
    """BP5-e: every restitution problem is finished by the polish from e_P f_c."""
    from diffcontact.contact import impulse

    seen = []  # (warm started, interior-point iterations of the call), either backend
    original_solve = impulse.solve_cone_qp

    def recording(*args, warm_start=None, return_status=False, **kwargs):
        f, status = original_solve(*args, warm_start=warm_start, return_status=True, **kwargs)
        seen.append((warm_start is not None, int(status.iterations.sum())))
        return (f, status) if return_status else f

    monkeypatch.setattr(impulse, "solve_cone_qp", recording)
    system = dc.load_system("BP5-e")
    system.simulate(system.sample_initial_conditions(16, seed=3), 60)
    compression = [n for warm, n in seen if not warm]
    restitution = [n for warm, n in seen if warm]
    assert len(restitution) == len(compression) > 0
    assert sum(restitution) == 0
