"""solve_cone_qp: optimality, masking, degenerate points, gradients and input errors.

Agreement with an independent conic solver (Clarabel) is in
test_reference_agreement.py; this file checks the solver against the
optimality conditions and closed-form cases, which need no other solver.
"""

from __future__ import annotations

import gc
import itertools
import math

import pytest
import torch

import diffcontact as dc
from diffcontact.contact import ConeQPError, SolverSettings, fused, solve_cone_qp
from diffcontact.contact.cone import project_contact_set
from diffcontact.testing import assert_gradients_close

F64 = torch.float64


def random_problems(n, K, d, seed, rank=None, lower_frac=0.0):
    gen = torch.Generator().manual_seed(seed)
    C = K * d
    r = C if rank is None else rank
    B = torch.randn(n, C, r, generator=gen, dtype=F64)
    A = B @ B.transpose(-1, -2) / r
    if rank is None:
        A = A + 0.05 * torch.eye(C, dtype=F64)
    b = torch.randn(n, C, generator=gen, dtype=F64)
    mu = torch.rand(n, K, generator=gen, dtype=F64) * 1.2
    lower = torch.rand(n, K, generator=gen, dtype=F64)
    lower = lower * (torch.rand(n, K, generator=gen) < lower_frac)
    return A, b, mu, lower


def sym(x):
    return 0.5 * (x + x.transpose(-1, -2))


def natural_residual(A, b, mu, lower, f, d):
    """||f - Pi_C(f - (A f + b))||_inf: zero exactly at minimisers."""
    K = mu.shape[-1]
    z = f - (A @ f.unsqueeze(-1)).squeeze(-1) - b
    proj, *_ = project_contact_set(z.reshape(*z.shape[:-1], K, d), mu, lower)
    return (f - proj.flatten(-2)).abs().amax(-1)


@pytest.mark.parametrize("d", [1, 2, 3])
@pytest.mark.parametrize("K", [1, 7, 30])
def test_solution_is_feasible_and_optimal(d, K):
    A, b, mu, lower = random_problems(16, K, d, seed=K * 10 + d, lower_frac=0.3)
    f = solve_cone_qp(A, b, mu, d, lower)
    fk = f.reshape(16, K, d)
    assert (fk[..., 0] >= lower - 1e-12).all()
    if d > 1:
        assert (fk[..., 1:].norm(dim=-1) <= mu * fk[..., 0] + 1e-10).all()
    assert natural_residual(A, b, mu, lower, f, d).max() < 1e-9
    # no feasible perturbation lowers the objective
    obj = lambda x: 0.5 * (x * (A @ x.unsqueeze(-1)).squeeze(-1)).sum(-1) + (b * x).sum(-1)  # noqa: E731
    gen = torch.Generator().manual_seed(1)
    for _ in range(20):
        y = fk + 0.05 * torch.randn(fk.shape, generator=gen, dtype=F64)
        y_proj, *_ = project_contact_set(y, mu, lower)
        assert (obj(y_proj.flatten(-2)) >= obj(f) - 1e-10).all()


def test_ball_hits_wall_with_friction_closed_form():
    # unit mass point, wall contact: A = I (d = 2), so f = Pi_cone(-v_C) (maximum
    # dissipation). v_C = (-2, 1), mu = 0.3: sliding, on the cone's surface,
    # f = c (1, -mu) with c = (2 + mu * 1) / (1 + mu^2)
    A = torch.eye(2, dtype=F64)
    f = solve_cone_qp(A, torch.tensor([-2.0, 1.0], dtype=F64), torch.tensor([0.3], dtype=F64), 2)
    c = (2 + 0.3) / (1 + 0.09)
    torch.testing.assert_close(f, torch.tensor([c, -0.3 * c], dtype=F64))
    # sticking when mu is large: the tangential velocity is removed
    f = solve_cone_qp(A, torch.tensor([-2.0, 1.0], dtype=F64), torch.tensor([0.8], dtype=F64), 2)
    torch.testing.assert_close(f, torch.tensor([2.0, -1.0], dtype=F64))
    # separating: no impulse
    f = solve_cone_qp(A, torch.tensor([2.0, 1.0], dtype=F64), torch.tensor([0.8], dtype=F64), 2)
    assert (f == 0).all()


@pytest.mark.parametrize("d", [1, 2, 3])
def test_inactive_contacts_are_zero_and_do_not_interact(d):
    K = 6
    A, b, mu, lower = random_problems(8, K, d, seed=3, lower_frac=0.3)
    active = torch.rand(8, K, generator=torch.Generator().manual_seed(0)) < 0.5
    active[:, 0] = True
    f = solve_cone_qp(A, b, mu, d, lower, active)
    mask_c = active.repeat_interleave(d, -1)
    assert (f[~mask_c] == 0).all()
    for i in range(8):  # reference: the reduced problem without the inactive contacts
        keep = mask_c[i]
        f_red = solve_cone_qp(
            A[i][keep][:, keep], b[i][keep], mu[i][active[i]], d, lower[i][active[i]]
        )
        torch.testing.assert_close(f[i][keep], f_red, rtol=1e-9, atol=1e-11)


@pytest.mark.parametrize("d", [1, 2, 3])
def test_gradients_match_finite_differences(d):
    A, b, mu, lower = random_problems(6, 5, d, seed=7 + d, lower_frac=0.4)
    mu = mu + 0.1
    assert_gradients_close(
        lambda A, b, mu, lower: solve_cone_qp(A, b, mu, d, lower),
        (A, b, mu, lower),
        directions={0: sym, 3: lambda x: x * (lower > 0)},
        rtol=1e-4,
    )


def test_gradient_at_mu_zero_is_the_right_derivative():
    A = torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=F64)
    b = torch.tensor([-1.0, 0.5], dtype=F64)
    mu = torch.zeros(1, dtype=F64, requires_grad=True)
    f = solve_cone_qp(A, b, mu, 2)
    assert f[1] == 0
    (g,) = torch.autograd.grad(f[1], mu)
    eps = 1e-7
    fd = solve_cone_qp(A, b, torch.tensor([eps], dtype=F64), 2)[1] / eps
    assert torch.isfinite(g).all()
    torch.testing.assert_close(g[0], fd, rtol=1e-5, atol=1e-9)
    assert g[0] < 0  # friction opposes the positive tangential velocity


def test_gradient_at_separating_contact_is_zero_and_finite():
    A, b, mu, _ = random_problems(4, 3, 2, seed=2)
    b[:, ::2] = 5.0  # all contacts separate fast: f = 0 at the cone's tip
    A.requires_grad_()
    b.requires_grad_()
    mu.requires_grad_()
    f = solve_cone_qp(A, b, mu, 2)
    assert (f == 0).all()
    grads = torch.autograd.grad((f * torch.randn_like(f)).sum(), (A, b, mu))
    for g in grads:
        assert torch.isfinite(g).all() and (g == 0).all()


def test_gradient_with_lower_bound_active_and_lower_zero():
    # one separating contact pushed by its lower bound (restitution phase, f_n = l)
    A = torch.tensor([[1.5]], dtype=F64)
    b = torch.tensor([1.0], dtype=F64)
    for l0 in (0.0, 0.4):
        lower = torch.tensor([l0], dtype=F64, requires_grad=True)
        f = solve_cone_qp(A, b, torch.zeros(1, dtype=F64), 1, lower)
        (g,) = torch.autograd.grad(f.sum(), lower)
        assert f.item() == pytest.approx(l0)
        assert g.item() == pytest.approx(1.0)  # right derivative at l = 0


def test_rank_deficient_pendulum_contact():
    # a pendulum bob moving only along n: A = n n^T (rank 1), d = 2
    n = torch.tensor([0.6, 0.8], dtype=F64)
    A = torch.outer(n, n)
    b = torch.tensor([-1.0, 0.3], dtype=F64)
    mu = torch.tensor([0.3], dtype=F64)
    f = solve_cone_qp(A, b, mu, 2)
    r = A @ f + b  # post-impact contact velocity: sliding, r_n = mu |r_t|
    assert r[0] == pytest.approx(mu.item() * abs(r[1].item()), rel=1e-9)
    assert abs(f[1]) == pytest.approx(mu.item() * f[0].item(), rel=1e-9)
    assert_gradients_close(
        lambda A, b, mu: solve_cone_qp(A, b, mu, 2),
        (A, b, mu),
        directions={0: lambda x: torch.outer(n, n) * x.sum()},  # stay rank 1
    )


def test_rank_deficient_batch_matches_optimality():
    A, b, mu, lower = random_problems(32, 8, 2, seed=5, rank=10, lower_frac=0.3)
    f, status = solve_cone_qp(A, b, mu, 2, lower, return_status=True)
    ok = status.converged
    assert ok.sum() >= 8  # most random problems are bounded
    assert (status.unbounded | ok).all()  # the others are reported as unbounded
    assert natural_residual(A, b, mu, lower, f, 2)[ok].max() < 1e-8


def test_unbounded_problem_raises_or_reports():
    n = torch.tensor([0.6, 0.8], dtype=F64)
    A, b = torch.outer(n, n), torch.tensor([-1.0, 0.3], dtype=F64)
    mu = torch.tensor([2.0], dtype=F64)  # (0.8, -0.6) is a free descent direction in the cone
    with pytest.raises(ConeQPError, match="unbounded"):
        solve_cone_qp(A, b, mu, 2)
    _, status = solve_cone_qp(A, b, mu, 2, return_status=True)
    assert bool(status.unbounded) and not bool(status.converged)


def test_shared_parameter_receives_summed_gradient():
    A, b, _, _ = random_problems(5, 4, 2, seed=11)
    mu_shared = torch.full((4,), 0.4, dtype=F64, requires_grad=True)
    w = torch.randn(5, 8, dtype=F64)
    f = solve_cone_qp(A, b, mu_shared.expand(5, 4), 2)
    (g_shared,) = torch.autograd.grad((f * w).sum(), mu_shared)
    g_each = []
    for i in range(5):
        mu_i = mu_shared.detach().clone().requires_grad_()
        fi = solve_cone_qp(A[i], b[i], mu_i, 2)
        g_each.append(torch.autograd.grad((fi * w[i]).sum(), mu_i)[0])
    torch.testing.assert_close(g_shared, torch.stack(g_each).sum(0))


def test_leading_batch_dims_and_float32():
    A, b, mu, lower = random_problems(12, 5, 3, seed=4, lower_frac=0.3)
    f64 = solve_cone_qp(A, b, mu, 3, lower)
    f = solve_cone_qp(
        A.reshape(3, 4, 15, 15).float(),
        b.reshape(3, 4, 15).float(),
        mu.reshape(3, 4, 5).float(),
        3,
        lower.reshape(3, 4, 5).float(),
    )
    assert f.shape == (3, 4, 15) and f.dtype == torch.float32
    torch.testing.assert_close(f.reshape(12, 15).double(), f64, rtol=1e-4, atol=1e-5)
    f_native = solve_cone_qp(
        A.float(),
        b.float(),
        mu.float(),
        3,
        lower.float(),
        settings=SolverSettings(compute_dtype=None),
        return_status=True,
    )[0]
    assert f_native.dtype == torch.float32


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    A, b, mu, lower = random_problems(64, 10, 2, seed=9, lower_frac=0.3)
    f_cpu = solve_cone_qp(A, b, mu, 2, lower)
    f_gpu = solve_cone_qp(A.cuda(), b.cuda(), mu.cuda(), 2, lower.cuda())
    assert f_gpu.device.type == "cuda"
    torch.testing.assert_close(f_gpu.cpu(), f_cpu, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"d": 4}, "d must be 1, 2 or 3"),
        ({"d": 2.0}, r"d must be 1, 2 or 3 \(an integer\), got 2.0"),
        ({"d": True}, "d must be 1, 2 or 3"),
        ({"mu": -torch.ones(2, dtype=F64)}, "mu must be >= 0"),
        ({"lower": -torch.ones(2, dtype=F64)}, "lower must be >= 0"),
        ({"b": torch.ones(3, dtype=F64)}, "b must have shape"),
        ({"mu": torch.ones(3, dtype=F64)}, "mu must have shape"),
        ({"b": torch.tensor([float("nan"), 0, 0, 0], dtype=F64)}, "b contains NaN"),
        ({"A": torch.ones(4, 3, dtype=F64)}, "A must have shape"),
        ({"A": torch.triu(torch.ones(4, 4, dtype=F64))}, "A must be symmetric"),
        ({"active": torch.ones(2)}, "active must be a bool tensor"),
        ({"b": torch.ones(4, dtype=torch.float32)}, "b has dtype"),
        ({"mu": torch.ones(5, 2, dtype=F64), "b": torch.ones(3, 4, dtype=F64)}, "broadcast"),
    ],
)
def test_bad_calls_name_the_problem(kwargs, message):
    args = {
        "A": torch.eye(4, dtype=F64),
        "b": torch.ones(4, dtype=F64),
        "mu": torch.ones(2, dtype=F64),
        "d": 2,
        "lower": None,
        "active": None,
    }
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        solve_cone_qp(**args)


def _backends() -> list[str]:
    return ["torch", "warp"] if fused.warp_installed() else ["torch"]


@pytest.mark.parametrize("backend", _backends())
@pytest.mark.parametrize(
    ("name", "change", "message"),
    [
        ("A", lambda x: x.to_sparse(), "A must be a dense tensor, got layout torch.sparse_coo"),
        ("b", lambda x: x.to_sparse(), "b must be a dense tensor, got layout torch.sparse_coo"),
        ("A", lambda x: x.to("meta"), "A is on the meta device"),
        ("mu", lambda x: x.to("meta"), "mu is on the meta device"),
        ("active", lambda x: x.to_sparse(), "active must be a dense tensor"),
    ],
)
def test_sparse_and_meta_tensors_are_named(backend, name, change, message):
    # both ended in a raw error from deep inside (torch's 'aten::ne.Scalar' for the
    # SparseCPU backend, Warp's missing data pointer, .item() on a meta tensor)
    args = {
        "A": torch.eye(4, dtype=F64).expand(3, 4, 4),
        "b": torch.ones(3, 4, dtype=F64),
        "mu": torch.ones(3, 2, dtype=F64),
        "active": torch.ones(3, 2, dtype=torch.bool),
    }
    args[name] = change(args[name])
    with pytest.raises(ValueError, match=f"solve_cone_qp: {message}"):
        solve_cone_qp(**args, d=2, settings=SolverSettings(backend=backend))


def _set(name: str, index: tuple, value: float):
    def fault(args: dict) -> None:
        args[name][index] = value

    return fault


_FAULTS = {
    "NaN in A": _set("A", (0, 0, 0), float("nan")),
    "NaN in b": _set("b", (0, 0), float("nan")),
    "NaN in mu": _set("mu", (0, 0), float("nan")),
    "NaN in lower": _set("lower", (0, 0), float("nan")),
    "NaN in warm_start": _set("warm_start", (0, 0), float("nan")),
    "mu < 0": _set("mu", (1, 0), -1.0),
    "lower < 0": _set("lower", (1, 0), -1.0),
    "asymmetric A": _set("A", (1, 0, 1), 0.5),
    "indefinite A": lambda args: (_set("A", (1, 0, 2), 1.5)(args), _set("A", (1, 2, 0), 1.5)(args)),
}


@pytest.mark.skipif(not fused.warp_installed(), reason="compares the two backends")
def test_several_faults_name_the_same_one_on_both_backends():
    # the Warp backend named a NaN warm start before mu < 0, lower < 0, an asymmetric or an
    # indefinite A, where the torch backend names those first
    assert set(fused._FLAG_ORDER) == {i for i, m in enumerate(fused.FLAGS) if m is not None}
    base = {
        "A": torch.eye(4, dtype=F64).expand(2, 4, 4).clone(),
        "b": torch.ones(2, 4, dtype=F64),
        "mu": torch.ones(2, 2, dtype=F64),
        "lower": torch.zeros(2, 2, dtype=F64),
        "warm_start": torch.zeros(2, 4, dtype=F64),
    }
    for first, second in itertools.combinations(_FAULTS, 2):
        messages = []
        for backend in ("torch", "warp"):
            args = {k: v.clone() for k, v in base.items()}
            _FAULTS[first](args)
            _FAULTS[second](args)
            with pytest.raises(ValueError) as err:
                solve_cone_qp(**args, d=2, settings=SolverSettings(backend=backend))
            messages.append(str(err.value))
        assert messages[0] == messages[1], (first, second)


@pytest.mark.parametrize("backend", _backends())
def test_an_indefinite_A_is_refused_on_its_active_contacts(backend):
    # positive diagonal, symmetric, eigenvalue -0.5 from the coupling of contacts 0 and 1:
    # a nonconvex problem, on which the two backends returned different impulses silently
    A = torch.tensor([[1.0, 0, 1.5, 0], [0, 1, 0, 0], [1.5, 0, 1, 0], [0, 0, 0, 1]], dtype=F64)
    A = torch.stack([torch.eye(4, dtype=F64), A])  # the second problem of two
    b = torch.tensor([-1.0, 0.1, -1.0, 0.1], dtype=F64).expand(2, 4)
    mu = torch.full((2, 2), 0.5, dtype=F64)
    settings = SolverSettings(backend=backend)
    with pytest.raises(ValueError, match=r"A must be positive semi-definite \(a negative eigen"):
        solve_cone_qp(A, b, mu, 2, settings=settings)
    # with contact 1 inactive the active block is [[1, 0], [0, 1]]: solved
    active = torch.tensor([[True, True], [True, False]])
    f = solve_cone_qp(A, b, mu, 2, active=active, settings=settings)
    assert f[1, 2:].abs().max() == 0 and f[1, 0] > 0
    # without the checks (the simulator's inner calls) nothing is refused
    solve_cone_qp(A, b, mu, 2, settings=SolverSettings(backend=backend, check_inputs=False),
                  return_status=True)  # fmt: skip


@pytest.mark.parametrize("backend", _backends())
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_a_singular_A_rounded_in_its_dtype_is_accepted(backend, dtype):
    # Delassus matrices J M^-1 J^T of 6 contacts on 2 bodies in 2D (rank 6 of 12), built
    # in the dtype: their rounding-level negative eigenvalues are not refused
    gen = torch.Generator().manual_seed(3)
    J = torch.randn(64, 12, 6, generator=gen, dtype=F64).to(dtype)
    M_inv = torch.diag_embed(torch.rand(64, 6, generator=gen, dtype=F64) * 1e3 + 1e-3).to(dtype)
    A = J @ M_inv @ J.transpose(-1, -2)
    A = 0.5 * (A + A.transpose(-1, -2))
    assert torch.linalg.eigvalsh(A.double()).min() < 0  # rounding made it indefinite
    b = torch.randn(64, 12, generator=gen, dtype=F64).to(dtype)
    mu = torch.full((64, 6), 0.3, dtype=dtype)
    solve_cone_qp(A, b, mu, 2, settings=SolverSettings(backend=backend), return_status=True)


@pytest.mark.parametrize("backend", _backends())
@pytest.mark.parametrize(
    ("A", "d", "active"),
    [
        # rounding-level negative diagonals of singular matrices (a negative-diagonal test
        # refused these before; the second: a 1 kg point tied to a 1e8 kg one)
        ([[1.0, 0.0], [0.0, -1e-8]], 1, None),
        ([[-1.2e-16, -3e-17], [-3e-17, 1.07e-8]], 1, None),
        # an inactive contact's block is not the problem's
        ([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]], 2, [True, False]),
    ],
)
def test_singular_or_masked_matrices_are_accepted(backend, A, d, active):
    A = torch.tensor(A, dtype=F64)
    C = A.shape[-1]
    active = None if active is None else torch.tensor(active)
    settings = SolverSettings(backend=backend)
    b, mu = -torch.ones(C, dtype=F64), torch.ones(C // d, dtype=F64)
    solve_cone_qp(A, b, mu, d, active=active, settings=settings, return_status=True)


def test_the_backends_agree_on_semidefiniteness_at_the_tolerance():
    if not fused.warp_installed():
        pytest.skip("needs warp-lang")
    # float32 inputs, the check in the compute dtype (float64) on both backends
    edge = fused.SEMIDEFINITE_TOL / (1 - fused.SEMIDEFINITE_TOL)  # -e + tol (1 + e) = 0
    for e in (2.9e-4, 0.999 * edge, 1.001 * edge, 3.1e-4):
        A = torch.tensor([[1.0, 1.0 + e], [1.0 + e, 1.0]], dtype=torch.float32)
        b, mu = -torch.ones(2, dtype=torch.float32), torch.ones(2, dtype=torch.float32)
        refused = []
        for backend in ("torch", "warp"):
            try:
                solve_cone_qp(A, b, mu, 1, settings=SolverSettings(backend=backend),
                              return_status=True)  # fmt: skip
                refused.append(False)
            except ValueError as err:
                assert "semi-definite" in str(err)
                refused.append(True)
        assert refused[0] == refused[1], (e, refused)
        assert refused[0] == (e > edge), (e, refused)


@pytest.mark.parametrize("backend", _backends())
def test_an_impulse_on_a_contact_constrained_away_is_not_refused(backend):
    # a point mass on a rod, the contact normal along the rod: A = J Mhat^-1 J^T is zero
    # up to rounding (about -1e-16 at some angles), semi-definite by construction
    from diffcontact.contact import two_phase_impulse
    from diffcontact.mechanics.dynamics import Mhat_inv

    angles = torch.linspace(0.1, 6.2, 40, dtype=F64)
    u = torch.stack([angles.cos(), angles.sin()], -1)  # (40, 2)
    M_hat = Mhat_inv(torch.eye(2, dtype=F64).expand(40, 2, 2) * 0.5, u.unsqueeze(-2))
    A = (u.unsqueeze(-2) @ M_hat @ u.unsqueeze(-1)).squeeze()
    assert (A < 0).any()  # rounding made some of them negative
    v = torch.stack([-u[:, 1], u[:, 0]], -1)  # swinging about the anchor (J_E v = 0)
    out = two_phase_impulse(
        u.unsqueeze(-2), M_hat, v, torch.full((40, 1), 0.3, dtype=F64),
        torch.full((40, 1), 0.5, dtype=F64), torch.ones(40, 1, dtype=torch.bool), 1,
        settings=SolverSettings(backend=backend),
    )  # fmt: skip
    torch.testing.assert_close(out.v_plus, v)  # the contact does not approach: no impulse


def test_half_precision_and_warm_start_dtype():
    f = solve_cone_qp(torch.eye(4, dtype=torch.float16), -torch.ones(4, dtype=torch.float16),
                      torch.ones(2, dtype=torch.float16), 2,
                      settings=SolverSettings(backend="torch"))  # fmt: skip
    assert f.dtype == torch.float16 and torch.allclose(f.float()[0::2], torch.ones(2))
    A = torch.eye(4, dtype=F64)
    with pytest.raises(ValueError, match=r"warm_start has dtype torch\.float32, A has"):
        solve_cone_qp(A, -torch.ones(4, dtype=F64), torch.ones(2, dtype=F64), 2,
                      warm_start=torch.zeros(4))  # fmt: skip


def test_the_semidefinite_tolerance_is_the_kernels():
    if not fused.warp_installed():
        pytest.skip("needs warp-lang")
    _, kernels = fused._load()
    assert float(kernels.SEMIDEFINITE.value if hasattr(kernels.SEMIDEFINITE, "value")
                 else kernels.SEMIDEFINITE) == fused.SEMIDEFINITE_TOL  # fmt: skip


def test_problems_the_polish_cannot_finish_are_solved_again():
    # a loose interior-point gap leaves active sets unidentified; the retries recover
    A, b, mu, lower = random_problems(64, 20, 3, seed=21, lower_frac=0.3)
    loose = SolverSettings(gap=1e-2, polish_steps=1, retries=0, tol=1e-10)
    _, status = solve_cone_qp(A, b, mu, 3, lower, settings=loose, return_status=True)
    assert not status.all_converged
    f, status = solve_cone_qp(
        A,
        b,
        mu,
        3,
        lower,
        settings=SolverSettings(gap=1e-2, polish_steps=1, retries=4, tol=1e-10),
        return_status=True,
    )
    assert status.all_converged
    assert natural_residual(A, b, mu, lower, f, 3).max() < 1e-8  # accepted: tol 1e-9 scaled


@pytest.mark.parametrize(
    ("name", "d", "tol"),
    [
        # 7 touching disks, mu = 0, restitution bounds, A of rank 11/14: the redundant
        # constraints at the cone's tip used to stall the interior point
        ("bd5_restitution_mu0_singular", 2, 1e-9),
        ("gyro_compression_singular", 3, 1e-9),  # the gyroscope's rim contact, singular A
        ("rope_d200_restitution", 1, 1e-9),  # many simultaneous rope limits
        # padded (inactive) contacts sit exactly on the cone's axis: the step length must
        # not let them pass through the apex
        ("bp5_restitution_inactive_tip", 2, 1e-9),
        # rope limits on which Mehrotra's second-order correction made the iterates cycle
        ("rope_mehrotra_cycling", 1, 1e-9),
        # 53 rope limits, several weakly active: the polish ends near 6e-8 (accepted)
        ("rope_d100_degenerate", 1, 1e-6),
    ],
)
def test_recorded_simulator_problems(name, d, tol):
    from pathlib import Path

    data = torch.load(Path(__file__).parent / "data" / f"{name}.pt")
    args = (data["A"], data["b"], data["mu"], d, data["lower"], data["active"])
    f, status = solve_cone_qp(*args, return_status=True)
    assert status.all_converged
    lower = data["lower"] if data["lower"] is not None else torch.zeros_like(data["mu"])
    active_c = data["active"].repeat_interleave(d, -1)
    assert (f[~active_c] == 0).all()
    A = torch.where(active_c[..., None] & active_c[..., None, :], data["A"], 0)
    res = natural_residual(A, torch.where(active_c, data["b"], 1.0), data["mu"], lower, f, d)
    assert res.max() < tol


def _live_solver_nodes() -> int:
    names = ("_ConeQPFunctionBackward", "FusedConeQPBackward")  # torch, Warp backend
    return sum(type(o).__name__ in names for o in gc.get_objects())


def test_no_solver_node_survives_a_training_step_without_gc():
    """The autograd node of a solve (and its saved factorisations) is freed by reference
    counting alone once the graph is dropped: no cycle waits for the garbage collector."""
    from diffcontact.learning.models.physical import LearnedModel
    from diffcontact.learning.training.module import rollout_loss

    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(8, seed=3)
    chunk = system.simulate(z0, 12)
    torch.manual_seed(0)
    model = LearnedModel("BP5", hidden=(8, 8)).double()
    gc.collect()
    gc.disable()
    try:
        before = _live_solver_nodes()
        # a graph alive holds its nodes (the count sees them) ...
        loss = rollout_loss(model, chunk)
        assert _live_solver_nodes() > before
        # ... a training step's backward and dropping the loss frees all of them
        loss.backward()
        del loss
        assert _live_solver_nodes() == before
        # the float32 path (solve in float64, result cast back) and a direct solve
        A, b, mu, _ = random_problems(4, 3, 2, seed=5)
        A32 = A.float().requires_grad_()
        f = solve_cone_qp(A32, b.float(), mu.float(), 2)
        assert _live_solver_nodes() == before + 1
        f.sum().backward()
        del f
        assert _live_solver_nodes() == before
        # a graph dropped without a backward is freed too
        f = solve_cone_qp(A.requires_grad_(), b, mu, 2)
        assert _live_solver_nodes() == before + 1
        del f
        assert _live_solver_nodes() == before
    finally:
        gc.enable()


def _in_dual_cones(b, mu, d):
    """b's blocks in the dual cones ``mu ||y_t|| <= y_n`` (d = 1: ``y_n >= 0``)."""
    bk = b.reshape(*b.shape[:-1], -1, d)
    if d == 1:
        return (bk[..., 0] >= 0).all(-1)
    return (mu * bk[..., 1:].norm(dim=-1) <= bk[..., 0]).all(-1)


def test_issue_example_with_a_zero_is_unbounded_not_converged():
    A = torch.zeros(1, 2, 2)
    b, mu = torch.tensor([[0.1786, 0.3511]]), torch.tensor([[1.4538]])
    for dtype in (torch.float32, F64):
        _, status = solve_cone_qp(A.to(dtype), b.to(dtype), mu.to(dtype), 2, return_status=True)
        assert bool(status.unbounded) and not bool(status.converged)
        with pytest.raises(ConeQPError, match="unbounded"):
            solve_cone_qp(A.to(dtype), b.to(dtype), mu.to(dtype), 2)


@pytest.mark.parametrize("d", [1, 2, 3])
def test_zero_A_is_unbounded_exactly_when_b_leaves_the_dual_cones(d):
    # A = 0: the objective b^T f is bounded below on the cones iff b lies in their duals
    gen = torch.Generator().manual_seed(d)
    n, K = 400, 3
    b = torch.randn(n, K * d, generator=gen, dtype=F64)
    mu = torch.rand(n, K, generator=gen, dtype=F64) * 2
    lower = torch.rand(n, K, generator=gen, dtype=F64) * (torch.rand(n, K, generator=gen) < 0.3)
    A = torch.zeros(n, K * d, K * d, dtype=F64)
    f, status = solve_cone_qp(A, b, mu, d, lower, return_status=True)
    bounded = _in_dual_cones(b, mu, d)
    assert 0 < int(bounded.sum()) < n
    assert torch.equal(status.unbounded, ~bounded)
    assert torch.equal(status.converged, bounded)
    # the bounded ones: f = lower on the normals (every b_k in its dual cone)
    assert natural_residual(A, b, mu, lower, f, d)[bounded].max() < 1e-12


def _singular_problems(n, K, d, rank, seed, unbounded):
    """Singular A = B B^T (rank ``rank``). Unbounded: a direction u in the cones spans
    null(A) partly and b^T u < 0. Bounded: b = A y + w with w inside the dual cones (a
    feasible dual point)."""
    gen = torch.Generator().manual_seed(seed)
    C = K * d
    mu = torch.rand(n, K, generator=gen, dtype=F64) * 1.5
    if d > 1:
        mu = torch.where(torch.rand(n, K, generator=gen) < 0.2, 0, mu)
    B = torch.randn(n, C, rank, generator=gen, dtype=F64)
    if unbounded:
        z = torch.randn(n, K, d, generator=gen, dtype=F64)
        z[..., 0] = z[..., 0].abs() + 0.5
        u = project_contact_set(z, mu, torch.zeros_like(mu))[0].reshape(n, C)
        some = (torch.rand(n, K, generator=gen) < 0.6).repeat_interleave(d, -1)
        some[:, :d] = True
        u = torch.where(some, u, 0)
        u = u / u.norm(dim=-1, keepdim=True)
        B = B - u[:, :, None] * (u[:, None, :] @ B)  # range(A) orthogonal to u
        A = B @ B.transpose(-1, -2) / rank
        b = torch.randn(n, C, generator=gen, dtype=F64)
        step = (b * u).sum(-1) + 0.05 + torch.rand(n, generator=gen, dtype=F64)
        b = b - step[:, None] * u
    else:
        A = B @ B.transpose(-1, -2) / rank
        w = torch.randn(n, K, d, generator=gen, dtype=F64)
        w[..., 0] = mu * w[..., 1:].norm(dim=-1) + 0.05 + torch.rand(n, K, generator=gen)
        y = torch.randn(n, C, 1, generator=gen, dtype=F64)
        b = (A @ y).squeeze(-1) + w.reshape(n, C)
    lower = torch.rand(n, K, generator=gen, dtype=F64) * (torch.rand(n, K, generator=gen) < 0.3)
    return A, b, mu, lower


@pytest.mark.parametrize(
    ("d", "K", "rank"), [(1, 3, 2), (1, 8, 7), (2, 3, 2), (2, 8, 10), (3, 3, 4)]
)
def test_singular_A_unbounded_and_bounded_problems_are_told_apart(d, K, rank):
    n = 100
    A, b, mu, lower = _singular_problems(n, K, d, rank, seed=K + 10 * d, unbounded=True)
    _, status = solve_cone_qp(A, b, mu, d, lower, return_status=True)
    assert not status.converged.any()  # never a runaway iterate reported as a solution
    # most carry a certificate; on a few hard ones with cones (the direction on a cone's
    # surface) neither phase finds one, and they are reported unconverged
    assert status.unbounded.float().mean() >= (1.0 if d == 1 else 0.9)
    A, b, mu, lower = _singular_problems(n, K, d, rank, seed=K + 10 * d, unbounded=False)
    f, status = solve_cone_qp(A, b, mu, d, lower, return_status=True)
    assert status.converged.all() and not status.unbounded.any()
    assert natural_residual(A, b, mu, lower, f, d).max() < 1e-9


@pytest.mark.parametrize("d", [1, 2, 3])
def test_separating_problems_skip_the_interior_point(d):
    """b in the dual cones and no lower bound: f = 0 without iterations, zero gradients;
    the other problems of the batch are solved as they would be alone."""
    A, b, mu, _ = random_problems(12, 4, d, seed=30 + d)
    bk = b.reshape(12, 4, d).clone()
    bk[:6, :, 0] = (mu[:6] * bk[:6, :, 1:].norm(dim=-1) if d > 1 else 0) + 0.1 + bk[:6, :, 0].abs()
    b = bk.reshape(12, 4 * d)
    A.requires_grad_()
    b.requires_grad_()
    mu.requires_grad_()
    f, status = solve_cone_qp(A, b, mu, d, return_status=True)
    assert torch.equal(f[:6], torch.zeros_like(f[:6])) and status.converged.all()
    separating = _in_dual_cones(b.detach(), mu.detach(), d)
    assert (status.iterations[separating] == 0).all()
    # the reference runs the interior point on every other problem (the Warp backend may
    # finish them by Newton steps from zero, without interior-point iterations)
    _, ref = solve_cone_qp(
        A.detach(), b.detach(), mu.detach(), d, settings=SolverSettings(backend="torch"),
        return_status=True,
    )  # fmt: skip
    assert torch.equal(ref.iterations == 0, separating)
    assert (ref.iterations[:6] == 0).all() and (ref.iterations[6:] > 0).any()
    w = torch.randn(12, 4 * d, dtype=F64)
    gA, gb, gmu = torch.autograd.grad((f * w).sum(), (A, b, mu))
    assert (gA[:6] == 0).all() and (gb[:6] == 0).all() and (gmu[:6] == 0).all()
    alone = solve_cone_qp(A[6:].detach(), b[6:].detach(), mu[6:].detach(), d)
    torch.testing.assert_close(f[6:].detach(), alone, rtol=0, atol=1e-14)
    # a lower bound makes f = 0 infeasible: solved as usual
    lower = torch.zeros(12, 4, dtype=F64)
    lower[0, 0] = 0.3
    f2, status = solve_cone_qp(A.detach(), b.detach(), mu.detach(), d, lower, return_status=True)
    assert status.converged[0] and f2[0, 0] >= 0.3 - 1e-12
    assert_gradients_close(
        lambda b_: solve_cone_qp(A.detach()[:6], b_, mu.detach()[:6], d), (b.detach()[:6],)
    )


def _wedged_light_body() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A point mass of 1e-6 pressed into a wall by one of 1e3: ``A, b, mu, v_C``.

    Contact 0 is the pair (normal ``n`` from the light body to the heavy one), contact 1
    the wall (normal ``w``); d = 2, both on the light body. ``A = J M^-1 J^T`` has
    eigenvalues 2e6 (the light body) and 5e-4 (the heavy body, through the pair):
    bounded, condition 4e9, with a minimiser about 2e9 natural impulse scales
    (``|b| / max diag A``) out. The kind of problem BP5 with masses 1e-6..1e6 meets
    (reported unbounded until 2026-11-26).
    """
    m_light, m_heavy = 1e-6, 1e3
    n = torch.tensor([math.cos(0.1), math.sin(0.1)], dtype=F64)
    w = torch.tensor([1.0, 0.0], dtype=F64)
    perp = lambda a: torch.stack([-a[1], a[0]])  # noqa: E731
    zero = torch.zeros(2, dtype=F64)
    # rows: velocity of contact space from (v_light, v_heavy), each (4,)
    J = torch.stack(
        [
            torch.cat([-n, n]),  # pair normal: separation speed of heavy from light
            torch.cat([-perp(n), perp(n)]),
            torch.cat([w, zero]),  # wall normal: speed of the light body off the wall
            torch.cat([perp(w), zero]),
        ]
    )
    M_inv = torch.diag(torch.tensor([1 / m_light] * 2 + [1 / m_heavy] * 2, dtype=F64))
    A = J @ M_inv @ J.T
    v = torch.cat([torch.tensor([-1.0, 0.5], dtype=F64), -2.0 * n])  # both pressing
    b = J @ v
    mu = torch.tensor([0.6, 0.1], dtype=F64)
    return A[None], b[None], mu[None], J


@pytest.mark.parametrize("backend", ["torch", "warp"])
def test_a_light_body_wedged_by_a_heavy_one_is_bounded(backend):
    """A nearly singular but positive definite A (condition 4e9) is solved, not called
    unbounded: the certificate also asks that the objective still fall along its direction
    at the solver's point, which it does not at a minimiser however far out."""
    if backend == "warp":
        pytest.importorskip("warp")
    A, b, mu, _ = _wedged_light_body()
    evals = torch.linalg.eigvalsh(A[0])
    assert evals.min() > 0 and evals.max() / evals.min() > 1e9  # bounded, badly conditioned
    f, status = solve_cone_qp(
        A, b, mu, 2, return_status=True, settings=SolverSettings(backend=backend)
    )
    assert bool(status.converged.all()) and not bool(status.unbounded.any())
    # far beyond the 1e2 scales from which the certificate examines a problem
    assert float(f.abs().max() * A[0].diagonal().max() / b.abs().max()) > 1e9
    scale = f.abs().max().clamp_min(1)
    assert natural_residual(A, b, mu, torch.zeros_like(mu), f, 2).max() / scale < 1e-9
    # the impulse stops the heavy body: no contact approaches after it (to rounding)
    v_after = b + (A @ f.unsqueeze(-1)).squeeze(-1)
    assert (v_after[0, ::2] >= -1e-9 * float((A.abs() @ f.abs().unsqueeze(-1)).max())).all()
    fk = f.reshape(2, 2)
    assert (fk[:, 1].abs() <= mu[0] * fk[:, 0] * (1 + 1e-9)).all()  # friction cones
    # the heavy body's momentum into the wall (2e3 along n) is what the impulses absorb
    assert 1e3 < float(fk[0, 0]) < 1e5


def test_wedged_light_body_agrees_across_backends():
    pytest.importorskip("warp")
    A, b, mu, _ = _wedged_light_body()
    f_t = solve_cone_qp(A, b, mu, 2, settings=SolverSettings(backend="torch"))
    f_w = solve_cone_qp(A, b, mu, 2, settings=SolverSettings(backend="warp"))
    torch.testing.assert_close(f_w, f_t, rtol=1e-6, atol=0)


@pytest.mark.parametrize("backend", ["torch", "warp"])
def test_contacts_of_very_different_scales_are_solved(backend):
    """Two contacts of bodies with masses 1e-6 and 1e6: bounded, and solved as such.

    The problem is the one BP5 with masses 1e-6..1e6 met (it was reported unbounded:
    its curvature along the heavy contact is 1e-12 of the light one's). Per-contact
    equilibration solves it; the answer is checked against the closed form of the
    decoupled contacts (A is diagonal) and the status is converged.
    """
    if backend == "warp":
        pytest.importorskip("warp")
    A = torch.diag(torch.tensor([1e6, 1e6, 1e-6, 1e-6], dtype=torch.float64))[None]
    b = torch.tensor([[-1.337277, 0.126539, -1.218436, -0.328941]], dtype=torch.float64)
    mu = torch.tensor([[0.6, 0.1]], dtype=torch.float64)
    settings = SolverSettings(backend=backend)
    f, status = solve_cone_qp(A, b, mu, 2, return_status=True, settings=settings)
    assert bool(status.converged.all()) and not bool(status.unbounded.any())
    # contact 1: -b / a is inside the cone (|f_t| = 0.095 <= 0.6 * 1.34)
    torch.testing.assert_close(f[0, :2], -b[0, :2] / 1e6, rtol=1e-9, atol=0)
    # contact 2: the objective 0.5 a |f|^2 + b'f is isotropic, so f is the projection of
    # -b / a onto the cone; that point is outside it: f_n = (-b_n + mu |b_t|) / (a (1 + mu^2))
    a, bn, bt = 1e-6, -1.218436, -0.328941
    fn = (-bn + 0.1 * abs(bt)) / (a * (1 + 0.1**2))
    expected = torch.tensor([fn, 0.1 * fn * (1 if bt < 0 else -1)], dtype=torch.float64)
    torch.testing.assert_close(f[0, 2:], expected, rtol=1e-9, atol=0)
    # gradients pass through the equilibration
    A_ = A.clone().requires_grad_()
    b_ = b.clone().requires_grad_()
    solve_cone_qp(A_, b_, mu, 2, settings=settings).sum().backward()
    assert torch.isfinite(A_.grad).all() and torch.isfinite(b_.grad).all()


@pytest.mark.parametrize("backend", ["torch", "warp"])
@pytest.mark.parametrize("d", [1, 2, 3])
def test_an_empty_batch_gives_empty_results(backend, d):
    """Zero problems: ``(0, C)`` impulses and an empty status on both backends (the
    reference solver raised an UnboundLocalError), and a backward pass through them."""
    if backend == "warp":
        pytest.importorskip("warp")
    K = 2
    A = torch.eye(K * d, dtype=torch.float64).expand(0, K * d, K * d).requires_grad_()
    b = torch.zeros(0, K * d, dtype=torch.float64, requires_grad=True)
    mu = torch.zeros(0, K, dtype=torch.float64)
    settings = SolverSettings(backend=backend)
    f, status = solve_cone_qp(A, b, mu, d, return_status=True, settings=settings)
    assert f.shape == (0, K * d) and f.dtype == torch.float64
    assert status.converged.shape == status.unbounded.shape == status.residual.shape == (0,)
    assert status.all_converged
    assert solve_cone_qp(A, b, mu, d, settings=settings).shape == (0, K * d)
    f.sum().backward()
    assert b.grad.shape == (0, K * d)


@pytest.mark.parametrize("backend", ["torch", "warp"])
def test_an_integral_d_of_another_type_is_the_same_d(backend):
    """A 0-d tensor ``d`` compared equal to 2 and reached the fused solver as a tensor:
    memory corruption (a double free) or zero impulses. Integral values are read as
    ints (``numpy.int64`` too)."""
    import numpy as np

    from diffcontact.contact import SolverSettings, two_phase_impulse

    if backend == "warp":
        pytest.importorskip("warp")
    settings = SolverSettings(backend=backend)
    A, b, mu, _ = random_problems(8, 3, 2, seed=4, lower_frac=0.0)
    want = solve_cone_qp(A, b, mu, 2, settings=settings)
    for d in (torch.tensor(2), np.int64(2)):
        assert torch.equal(solve_cone_qp(A, b, mu, d, settings=settings), want)
    # a point mass falling on the ground at (1, -2) leaves at (1, 1) with e = 0.5
    J = torch.tensor([[[0.0, 1.0], [1.0, 0.0]]], dtype=F64)
    out = two_phase_impulse(
        J, torch.eye(2, dtype=F64)[None], torch.tensor([[1.0, -2.0]], dtype=F64),
        torch.zeros(1, 1, dtype=F64), torch.full((1, 1), 0.5, dtype=F64),
        torch.ones(1, 1, dtype=torch.bool), torch.tensor(2), settings=settings,
    )  # fmt: skip
    torch.testing.assert_close(out.v_plus, torch.tensor([[1.0, 1.0]], dtype=F64))


@pytest.mark.parametrize("backend", ["torch", "warp"])
def test_second_derivatives_through_the_solver_are_a_clear_error(backend):
    """The implicit backward pass is first order. Under create_graph autograd built a graph
    around it without the solver's curvature: Hessians through a simulation came back
    wrong (BP5: d2L/dmu2 40.5 against -9.3 by finite differences; the Warp backend's not
    even symmetric), silently."""
    if backend == "warp":
        pytest.importorskip("warp")
    settings = SolverSettings(backend=backend)
    A, b, mu, _ = random_problems(4, 2, 2, seed=5)
    b = b.requires_grad_()
    f = solve_cone_qp(A, b, mu, 2, settings=settings)
    (g,) = torch.autograd.grad(f.square().sum(), b)
    f = solve_cone_qp(A, b, mu, 2, settings=settings)
    # the first derivative under create_graph is the same; the second is refused
    (g_graph,) = torch.autograd.grad(f.square().sum(), b, create_graph=True)
    assert torch.equal(g_graph.detach(), g)
    with pytest.raises(RuntimeError, match="second derivatives through the contact solver"):
        torch.autograd.grad(g_graph.sum(), b)
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(3, seed=0)
    params = system.parameters()

    def loss(theta):
        p = params.replace(mu=theta[0], cor=theta[1])
        traj = system.simulate(z0, 30, params=p, progress=False, solver_settings=settings)
        return traj[:, -1].square().sum()

    with pytest.raises(RuntimeError, match="second derivatives through the contact solver"):
        torch.autograd.functional.hessian(loss, torch.tensor([0.35, 0.55], dtype=F64))


def test_torch_func_grad_through_the_torch_backend_matches_autograd():
    """torch.func.grad builds a graph around every backward pass (create_graph): the
    first derivative must still come out, only a second one is refused."""
    settings = SolverSettings(backend="torch")
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(2, seed=0)
    params = system.parameters()

    def final(mu):
        p = params.replace(mu=mu)
        return system.simulate(z0, 30, params=p, progress=False, solver_settings=settings)[
            :, -1
        ].sum()

    mu = torch.tensor(0.3, dtype=F64, requires_grad=True)
    (want,) = torch.autograd.grad(final(mu), mu)
    assert want != 0
    torch.testing.assert_close(torch.func.grad(final)(mu.detach()), want, rtol=0, atol=0)


def test_torch_func_transforms_use_the_torch_backend_by_default():
    """With the default backend ("auto": Warp where installed) torch.func.grad through a
    rollout failed with torch's generic setup_context error; inside a transform "auto"
    is the torch solver now, and Warp asked for there is refused by name."""
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(2, seed=0)

    def final(z, settings=None):
        traj = system.simulate(z, 20, progress=False, solver_settings=settings)
        return traj[:, -1, 0].sum()

    z = z0.clone().requires_grad_(True)
    (want,) = torch.autograd.grad(final(z), z)
    torch.testing.assert_close(torch.func.grad(final)(z0), want, rtol=0, atol=1e-12)
    rope = dc.load_system("Rope")  # the projection's Warp J J^T (sparse_gram) falls back too
    y0 = rope.sample_initial_conditions(1, seed=0)
    assert torch.isfinite(torch.func.grad(lambda y: rope.simulate(y, 3)[:, -1, 0].sum())(y0)).all()
    if fused.warp_installed():
        warp = SolverSettings(backend="warp")
        with pytest.raises(ValueError, match=r"Warp solver does not support torch\.func"):
            torch.func.grad(lambda z: final(z, warp))(z0)


def test_public_impulse_functions_check_restitution_and_take_empty_batches():
    """cor = 1.5 had sent a ball away faster than it came, silently; a batch of 0 states
    failed in a reshape (two_phase_impulse, the exact Coulomb model)."""
    from diffcontact.contact import two_phase_impulse
    from diffcontact.contact.coulomb import coulomb_two_phase_impulse
    from diffcontact.contact.lcp import lcp_impulse

    J = torch.tensor([[[0.0, 1.0], [1.0, 0.0]]], dtype=F64)
    M = torch.eye(2, dtype=F64)[None]
    v = torch.tensor([[1.0, -2.0]], dtype=F64)
    mu = torch.zeros(1, 1, dtype=F64)
    active = torch.ones(1, 1, dtype=torch.bool)
    for fn in (two_phase_impulse, lcp_impulse, coulomb_two_phase_impulse):
        with pytest.raises(ValueError, match=r"cor \(e_P\) must lie in \[0, 1\]"):
            fn(J, M, v, mu, torch.full((1, 1), 1.5, dtype=F64), active, 2)
        cor = torch.full((0, 1), 0.5, dtype=F64)
        out = fn(J[:0], M[:0], v[:0], mu[:0], cor, active[:0], 2)
        assert out.v_plus.shape == (0, 2) and out.f_c.shape == (0, 2)


def test_solver_settings_are_checked_where_given():
    for dtype in (torch.int32, "float64", torch.complex128):
        with pytest.raises(ValueError, match=r"compute_dtype must be a floating torch\.dtype"):
            SolverSettings(compute_dtype=dtype)
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(2, seed=0)
    for bad in ({"backend": "torch"}, {}):  # ({} had been taken for the defaults)
        with pytest.raises(ValueError, match="solver_settings must be a SolverSettings, got"):
            system.simulate(z0, 3, solver_settings=bad)


@pytest.mark.parametrize("model", ["LCP", "Coulomb"])
def test_second_derivatives_through_the_other_models_are_a_clear_error(model):
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(3, seed=0)
    params = system.parameters()

    def loss(theta):
        p = params.replace(mu=theta[0], cor=theta[1])
        return (
            system.simulate(z0, 30, params=p, contact_model=model, progress=False)[:, -1]
            .square()
            .sum()
        )

    with pytest.raises(RuntimeError, match="second derivatives through the contact solver"):
        torch.autograd.functional.hessian(loss, torch.tensor([0.35, 0.55], dtype=F64))
